"""An independent simulator of NIRISS AMI level-2 images: poppy, pysiaf and synphot, no amigo.

    python benchmarks/independent_sim.py --out DIR [--filters F480M,F430M,F380M]
        [--template-dir DIR] [--effects] [--seed 0] [--teff 4500] [--jitter-mas 12]
        [--fit]

Why (issue 21): amigo's own simulator shares code and conventions with its model, so a fit
of it to the noise proves little. This script writes level-2 ``_cal.fits`` images of two
single stars (``INDEP-SCI`` and ``INDEP-CAL``) per filter from physics computed by
libraries amigo's model does not use, so that ``amigo fit`` on them measures what the
model gets wrong. Nothing here imports amigo.

Physics, term by term
---------------------
* Pupil: the seven hexagonal holes of the published NRM design (flat-to-flat 0.80 m,
  "flat-top" in the table's axes), placed in the telescope's V2/V3 frame on the primary
  as seen from the sky, each drawn by poppy's ``HexagonAperture`` (2 x 2 gray pixels on a
  1024-pixel grid of 1/150 m). A static wavefront error: Noll Zernikes 4-11 over the
  6.6 m circumscribed pupil (poppy's ``zernike_basis``), seeded, ~20 nm rms each.
* Optics: poppy's matrix Fourier transform of the pupil field, per wavelength, onto one
  fine grid of V2/V3 angle offsets (pitch ``FINE_MAS``), scaled absolutely by the
  Fraunhofer integral at the origin (``E(0) = sum(P exp(i phi)) pitch^2 / lambda``), so
  that the light falling outside the field is lost as on the sky (6 % of it in F480M).
* Spectrum: the filter's SVO transmission curve (the ``svo_filters`` package's VOTable,
  read with astropy.io.votable) times a blackbody of ``--teff`` in photons (synphot's
  ``BlackBody1D`` in PHOTLAM), integrated in ``N_WAVELENGTHS`` equal bins over the band
  where the filter passes > 1 % of its peak; each bin's wavelength is its photon-weighted
  mean. No detector QE (flat across these bands to a few per cent).
* Jitter: an isotropic Gaussian of ``--jitter-mas`` on the fine grid (scipy.ndimage).
* Geometry: every detector pixel is integrated over ``SUBSAMPLE`` x ``SUBSAMPLE`` points
  whose science-frame positions (1-based, as the SIAF counts them; array index + 1) are
  mapped to V2/V3 by pysiaf's full NIS_AMI1 polynomial (``sci_to_tel``); the fine PSF is
  interpolated there (cubic spline), relative to the star's own V2/V3, and weighted by
  each pixel's solid angle (the local Jacobian of the same map).
* Detector (``--effects``): a 3 x 3 inter-pixel capacitance kernel (0.6 % to each edge
  neighbour, 0.06 % to each corner), and 1/f stripes: a Gaussian process along each
  column (exponential kernel, ``STRIPE_TAU_DN_S`` and ``STRIPE_ELL_ROWS``), independent
  between columns, as the pipeline's ramp fit leaves them. Without ``--effects`` the
  images hold photon and read noise only.
* Noise: a level-2 image is the average of NINTS ramp slopes (NGROUPS, TGROUP from the
  template file; NFRAMES = 1). Its variance is the optimally weighted slope's
  (12 RN^2 / (ng^3 - ng) / tg^2 + 6 (ng^2 + 1) / (5 ng (ng^2 - 1)) rate / tg, in e-, per
  integration) over NINTS, with ``GAIN_E_PER_DN`` and ``READ_NOISE_E`` (a CDS-level
  read noise of the NIRISS detector). The data are drawn from a Gaussian of that
  variance; ERR is its square root, as the pipeline reports it from the true rate.

Files: the template's headers (a real COM 1093 ``_cal`` file of the same filter) with
TARGPROP/TARGNAME replaced, SCI (DN/s), ERR, DQ (the template's reference-row and
DO_NOT_USE flags only), VAR_POISSON and VAR_RNOISE; the star's flux is the template's
(its total count rate in the subarray). ``truth.json`` records every drawn value.

``--fit`` then runs, through the command line, ``amigo fit`` (INDEP-SCI against
INDEP-CAL, all filters) with the default model and with the nominal instrument
(``--model`` an instrument file written here), and ``amigo detect --no-hmc`` on each, and
prints a table per exposure (pixel z-score std, the fitted geometry and jitter, the
measured amplitude of the model's detector) and per run (DISCO error scale, the best
candidate, the 3-sigma Absil limits at 100 / 200 / 400 mas). The truth: two single stars.

The simulation takes 5-15 s per filter on a 2-core CPU (poppy's transforms); ``--fit``
4-5 minutes per model.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import subprocess
import sys
import time
from importlib import util as importlib_util
from pathlib import Path

import numpy as np
import poppy
import pysiaf
import synphot
from astropy import units as u
from astropy.io import fits, votable
from poppy.matrixDFT import matrix_dft
from scipy import ndimage

DEFAULT_TEMPLATES = Path(__file__).resolve().parents[2] / "shared" / "data" / "jwst" / "com1093"
#: One template file per filter: HD 37093, COM 1093 obs 15 (exposure numbers by filter).
TEMPLATE_NAMES = {
    "F480M": "jw01093015001_03102_00001_nis_cal.fits",
    "F430M": "jw01093015001_03103_00001_nis_cal.fits",
    "F380M": "jw01093015001_03104_00001_nis_cal.fits",
}

#: The NRM's as-designed hole centres on the primary (m), as published (the JWST
#: pipeline's ImPlaneIA heritage, "jwst_g7s6c"), columns (x, y) with ``x = -V2``,
#: ``y = +V3`` as seen from the sky. (A point inversion of the table, as some codes use,
#: gives the same intensity: the far field of a real pupil is centrosymmetric.)
PUBLISHED_HOLES_XY_M = np.array(
    [
        [0.00000, -2.64000],
        [-2.28631, 0.00000],
        [2.28631, -1.32000],
        [-2.28631, 1.32000],
        [-1.14315, 1.98000],
        [2.28631, 1.32000],
        [1.14315, 1.98000],
    ]
)
#: The same centres in the telescope frame, columns (V2, V3).
HOLE_CENTRES_V2V3_M = PUBLISHED_HOLES_XY_M * np.array([-1.0, 1.0])
HOLE_FLAT_TO_FLAT_M = 0.80
#: The circumscribed pupil over which the Zernike wavefront is defined (m).
ZERNIKE_DIAMETER_M = 6.603464

PUPIL_NPIX = 1024
PUPIL_PITCH_M = 1.0 / 150.0
PUPIL_SUBSAMPLE = 2
FINE_MAS = 8.0  # angle pitch of the fine PSF grid
FINE_NPIX = 801  # odd: the origin on the centre sample
N_WAVELENGTHS = 21
SUBSAMPLE = 5  # points per pixel per axis
GAIN_E_PER_DN = 1.61
READ_NOISE_E = 14.0
STRIPE_TAU_DN_S = 0.15
STRIPE_ELL_ROWS = 20.0
ZERNIKE_NM_RMS = 20.0
APERTURE = "NIS_AMI1"

MAS_TO_RAD = np.pi / 180.0 / 3600.0 / 1000.0


# ----------------------------------------------------------------------------------------
# Pupil and optics (poppy)
# ----------------------------------------------------------------------------------------


def pupil_amplitude() -> np.ndarray:
    """(PUPIL_NPIX, PUPIL_NPIX) gray-pixel transmission of the holes, rows along V3.

    Pixel centres at ``(k - (n - 1) / 2) * pitch`` on both axes; column index along V2.
    """
    n = PUPIL_NPIX
    patch = int(np.ceil(2.0 * HOLE_FLAT_TO_FLAT_M / np.sqrt(3.0) / PUPIL_PITCH_M)) + 4
    out = np.zeros((n, n))
    for v2, v3 in HOLE_CENTRES_V2V3_M:
        first = [round(c / PUPIL_PITCH_M + 0.5 * (n - 1) - 0.5 * (patch - 1)) for c in (v2, v3)]
        centre = [(k + 0.5 * (patch - 1) - 0.5 * (n - 1)) * PUPIL_PITCH_M for k in first]
        wave = poppy.Wavefront(
            wavelength=1e-6 * u.m,
            npix=patch * PUPIL_SUBSAMPLE,
            diam=patch * PUPIL_PITCH_M * u.m,
        )
        hole = poppy.HexagonAperture(
            flattoflat=HOLE_FLAT_TO_FLAT_M * u.m, shift_x=v2 - centre[0], shift_y=v3 - centre[1]
        )
        fine = np.asarray(hole.get_transmission(wave), dtype=float)
        gray = fine.reshape(patch, PUPIL_SUBSAMPLE, patch, PUPIL_SUBSAMPLE).mean(axis=(1, 3))
        out[first[1] : first[1] + patch, first[0] : first[0] + patch] += gray
    return out


def wavefront_m(coefficients_m: np.ndarray) -> np.ndarray:
    """(PUPIL_NPIX, PUPIL_NPIX) optical path difference (m): Noll Zernikes 4.. over the
    circumscribed pupil, by poppy's ``zernike_basis`` (unit rms over the disk)."""
    n_terms = 3 + len(coefficients_m)
    grid = (np.arange(PUPIL_NPIX) - 0.5 * (PUPIL_NPIX - 1)) * PUPIL_PITCH_M
    v2, v3 = np.meshgrid(grid, grid)
    radius = 0.5 * ZERNIKE_DIAMETER_M
    rho = np.hypot(v2, v3) / radius
    theta = np.arctan2(v3, v2)
    basis = poppy.zernike.zernike_basis(nterms=n_terms, rho=rho, theta=theta, outside=0.0)
    return np.tensordot(coefficients_m, basis[3:], axes=1)


def monochromatic_psf(amplitude: np.ndarray, opd_m: np.ndarray, wavelength_m: float) -> np.ndarray:
    """(FINE_NPIX, FINE_NPIX) intensity per steradian for unit incident photon flux
    (photons / m^2), rows along V3 angle offsets, on pitch ``FINE_MAS``.

    poppy's ``matrix_dft`` gives the field up to a constant; the constant is fixed by the
    Fraunhofer integral at the origin, ``E(0) = sum(P exp(i phi)) pitch^2 / lambda``.
    """
    field = amplitude * np.exp(2j * np.pi * opd_m / wavelength_m)
    grid_m = PUPIL_NPIX * PUPIL_PITCH_M
    fov_rad = FINE_NPIX * FINE_MAS * MAS_TO_RAD
    nlam_d = fov_rad / (wavelength_m / grid_m)
    out = matrix_dft(field, nlam_d, FINE_NPIX, centering="FFTSTYLE")
    origin = np.sum(field) * PUPIL_PITCH_M**2 / wavelength_m
    centre = FINE_NPIX // 2
    scale = origin / out[centre, centre]
    return np.abs(out * scale) ** 2


# ----------------------------------------------------------------------------------------
# Spectrum (synphot)
# ----------------------------------------------------------------------------------------


def filter_curve(filter_name: str) -> tuple[np.ndarray, np.ndarray]:
    """The SVO transmission of ``filter_name``: wavelengths (Angstrom) and throughput."""
    spec = importlib_util.find_spec("svo_filters")
    if spec is None or spec.origin is None:
        raise SystemExit("svo_filters is not installed")
    path = Path(spec.origin).parent / "data" / "filters" / f"NIRISS.{filter_name}"
    table = votable.parse_single_table(path).to_table()
    wave_a = np.asarray(table.columns[0], dtype=float)
    throughput = np.asarray(table.columns[1], dtype=float)
    order = np.argsort(wave_a)
    return wave_a[order], np.clip(throughput[order], 0.0, None)


def wavelength_bins(filter_name: str, teff_k: float) -> tuple[np.ndarray, np.ndarray]:
    """``N_WAVELENGTHS`` bin wavelengths (m) and photon fractions (sum 1) of a blackbody of
    ``teff_k`` seen through the filter (synphot)."""
    wave_a, throughput = filter_curve(filter_name)
    band = synphot.SpectralElement(
        synphot.Empirical1D, points=wave_a * u.AA, lookup_table=throughput
    )
    star = synphot.SourceSpectrum(synphot.BlackBody1D, temperature=teff_k * u.K)
    passing = wave_a[throughput > 0.01 * throughput.max()]
    edges = np.linspace(passing.min(), passing.max(), N_WAVELENGTHS + 1)
    counts, centres = [], []
    for lo, hi in itertools.pairwise(edges):
        w = np.linspace(lo, hi, 201)
        flux = (star(w * u.AA) * band(w * u.AA)).value  # photons / s / cm^2 / A
        counts.append(np.trapezoid(flux, w))
        centres.append(np.trapezoid(flux * w, w) / counts[-1])
    counts_arr = np.array(counts)
    return np.array(centres) * 1e-10, counts_arr / counts_arr.sum()


def polychromatic_psf(
    filter_name: str, teff_k: float, amplitude: np.ndarray, opd_m: np.ndarray, jitter_mas: float
) -> np.ndarray:
    """Photon-weighted PSF (per steradian, unit incident flux), blurred by the jitter."""
    wavelengths, weights = wavelength_bins(filter_name, teff_k)
    psf = sum(
        w * monochromatic_psf(amplitude, opd_m, lam)
        for lam, w in zip(wavelengths, weights, strict=True)
    )
    if jitter_mas > 0:
        psf = ndimage.gaussian_filter(psf, jitter_mas / FINE_MAS, mode="constant")
    return np.asarray(psf)


# ----------------------------------------------------------------------------------------
# Geometry (pysiaf) and pixel integration
# ----------------------------------------------------------------------------------------


def pixel_image(psf: np.ndarray, star_sci: tuple[float, float], size: int = 80) -> np.ndarray:
    """(size, size) photons per pixel for unit incident flux (photons / m^2): ``psf``
    integrated over each pixel through the SIAF's sci -> V2/V3 polynomial.

    ``star_sci``: the star's science-frame position (1-based pixels, SIAF convention).
    """
    aperture = pysiaf.Siaf("NIRISS")[APERTURE]
    star_v2, star_v3 = aperture.sci_to_tel(*star_sci)
    offsets = (np.arange(SUBSAMPLE) + 0.5) / SUBSAMPLE - 0.5
    index = np.arange(size)
    # Sub-sample positions (1-based science pixels), shape (size, size, k, k): [y, x, sy, sx].
    y = (index + 1.0)[:, None, None, None] + offsets[None, None, :, None]
    x = (index + 1.0)[None, :, None, None] + offsets[None, None, None, :]
    y, x = np.broadcast_arrays(y, x)
    v2, v3 = aperture.sci_to_tel(x.ravel(), y.ravel())
    # Solid angle of each sub-sample: the map's Jacobian determinant (central differences).
    h = 0.01
    v2x, v3x = aperture.sci_to_tel(x.ravel() + h, y.ravel())
    v2y, v3y = aperture.sci_to_tel(x.ravel(), y.ravel() + h)
    v2x0, v3x0 = aperture.sci_to_tel(x.ravel() - h, y.ravel())
    v2y0, v3y0 = aperture.sci_to_tel(x.ravel(), y.ravel() - h)
    det = ((v2x - v2x0) * (v3y - v3y0) - (v3x - v3x0) * (v2y - v2y0)) / (2 * h) ** 2
    area_sr = np.abs(det) * (1e3 * MAS_TO_RAD) ** 2 / SUBSAMPLE**2
    # Fine-grid coordinates: column along V2 offsets, row along V3 offsets.
    centre = FINE_NPIX // 2
    col = (v2 - star_v2) * 1e3 / FINE_MAS + centre
    row = (v3 - star_v3) * 1e3 / FINE_MAS + centre
    values = ndimage.map_coordinates(psf, [row, col], order=3, mode="constant", cval=0.0)
    return (values * area_sr).reshape(size, size, SUBSAMPLE, SUBSAMPLE).sum(axis=(2, 3))


# ----------------------------------------------------------------------------------------
# Detector and noise
# ----------------------------------------------------------------------------------------


def ipc(image: np.ndarray) -> np.ndarray:
    """A 3 x 3 inter-pixel capacitance kernel (conserves charge)."""
    edge, corner = 0.006, 0.0006
    kernel = np.array([[corner, edge, corner], [edge, 0.0, edge], [corner, edge, corner]])
    kernel[1, 1] = 1.0 - kernel.sum()
    return ndimage.convolve(image, kernel, mode="constant", cval=0.0)


def stripes(shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """(ny, nx) DN/s: per column a Gaussian process along y, ``tau^2 exp(-|dy| / ell)``."""
    ny, nx = shape
    rows = np.arange(ny)
    cov = STRIPE_TAU_DN_S**2 * np.exp(-np.abs(rows[:, None] - rows[None, :]) / STRIPE_ELL_ROWS)
    root = np.linalg.cholesky(cov + 1e-12 * np.eye(ny))
    return root @ rng.normal(size=(ny, nx))


def slope_variances(
    rate_dn_s: np.ndarray, ngroups: int, tgroup_s: float, nints: int
) -> tuple[np.ndarray, np.ndarray]:
    """Poisson and read-noise variances (DN/s)^2 of the NINTS-averaged slope."""
    ng, tg = ngroups, tgroup_s
    rate_e = np.clip(rate_dn_s, 0.0, None) * GAIN_E_PER_DN
    poisson_e = 6.0 * (ng**2 + 1) / (5.0 * ng * (ng**2 - 1)) * rate_e / tg
    read_e = 12.0 * READ_NOISE_E**2 / ((ng**3 - ng) * tg**2)
    scale = 1.0 / (nints * GAIN_E_PER_DN**2)
    return poisson_e * scale, np.full_like(rate_e, read_e * scale)


# ----------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------


def write_level2(
    path: Path,
    template: Path,
    targprop: str,
    var_poisson: np.ndarray,
    var_rnoise: np.ndarray,
    data: np.ndarray,
) -> None:
    """A ``_cal`` file with the template's headers, written atomically."""
    with fits.open(template) as hdul:
        primary = hdul[0].header.copy()
        sci_header = hdul["SCI"].header.copy()
        dq = np.asarray(hdul["DQ"].data).astype(np.uint32) & np.uint32(2**31 | 1)
    primary["TARGPROP"] = targprop
    primary["TARGNAME"] = targprop
    primary["HISTORY"] = "Simulated by amigo's benchmarks/independent_sim.py (poppy, pysiaf)."
    out = fits.HDUList(
        [
            fits.PrimaryHDU(header=primary),
            fits.ImageHDU(data.astype(np.float32), header=sci_header, name="SCI"),
            fits.ImageHDU(np.sqrt(var_poisson + var_rnoise).astype(np.float32), name="ERR"),
            fits.ImageHDU(dq, name="DQ"),
            fits.ImageHDU(var_poisson.astype(np.float32), name="VAR_POISSON"),
            fits.ImageHDU(var_rnoise.astype(np.float32), name="VAR_RNOISE"),
        ]
    )
    partial = path.with_suffix(".partial")
    out.writeto(partial, overwrite=True)
    partial.replace(path)


def simulate(args: argparse.Namespace) -> dict:
    rng = np.random.default_rng(args.seed)
    amplitude = pupil_amplitude()
    zernikes_m = rng.normal(0.0, ZERNIKE_NM_RMS * 1e-9, size=8)
    opd = wavefront_m(zernikes_m)
    truth: dict = {
        "seed": args.seed,
        "teff_k": args.teff,
        "jitter_mas": args.jitter_mas,
        "effects": bool(args.effects),
        "zernikes_noll4_11_nm": (zernikes_m * 1e9).round(3).tolist(),
        "files": {},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    stars = {"INDEP-SCI": (46.0 + 0.23, 41.0 - 0.31), "INDEP-CAL": (46.0 - 0.17, 41.0 + 0.12)}
    for filter_name in args.filters.split(","):
        start = time.perf_counter()
        template = args.template_dir / TEMPLATE_NAMES[filter_name]
        with fits.open(template) as hdul:
            p = hdul[0].header
            ngroups, nints, tgroup = int(p["NGROUPS"]), int(p["NINTS"]), float(p["TGROUP"])
            total_dn_s = float(np.nansum(np.clip(hdul["SCI"].data, 0.0, None)))
        psf = polychromatic_psf(filter_name, args.teff, amplitude, opd, args.jitter_mas)
        for targprop, star_sci in stars.items():
            unit = pixel_image(psf, star_sci)
            rate = unit * (total_dn_s / unit.sum())
            if args.effects:
                rate = ipc(rate)
            var_poisson, var_rnoise = slope_variances(rate, ngroups, tgroup, nints)
            data = rate + np.sqrt(var_poisson + var_rnoise) * rng.normal(size=rate.shape)
            if args.effects:
                data = data + stripes(rate.shape, rng)
            name = f"indep_{targprop.split('-')[1].lower()}_{filter_name}_cal.fits"
            write_level2(args.out / name, template, targprop, var_poisson, var_rnoise, data)
            truth["files"][name] = {
                "filter": filter_name,
                "star_sci_xy": list(star_sci),
                "total_dn_s": total_dn_s,
                "ngroups": ngroups,
                "nints": nints,
            }
        print(f"{filter_name}: {time.perf_counter() - start:.1f} s", flush=True)
    (args.out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def _amigo(*args: str) -> None:
    """Run an amigo command in a new process (this script imports no amigo code)."""
    command = [sys.executable, "-m", "amigo", *args]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode not in (0, 3):
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")


def _limit_at(rows: list[dict], filter_name: str, sep_mas: float) -> float:
    """The Absil 3-sigma limit (mag) at ``sep_mas``, linear in separation."""
    mine = [r for r in rows if r["filter"] == filter_name and int(r["n_sigma"]) == 3]
    seps = np.array([float(r["sep_mas"]) for r in mine])
    return float(np.interp(sep_mas, seps, [float(r["absil_dmag"]) for r in mine]))


def fit_and_detect(out: Path, filters: list[str]) -> None:
    """``amigo fit`` and ``amigo detect`` on the simulated files; prints the tables."""
    nominal = out / "nominal.instrument"
    _amigo_nominal_instrument(nominal)
    sci = [str(out / f"indep_sci_{f}_cal.fits") for f in filters]
    cal = [str(out / f"indep_cal_{f}_cal.fits") for f in filters]
    runs = {"default": [], "nominal": ["--model", str(nominal)]}
    print("| model | file | z std | rotation (deg) | anisotropy | skew (deg) | jitter (mas) "
          "| detector amplitude |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    detections = []
    for name, extra in runs.items():
        fit_dir, detect_dir = out / f"fit_{name}", out / f"detect_{name}"
        start = time.perf_counter()
        _amigo("fit", "--sci", *sci, "--cal", *cal, "--out", str(fit_dir), "--force", *extra)
        fit_s = time.perf_counter() - start
        summary = json.loads((fit_dir / "fit_summary.json").read_text())
        for e in summary["exposures"]:
            amplitude = e.get("detector_amplitude")
            detector = (
                "-"
                if amplitude is None
                else f"{amplitude:.2f} +- {e['detector_amplitude_err']:.2f}"
            )
            print(
                f"| {name} | {e['file']} | {e['zscore_std']:.3f} | {e['rotation_deg']:+.4f} | "
                f"{e['anisotropy']:.5f} | {e['skew_deg']:+.4f} | {e['jitter_mas']:.1f} | {detector} |"
            )
        calvis = sorted(str(p) for p in fit_dir.glob("INDEP-SCI_*_calvis.fits"))
        _amigo("detect", *calvis, "--out", str(detect_dir), "--force", "--no-hmc")
        found = json.loads((detect_dir / "companions.json").read_text())
        with open(detect_dir / "contrast_limits.csv") as stream:
            rows = list(csv.DictReader(stream))
        detections.append((name, fit_s, found, rows))
    print()
    print("| model | fit (s) | DISCO error scale | grid maximum (local sigma) | companions "
          "| rejected | 3-sigma limits at 100 / 200 / 400 mas (mag) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for name, fit_s, found, rows in detections:
        scales = ", ".join(f"{f} {v:.2f}" for f, v in found.get("sigma_scale", {}).items())
        best = max(found["search"]["max_joint_sigma_per_iteration"])
        rejected = len(found.get("rejected_candidates", []))
        limits = "; ".join(
            f"{f} " + " / ".join(f"{_limit_at(rows, f, s):.2f}" for s in (100, 200, 400))
            for f in filters
        )
        print(
            f"| {name} | {fit_s:.0f} | {scales} | {best:.1f} | "
            f"{len(found.get('companions', []))} | {rejected} | {limits} |"
        )


def _amigo_nominal_instrument(path: Path) -> None:
    """The nominal instrument as an instrument file, written by amigo in a new process."""
    code = (
        "import sys; from amigo.model.image import Instrument, save_instrument; "
        "save_instrument(Instrument.nominal(), sys.argv[1])"
    )
    subprocess.run([sys.executable, "-c", code, str(path)], check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--filters", default="F480M,F430M,F380M")
    parser.add_argument("--template-dir", type=Path, default=DEFAULT_TEMPLATES)
    parser.add_argument("--effects", action="store_true", help="IPC and 1/f stripes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--teff", type=float, default=4500.0)
    parser.add_argument("--jitter-mas", type=float, default=12.0)
    parser.add_argument("--fit", action="store_true", help="then amigo fit and detect them")
    args = parser.parse_args()
    simulate(args)
    if args.fit:
        fit_and_detect(args.out, args.filters.split(","))


if __name__ == "__main__":
    main()
