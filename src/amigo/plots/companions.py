"""Figures of ``amigo detect`` (matplotlib, Agg backend; written atomically).

* ``detection_maps.png``: per-filter signed significance and the joint significance of
  each search iteration; east is to the left, the masked inner working angle is grey, the
  companions already in the search's background scene are circled and the companion the
  search found is crossed.
* ``corner_<id>.png``: posterior of each companion (separation, position angle, delta-mag
  per filter) with a small corner plotter written here.
* ``contrast_limits.png``: Ruffio (2018) curves with their azimuthal spread, Absil-style
  curves, the photon rule of thumb and the companions.
* ``posterior_predictive.png``: data against model for amplitude- and phase-type
  observables, with normalised residuals (errors times sigma_scale).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import jax
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from amigo.companions.limits import COMBINED, lambda_over_d_mas
from amigo.companions.observables import KIND_NAMES, predicted_scenes, program_view
from amigo.companions.search import DetectionResult
from amigo.io.atomic import atomic_path
from amigo.niriss import PUPIL_DIAMETER_M

FILTER_COLOURS = {
    "F380M": "tab:blue",
    "F430M": "tab:green",
    "F480M": "tab:red",
    "F277W": "tab:purple",
    COMBINED: "k",
}


def _colour(name: str, index: int) -> str:
    return FILTER_COLOURS.get(name, f"C{index % 10}")


def _save(fig, path: str | os.PathLike[str], tight: bool = True) -> Path:
    """Write ``fig`` as PNG atomically and close it. ``tight``: crop to the drawn
    artists (a second measuring pass over every label); figures laid out by a layout
    engine or fixed margins do without it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight" if tight else None)
    plt.close(fig)
    return Path(path)


def _map_panel(ax, grid, values, iwa, title, cmap, vmin, vmax, label):
    extent = [
        grid.x_mas[0] - grid.step_mas / 2,
        grid.x_mas[-1] + grid.step_mas / 2,
        grid.y_mas[0] - grid.step_mas / 2,
        grid.y_mas[-1] + grid.step_mas / 2,
    ]
    shown = np.where(grid.radius_mas <= grid.rmax_mas, values, np.nan)
    image = ax.imshow(
        shown,
        origin="lower",
        extent=extent,
        cmap=cmap,
        vmin=vmin,
        vmax=vmax,
        interpolation="nearest",
    )
    ax.add_patch(plt.Circle((0, 0), iwa, color="0.6", zorder=3))
    ax.set_xlim(extent[1], extent[0])  # east (positive dRA) to the left
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("dRA (mas, east left)")
    ax.set_ylabel("dDec (mas)")
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal")
    plt.colorbar(image, ax=ax, fraction=0.046, pad=0.03, label=label)


def plot_detection_maps(
    result: DetectionResult, path: str | os.PathLike[str], max_rows: int = 4
) -> Path:
    maps = result.detection_maps[:max_rows]
    n_cols = len(result.dataset.filters) + (1 if len(result.dataset.filters) > 1 else 0)
    fig, axes = plt.subplots(
        len(maps),
        n_cols,
        figsize=(4.4 * n_cols, 4.0 * len(maps)),
        squeeze=False,
        layout="constrained",
    )
    found = [c.estimate for c in result.companions]
    for row, gr in enumerate(maps):
        panels = [
            (m.significance, f"{m.filter_name}: signed significance", m.iwa_mas) for m in gr.maps
        ]
        if n_cols > len(gr.maps):
            panels.append((gr.joint_significance, "joint significance", gr.iwa_mas))
        for col, (values, title, iwa) in enumerate(panels):
            ax = axes[row, col]
            inside = values[gr.grid.valid(iwa)]
            top = max(float(np.nanmax(np.abs(inside))) if inside.size else 1.0, 1.0)
            signed = "joint" not in title
            _map_panel(
                ax,
                gr.grid,
                values,
                iwa,
                f"search {row + 1}, {title}",
                "RdBu_r" if signed else "magma",
                -top if signed else 0.0,
                top,
                "sigma",
            )
            # Circles: companions in this search's background; cross: the one it found.
            for k, e in enumerate(found[: row + 1]):
                style = ("o", 12) if k < row else ("x", 9)
                ax.plot(
                    e.dra_mas,
                    e.ddec_mas,
                    style[0],
                    mfc="none",
                    mec="lime",
                    color="lime",
                    ms=style[1],
                    mew=1.5,
                )
                ax.annotate(
                    str(k + 1),
                    (e.dra_mas, e.ddec_mas),
                    color="lime",
                    fontsize=8,
                    xytext=(6, 6),
                    textcoords="offset points",
                )
    fig.suptitle(
        f"Detection maps (threshold {result.settings.threshold_sigma:g} sigma); "
        "grey: inner working angle",
        fontsize=10,
    )
    # Cropped tight: the title is wider than a one-filter figure.
    return _save(fig, path)


def corner(
    samples: np.ndarray, labels: list[str], truths: list[float] | None = None, bins: int = 30
) -> Figure:
    """A minimal corner plot: 1-D histograms on the diagonal, 2-D histograms below."""
    n = samples.shape[1]
    fig, axes = plt.subplots(n, n, figsize=(1.9 * n + 1, 1.9 * n + 1), squeeze=False)
    for i in range(n):
        for j in range(n):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(samples[:, i], bins=bins, histtype="step", color="k")
                lo, mid, hi = np.percentile(samples[:, i], [15.865, 50, 84.135])
                for v in (lo, mid, hi):
                    ax.axvline(v, color="k", ls="--" if v != mid else "-", lw=0.8)
                ax.set_title(f"{labels[i]} = {mid:.4g} ± {0.5 * (hi - lo):.2g}", fontsize=7)
                ax.set_yticks([])
            else:
                ax.hist2d(samples[:, j], samples[:, i], bins=bins, cmap="Greys")
            if truths is not None:
                ax.axvline(truths[j], color="tab:orange", lw=0.8)
                if i != j:
                    ax.axhline(truths[i], color="tab:orange", lw=0.8)
            if i == n - 1:
                ax.set_xlabel(labels[j], fontsize=8)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(labels[i], fontsize=8)
            elif j > 0:
                ax.set_yticklabels([])
            ax.tick_params(labelsize=6)
    fig.subplots_adjust(wspace=0.05, hspace=0.05)
    return fig


def plot_corners(result: DetectionResult, out_dir: str | os.PathLike[str]) -> list[Path]:
    """One corner plot per companion from the joint posterior (nothing without HMC)."""
    if result.posterior is None:
        return []
    from amigo.orientation import separation_pa

    s = result.posterior.samples
    paths = []
    for c in result.companions:
        k = c.id - 1
        sep, pa = separation_pa(s["dra"][:, k], s["ddec"][:, k])
        centre = c.estimate.pa_deg
        pa = centre + (pa - centre + 180.0) % 360.0 - 180.0
        columns = [sep, pa] + [
            -2.5 * s["log10c"][:, k, f] for f in range(len(result.dataset.filters))
        ]
        labels = ["sep (mas)", "PA (deg)"] + [f"dmag {f}" for f in result.dataset.filters]
        fig = corner(np.column_stack(columns), labels)
        fig.suptitle(f"companion {c.id}: joint posterior (NUTS)", fontsize=10)
        paths.append(_save(fig, Path(out_dir) / f"corner_{c.id}.png"))
    return paths


def plot_contrast_limits(result: DetectionResult, path: str | os.PathLike[str]) -> Path:
    # Fixed margins (room for the lambda/D axis and the title above, the legend below:
    # inside the axes it would hide the curves or the companions), not a tight crop.
    fig, ax = plt.subplots(figsize=(7, 6.0))
    fig.subplots_adjust(left=0.1, right=0.97, bottom=0.3, top=0.87)
    for i, curve in enumerate(result.limits):
        colour = _colour(curve.filter_name, i)
        ax.plot(
            curve.sep_mas,
            curve.ruffio_dmag,
            color=colour,
            label=f"{curve.filter_name} Ruffio {curve.n_sigma:g}σ",
        )
        ax.fill_between(
            curve.sep_mas,
            curve.ruffio_dmag - curve.ruffio_dmag_std,
            curve.ruffio_dmag + curve.ruffio_dmag_std,
            color=colour,
            alpha=0.2,
        )
        ax.plot(
            curve.sep_mas,
            curve.absil_dmag,
            color=colour,
            ls="--",
            lw=1,
            # The test's degrees of freedom: the signal subspace's k of the N observables.
            label=f"{curve.filter_name} Absil {curve.n_sigma:g}σ"
            + (f" ({curve.absil_dof} of {curve.n_obs} dof)" if curve.absil_dof else ""),
        )
        if curve.photon_limit_dmag is not None:
            ax.axhline(
                curve.photon_limit_dmag,
                color=colour,
                ls=":",
                lw=1,
                label=f"{curve.filter_name} photon rule √(100/N)",
            )
    for c in result.companions:
        for i, f in enumerate(result.dataset.filters):
            ax.errorbar(
                c.estimate.sep_mas,
                c.estimate.dmag[f],
                yerr=c.estimate.dmag_err[f],
                fmt="*",
                color=_colour(f, i),
                ms=10,
                mec="k",
            )
    ax.invert_yaxis()
    ax.set_xlabel("separation (mas)")
    # lambda/D of the mean wavelength of all the curves (the combined one's).
    waves = [c.wavelength_m for c in result.limits if np.isfinite(c.wavelength_m)]
    if waves:
        wave = float(np.mean(waves))
        mas_per_unit = lambda_over_d_mas(wave)

        # Any: matplotlib passes arrays (its stub says ArrayLike, which has no arithmetic).
        def to_units(x: Any) -> Any:
            return x / mas_per_unit

        def to_mas(x: Any) -> Any:
            return x * mas_per_unit

        top = ax.secondary_xaxis("top", functions=(to_units, to_mas))
        top.set_xlabel(f"separation (λ/D at {wave * 1e6:.2f} µm, D = {PUPIL_DIAMETER_M:.2f} m)")
    ax.set_ylabel("contrast limit (delta mag)")
    ax.set_title("Contrast limits on the companion-subtracted data", fontsize=10)
    ax.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.14))
    ax.grid(alpha=0.3)
    return _save(fig, path, tight=False)


def plot_posterior_predictive(
    result: DetectionResult, path: str | os.PathLike[str], n_draws: int = 50
) -> Path:
    """Data vs model (posterior median, with the spread of posterior draws) and residuals."""
    ds = result.dataset
    diameter = result.settings.primary_diameter_mas
    if result.companions:
        if result.posterior is not None:
            s = result.posterior.samples
            median = (np.median(s["dra"], 0), np.median(s["ddec"], 0), np.median(s["log10c"], 0))
            rng = np.random.default_rng(0)
            draws = rng.choice(
                s["dra"].shape[0], size=min(n_draws, s["dra"].shape[0]), replace=False
            )
            params = [(s["dra"][d], s["ddec"][d], s["log10c"][d]) for d in draws]
        else:
            assert result.fit is not None  # a result with companions has their fit
            median = (
                result.fit.offsets_mas[:, 0],
                result.fit.offsets_mas[:, 1],
                result.fit.log10_contrasts,
            )
            params = []
    else:
        median = (np.zeros(0), np.zeros(0), np.zeros((0, ds.n_filters)))
        params = []

    # On the padded blocks (programs shared with other targets), back to each's rows.
    view = program_view(ds)

    def predict(scenes):
        """Per block, (n_scenes, n_obs) model observables of ``scenes``, a list of
        ``(dra, ddec, log10c)``."""
        offsets = np.stack([np.column_stack([dra, ddec]) for dra, ddec, _ in scenes])
        log10c = np.stack([np.asarray(c, float) for _, _, c in scenes])  # (n, n_comp, n_f)
        return [
            np.asarray(
                predicted_scenes(b, offsets, 10.0 ** log10c[:, :, ds.filter_index(i)], diameter)
            )[:, rows]
            for i, (b, rows) in enumerate(zip(view.dataset.blocks, view.rows, strict=True))
        ]

    best = [rows[0] for rows in predict([median])]
    spread = [np.std(rows, axis=0) for rows in predict(params)] if params else None
    scales = ds.scale_vectors(result.group_scales)
    kinds_present = sorted({k for b in ds.blocks for k in b.kinds})
    fig, axes = plt.subplots(
        2,
        len(kinds_present),
        figsize=(5.5 * len(kinds_present), 6),
        squeeze=False,
        gridspec_kw={"height_ratios": [3, 1]},
        sharex="col",
    )
    # Fixed margins, not a tight crop: 1.1 inch left of the first column for its tick
    # labels and label (the widest seen, -0.0005, fit), 1 inch between the columns.
    width_in = 5.5 * len(kinds_present)
    fig.subplots_adjust(
        left=1.1 / width_in, right=1 - 0.2 / width_in, bottom=0.09, top=0.94, hspace=0.08,
        wspace=0.25,
    )  # fmt: skip
    for col, kind in enumerate(kinds_present):
        top, bottom = axes[0, col], axes[1, col]
        for i, b in enumerate(ds.blocks):
            rows = np.asarray(b.kinds) == kind
            f = ds.filter_index(i)
            data = np.asarray(b.observed())[rows]
            err = (np.asarray(b.errors) * np.asarray(scales[i]))[rows]
            model = best[i][rows]
            model_err = spread[i][rows] if spread is not None else None
            name = b.filter_name
            scale = result.sigma_scale_by_kind[name][KIND_NAMES[kind]]
            colour = _colour(name, f)
            top.errorbar(
                model,
                data,
                yerr=err,
                xerr=model_err,
                fmt=".",
                color=colour,
                ms=3,
                lw=0.6,
                label=f"{name} (σ_scale {scale:.2f})",
            )
            bottom.plot(model, (data - model) / err, ".", color=colour, ms=3)
        lims = np.array(top.get_xlim())
        top.plot(lims, lims, "k--", lw=0.8)
        top.set_ylabel(f"data ({KIND_NAMES[kind]} observables)")
        top.set_title(f"Posterior predictive check: {KIND_NAMES[kind]}", fontsize=10)
        top.legend(fontsize=7)
        bottom.axhline(0, color="k", lw=0.8)
        bottom.set_xlabel("model")
        bottom.set_ylabel("residual / σ")
    return _save(fig, path, tight=False)


def write_all(result: DetectionResult, out_dir: str | os.PathLike[str]) -> list[Path]:
    """Write every figure into ``out_dir``; returns the paths."""
    out = Path(out_dir)
    with jax.enable_x64(True):  # model predictions in float64, as in the fits
        paths = [
            plot_detection_maps(result, out / "detection_maps.png"),
            plot_contrast_limits(result, out / "contrast_limits.png"),
            plot_posterior_predictive(result, out / "posterior_predictive.png"),
        ]
        paths.extend(plot_corners(result, out))
    return paths


__all__ = [
    "corner",
    "plot_contrast_limits",
    "plot_corners",
    "plot_detection_maps",
    "plot_posterior_predictive",
    "write_all",
]
