"""Diagnostic figures of a fit: data, model, normalised residuals, z-score histogram."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import NullLocator

from amigo.plots.optics import save

if TYPE_CHECKING:
    from amigo.likelihood.pixels import ImageData
    from amigo.observables.extract import ExposureStats


def exposure_figure(image: ImageData, model: np.ndarray, stats: ExposureStats) -> Figure:
    """Four panels for one exposure.

    Parameters
    ----------
    image
        :class:`amigo.likelihood.pixels.ImageData` (data, error, mask).
    model
        (80, 80) model image, same unit as the data (DN/s).
    stats
        :class:`amigo.observables.extract.ExposureStats` (for the title).
    """
    fig = Figure(figsize=(16, 4.2))
    FigureCanvasAgg(fig)
    # Fixed panel positions (figure fractions), not a layout engine: a constrained
    # layout measured every tick label twice and cost ~1 s per figure, twice per fit.
    axes, colorbar_axes = _panels(fig)
    data = np.where(image.mask, image.data, np.nan)
    peak = np.nanmax(np.abs(data)) or 1.0
    stretch = dict(origin="lower", cmap="inferno", vmin=0.0, vmax=np.sqrt(peak))
    for ax, cax, values, title in zip(
        axes[:2], colorbar_axes[:2], (data, model), ("data", "model"), strict=True
    ):
        im = ax.imshow(np.sqrt(np.clip(values, 0, None)), **stretch)
        ax.set_title(f"{title} (sqrt, DN/s)")
        fig.colorbar(im, cax=cax)
    z = np.where(image.mask, (image.data - model) / image.error, np.nan)
    lim = max(3.0, float(np.nanpercentile(np.abs(z), 99.5)))
    im = axes[2].imshow(z, origin="lower", cmap="RdBu_r", vmin=-lim, vmax=lim)
    axes[2].set_title("(data - model) / sigma")
    fig.colorbar(im, cax=colorbar_axes[2])
    values = z[np.isfinite(z)]
    bins = np.linspace(-max(5.0, lim), max(5.0, lim), 81)
    axes[3].hist(
        values,
        bins=bins.tolist(),
        density=True,
        histtype="stepfilled",  # one polygon, not 80 rectangles to draw
        color="tab:blue",
        alpha=0.7,
        label="pixels",
    )
    grid = np.linspace(bins[0], bins[-1], 400)
    axes[3].plot(grid, np.exp(-0.5 * grid**2) / np.sqrt(2 * np.pi), "k--", label="N(0, 1)")
    axes[3].set_yscale("log")
    # No minor ticks on the log axis: 8 per decade over 5 decades, each a Tick object with
    # two lines and two labels, were half the time of writing the figure.
    axes[3].yaxis.set_minor_locator(NullLocator())
    axes[3].set_ylim(1e-5, 1.0)
    axes[3].set_xlabel("z-score")
    axes[3].set_title(f"std {np.std(values):.3f}")
    axes[3].legend()
    fig.suptitle(
        f"{stats.name}  {stats.role} {stats.target} {stats.filter}:  "
        f"chi2/dof = {stats.chi2:.0f}/{stats.dof:.0f} = {stats.chi2 / stats.dof:.3f}",
        y=0.97,
    )
    return fig


def _panels(fig: Figure) -> tuple[list, list]:
    """Three square image panels, each with a colorbar on its right, and a histogram
    panel, in one row of a 16 x 4.2 inch figure."""
    bottom, height = 0.13, 0.7  # 2.9 inches: square images
    width = height * 4.2 / 16.0
    axes, colorbars = [], []
    for i in range(3):
        left = 0.035 + 0.24 * i
        axes.append(fig.add_axes((left, bottom, width, height)))
        colorbars.append(fig.add_axes((left + width + 0.006, bottom, 0.009, height)))
    axes.append(fig.add_axes((0.805, bottom, 0.185, height)))
    return axes, colorbars


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Write a figure as PNG atomically (creating the folder)."""
    return save(fig, path)
