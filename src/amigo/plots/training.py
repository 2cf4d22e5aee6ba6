"""The loss curve of a training run (``amigo train`` writes it beside the model)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

if TYPE_CHECKING:
    from amigo.training.data import History


def loss_curve_figure(history: History, title: str = "") -> Figure:
    """The calibration losses (per batch step and per epoch) and the validation loss (per
    epoch), chi2/2 per value, against the step; dashed lines where a stage begins.

    ``history`` is an :class:`amigo.training.data.History`.
    """
    fig = Figure(figsize=(7, 4.2))
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.12, 0.12, 0.85, 0.8))  # fixed margins: no layout engine to run
    if history.step:
        ax.plot(history.step, history.loss, ".", ms=3, color="0.6", label="calibration batch")
    if history.epoch_step:
        ax.plot(history.epoch_step, history.cal_loss, "-o", ms=3, label="calibration (epoch)")
        val = np.asarray(history.val_loss, float)
        if np.isfinite(val).any():
            ax.plot(history.epoch_step, val, "-s", ms=3, label="validation (epoch)")
    for k in np.nonzero(np.diff(np.asarray(history.stage)))[0]:
        ax.axvline(history.step[k + 1] - 0.5, color="0.8", lw=0.8, ls="--")
    values = np.asarray([*history.loss, *history.cal_loss, *history.val_loss], float)
    if np.isfinite(values).any() and np.all(values[np.isfinite(values)] > 0):
        ax.set_yscale("log")
    ax.set_xlabel("step (dashed: a new stage)")
    ax.set_ylabel("chi2 / 2 per value")
    ax.set_title(title or "training loss")
    if ax.get_legend_handles_labels()[0]:  # nothing to draw after zero steps
        ax.legend(frameon=False, fontsize=8)
    return fig
