"""What each physical term of the forward model is worth: single-star fits (prints tables).

    python benchmarks/fidelity.py [--real DIR] [--files GLOB] [--filters F480M,...]
                                  [--no-sim] [--no-real] [--rows before,siaf,...]

A single star is fitted alone (one calibrator exposure: position, flux, wavefront, latent
visibilities; the Levenberg-Marquardt solver of ``amigo fit``), once per model setting,
each row adding one physical term (issue 21):

=========  ==================================================================================
row        model
=========  ==================================================================================
before     the old detector geometry (rotation +0.561 deg, anisotropy 1.00765, no skew, as
           copied from the research code) frozen; jitter frozen at 21.4 mas
siaf       the SIAF-derived geometry (docs/geometry.md) frozen; jitter frozen
geometry   the geometry fitted (prior centred on the SIAF value); jitter frozen
jitter     the geometry and the exposure's jitter fitted
ipc        as ``jitter``, with the detector's inter-pixel capacitance (5x5 kernel) on the
           pixel image
band       as ``ipc``, with the band-shape correction (the taper of ``LinearSpectrum``)
           fitted: what ``amigo fit`` does with level-2 images
bandpass   as ``band``, with the physical band (filter x detector QE, flat photon
           spectrum: :func:`amigo.model.bandpass.effective_bins`) instead of the filter alone
=========  ==================================================================================

Data: (1) real COM 1093 calibrator files (level 2, default the HD 37093 visit, obs 15,
three filters); 1/f noise there was already treated by the STScI pipeline's reference
pixels, so it has no row here (see benchmarks/one_over_f.py for raw ramps); (2) the
project's own simulator at simulation fidelity (:class:`OpticalModelIllumination`:
512-pixel pupil, 15 wavelengths, the SIAF geometry, 18 mas jitter, the filter curve
alone, no IPC: its level-2 images carry no read-out effects) with the noise of the real
file of that filter. For each fit: the pixel z-score standard deviation and the
fitted geometry. Several minutes per filter on a 2-core CPU. Not a test: nothing is
asserted.
"""

from __future__ import annotations

import argparse
import glob
import os
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from amigo import niriss
from amigo.fitting.filter_fit import FilterFit, FitConfig, FitExposure
from amigo.fitting.newton import NewtonConfig
from amigo.io.jwst import read_exposure
from amigo.likelihood.pixels import ImageData
from amigo.model.bandpass import effective_bins
from amigo.model.basis import load_basis
from amigo.model.detector.linear import LinearDetector, bin_pixels
from amigo.model.image import FilterSetup, Instrument

ROWS = ("before", "siaf", "geometry", "jitter", "ipc", "band", "bandpass")
#: Prior widths that freeze a parameter at its starting value.
FROZEN = 1e-7
DEFAULT_REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "jwst" / "com1093"
SIM_JITTER_MAS = 18.0


def _instrument(row: str) -> Instrument:
    """The nominal instrument with the detector of ``row`` (see the module notes)."""
    ipc = ROWS.index(row) >= ROWS.index("ipc")
    if row == "before":
        detector = LinearDetector.create(
            ipc=False, rotation_deg=0.561, anisotropy=1.00765, skew_deg=0.0, scale=1.0
        )
    else:
        detector = LinearDetector.create(ipc=ipc)
    return eqx.tree_at(lambda i: i.detector, Instrument.nominal(), detector)


def _config(row: str) -> FitConfig:
    """Freeze what ``row`` does not yet fit (priors of negligible width)."""
    order = ROWS.index(row)
    default = NewtonConfig()
    newton = NewtonConfig(
        geometry_prior_sigma=default.geometry_prior_sigma
        if order >= ROWS.index("geometry")
        else (FROZEN,) * 4,
        jitter_prior_mas=None if order >= ROWS.index("jitter") else FROZEN,
        band_taper_prior=default.band_taper_prior if order >= ROWS.index("band") else FROZEN,
    )
    return FitConfig(newton=newton)


def fit_single_star(image: ImageData, filter_name: str, row: str, basis) -> dict:
    """One row's single-star fit: z-score std, fitted geometry, jitter, seconds."""
    instrument = _instrument(row)
    bins = effective_bins(filter_name, instrument.n_wavelengths) if row == "bandpass" else None
    setup = FilterSetup.create(filter_name, instrument, basis, bins=bins)
    fit = FilterFit(instrument, setup, [FitExposure("star", "calibrator", "STAR", image)])
    start = time.perf_counter()
    result = fit.fit(_config(row))
    seconds = time.perf_counter() - start
    model = np.asarray(fit.models(result.params)[0], np.float64)
    z = image.zscores(model)
    geometry = np.asarray(result.params.optics.geometry, np.float64)
    return {
        "z_std": float(np.std(z)),
        "chi2_n": float(np.mean(z**2)),
        "geometry": geometry,
        "jitter_mas": abs(float(result.params.exposures.jitter_mas[0])),
        "taper": float(result.params.optics.band_taper_per_um2),
        "converged": bool(result.converged),
        "seconds": seconds,
    }


def simulated_image(filter_name: str, like: ImageData, seed: int = 0) -> ImageData:
    """The project's simulator's point source with the flux and noise of a real file."""
    from amigo.simulation.optics_illumination import OpticalModelIllumination
    from amigo.simulation.scene import DetectorScene, DetectorSource
    from amigo.simulation.state import InstrumentState

    state = dataclasses.replace(InstrumentState.perfect(), jitter_mas=SIM_JITTER_MAS)
    k = 3
    centre = 0.5 * (niriss.SUBARRAY_SIZE - 1)
    scene = DetectorScene((DetectorSource(centre + 0.3, centre - 0.2, 1.0),))
    rate = OpticalModelIllumination().render(scene, filter_name, state, k)
    unit = np.asarray(bin_pixels(jnp.asarray(rate), k), np.float64)
    flux = float(np.sum(np.where(like.mask, like.data, 0.0)) / np.sum(unit[like.mask]))
    truth = flux * unit
    # The real file's noise as a function of its signal: read floor + photon term.
    error = np.asarray(like.error, np.float64)
    ok = like.mask & (like.data > 0)
    slope = np.polyfit(like.data[ok], error[ok] ** 2, 1)
    variance = np.clip(slope[0] * truth + slope[1], np.min(error[ok] ** 2), None)
    sigma = np.sqrt(variance)
    noisy = truth + sigma * np.random.default_rng(seed).normal(size=truth.shape)
    return ImageData(noisy, sigma, like.mask.copy())


def _row_text(name: str, filter_name: str, row: str, r: dict) -> str:
    g = r["geometry"]
    flag = "" if r["converged"] else " (not converged)"
    return (
        f"| {name} | {filter_name} | {row} | {r['z_std']:.3f} | {g[0]:+.4f} | {g[1]:.5f} | "
        f"{g[2]:+.4f} | {g[3]:.5f} | {r['jitter_mas']:.1f} | {r['taper']:+.1f} | "
        f"{r['seconds']:.0f}{flag} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", type=Path, default=DEFAULT_REAL, help="folder of _cal files")
    parser.add_argument("--files", default="jw01093015001_*_cal.fits", help="glob in --real")
    parser.add_argument("--filters", default="F480M,F430M,F380M")
    parser.add_argument("--rows", default=",".join(ROWS))
    parser.add_argument("--no-sim", action="store_true")
    parser.add_argument("--no-real", action="store_true")
    args = parser.parse_args()
    rows = [r for r in args.rows.split(",") if r]
    filters = [f for f in args.filters.split(",") if f]
    files = sorted(glob.glob(str(args.real / args.files)))
    if not files:
        raise SystemExit(f"no files match {args.real / args.files}")
    print(
        "| data | filter | row | z std | rotation (deg) | anisotropy | skew (deg) | scale | "
        "jitter (mas) | taper (um^-2) | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for path in files:
        exposure = read_exposure(Path(path))
        filter_name = exposure.meta.filter
        if filter_name not in filters:
            continue
        image = ImageData.from_exposure(exposure)
        # One basis per filter, from the nominal instrument, shared by every row.
        basis, _ = load_basis(Instrument.nominal(), filter_name)
        datasets = []
        if not args.no_real:
            datasets.append((f"{exposure.meta.target} {Path(path).name[:13]}", image))
        if not args.no_sim:
            datasets.append(("amigo simulator", simulated_image(filter_name, image)))
        for name, data in datasets:
            for row in rows:
                result = fit_single_star(data, filter_name, row, basis)
                print(_row_text(name, filter_name, row, result), flush=True)


if __name__ == "__main__":
    main()
