"""Figures of the optical model: pupil, PSF (sqrt stretch), power spectrum with baselines.

Every function returns a :class:`matplotlib.figure.Figure` built on the Agg backend
(no display needed); :func:`save` writes one atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from amigo import niriss
from amigo.io.atomic import atomic_path

if TYPE_CHECKING:
    from amigo.model.optics.model import NRMOptics


def _figure(ncols: int = 1, size: float = 4.2) -> tuple[Figure, list]:
    fig = Figure(figsize=(size * ncols, size * 0.92), layout="constrained")
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, ncols, i + 1) for i in range(ncols)]
    return fig, axes


def pupil_figure(optics: NRMOptics) -> Figure:
    """Amplitude transmission and OPD (nm, inside the holes) of an :class:`NRMOptics`."""
    amplitude, opd_m = (np.asarray(a) for a in optics.pupil())
    x, y = np.asarray(optics.grid.x_m), np.asarray(optics.grid.y_m)
    extent = (x[0], x[-1], y[0], y[-1])
    fig, (ax_a, ax_o) = _figure(2)
    im = ax_a.imshow(amplitude, origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1)
    fig.colorbar(im, ax=ax_a, shrink=0.8, label="amplitude")
    for k, (cx, cy) in enumerate(np.asarray(niriss.HOLE_CENTRES_M)):
        ax_a.annotate(str(k), (cx, cy), color="tab:red", ha="center", va="center")
    opd_nm = np.where(amplitude > 0.5, opd_m * 1e9, np.nan)
    lim = np.nanmax(np.abs(opd_nm)) or 1.0
    im = ax_o.imshow(opd_nm, origin="lower", extent=extent, cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=ax_o, shrink=0.8, label="OPD (nm)")
    for ax, title in ((ax_a, "mask (pupil frame)"), (ax_o, "wavefront")):
        ax.set(xlabel="x (m)", ylabel="y (m)", title=title)
    return fig


def psf_figure(image: np.ndarray, pixel_scale_arcsec: float, title: str = "PSF") -> Figure:
    """An image (e.g. a 240x240 illuminance or an 80x80 detector image), sqrt stretch."""
    image = np.asarray(image)
    n, m = image.shape
    half = 0.5 * np.array([m, n]) * pixel_scale_arcsec
    fig, (ax,) = _figure(1)
    im = ax.imshow(
        np.sqrt(np.clip(image, 0, None)),
        origin="lower",
        cmap="inferno",
        extent=(-half[0], half[0], -half[1], half[1]),
    )
    fig.colorbar(im, ax=ax, shrink=0.8, label="sqrt(intensity)")
    ax.set(xlabel="x (arcsec)", ylabel="y (arcsec)", title=title)
    return fig


def power_spectrum(image: np.ndarray, pad: int = 2) -> np.ndarray:
    """|FFT|^2 of a zero-padded image, zero frequency at the centre (normalised to 1)."""
    image = np.asarray(image, dtype=float)
    n, m = image.shape
    big = np.zeros((pad * n, pad * m))
    big[:n, :m] = image
    p = np.abs(np.fft.fftshift(np.fft.fft2(big))) ** 2
    return p / p.max()


def power_spectrum_figure(
    image: np.ndarray,
    pixel_scale_arcsec: float,
    wavelength_m: float,
    pad: int = 2,
) -> Figure:
    """Power spectrum (log) in metres of baseline (``u = f lambda``), with the 21
    baselines of :func:`amigo.niriss.baselines_m` (and their mirrors) overlaid.
    """
    p = power_spectrum(image, pad)
    n, m = np.asarray(image).shape
    rad = pixel_scale_arcsec * np.pi / (180 * 3600)
    # Frequency pitch of the padded FFT, in metres of baseline.
    du, dv = wavelength_m / (pad * m * rad), wavelength_m / (pad * n * rad)
    extent = (-pad * m / 2 * du, (pad * m / 2 - 1) * du, -pad * n / 2 * dv, (pad * n / 2 - 1) * dv)
    fig, (ax,) = _figure(1, 4.8)
    ax.imshow(np.log10(p + 1e-12), origin="lower", extent=extent, cmap="viridis", vmin=-7, vmax=0)
    b = niriss.baselines_m()
    ax.scatter(b[:, 0], b[:, 1], s=60, facecolors="none", edgecolors="w", label="baselines")
    ax.scatter(-b[:, 0], -b[:, 1], s=60, facecolors="none", edgecolors="w", linestyles=":")
    lim = 7.0
    ax.set(
        xlim=(-lim, lim),
        ylim=(-lim, lim),
        xlabel="u (m)",
        ylabel="v (m)",
        title="log10 power spectrum",
    )
    ax.legend(loc="upper right", fontsize="small")
    return fig


def save(fig: Figure, path: str | Path, dpi: int = 110) -> Path:
    """Write a figure as PNG through a temporary name."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return path
