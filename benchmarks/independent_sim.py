"""An independent simulator of NIRISS AMI level-2 images: poppy, pysiaf and synphot, no amigo.

    python benchmarks/independent_sim.py --out DIR [--filters F480M,F430M,F380M]
        [--template-dir DIR] [--effects] [--seed 0] [--teff 4500] [--jitter-mas 12]
        [--cal-flux 1.0] [--fit [--no-simulate]]
        [--ramps [--bfe 1e-6] [--detector-maps MODEL.npz] [--detectors full,linear,boundary]]

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

Raw ramps (``--ramps``): ``_uncal`` files instead, the charge collected up the ramp
with a physical brighter-fatter effect (:func:`simulate_ramps`): the boundary between two
pixels moves away from the side holding more charge by ``--bfe`` pixels per electron of
the field-weighted charge difference (:func:`bfe_coefficients`: a point charge's
boundary-normal field at the boundary's midpoint, from the pixels within
``BFE_RADIUS_PIX``), and the photo-electrons falling in the swept strip (the sub-samples'
rate density at the boundary) change pixel; integrated in ``SUBSTEPS_PER_GROUP`` Poisson
steps per group. Then dark current, the pixel's quadratic non-linearity, IPC, gain, bias,
reset, read noise, 1/f offsets per column and read (``--effects``) and the ADC's integral
non-linearity. The detector's pixel calibration (flat, intra-pixel response, dark,
non-linearity, IPC kernel) is ideal unless ``--detector-maps`` names a base model, whose
arrays are then read with NumPy as a laboratory's reference files would be: a base model
can only be asked to fit the detector it was calibrated on; what is independent is the
brighter-fatter physics, the optics, the geometry, the spectrum and the read-out.
``--fit`` then runs ``amigo process``, ``amigo fit --detector D`` for each D of
``--detectors`` (default ``full,linear``; ``boundary`` the physical account) and
``amigo detect --no-hmc`` on each, and prints their tables; ``--no-simulate`` fits the
files an earlier run left in ``--out``.

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
4-5 minutes per model (with ``--ramps``, 8-9 minutes per detector model).
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
STRIPE_READ_DN = 1.0  # raw ramps: a 1/f offset per column and read (--effects)
ZERNIKE_NM_RMS = 20.0
APERTURE = "NIS_AMI1"

MAS_TO_RAD = np.pi / 180.0 / 3600.0 / 1000.0

# Raw ramps (--ramps)
SUBSTEPS_PER_GROUP = 8  # Poisson steps of charge collection per group time
BFE_STRENGTH_PIX_PER_E = 1.0e-6  # boundary shift per electron of field-weighted charge
BFE_RADIUS_PIX = 3  # pixels on either side of a boundary whose charge moves it
BFE_DEPTH_PIX = 0.5  # depth of the boundary's field point below the charge (pixels)
NONLINEARITY_PER_E = -5.0e-7  # q -> q + nl q^2 for the ideal detector
BIAS_DN = 12000.0
BIAS_SPREAD_DN = 400.0
RESET_DN = 30.0  # common to a frame's pixels, per integration
RESET_PIXEL_DN = 15.0  # per pixel and integration (kTC)
ADC_AMPLITUDE_DN = 2.0
ADC_PERIOD_DN = 1024.0


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
    return pixel_subsamples(psf, star_sci, size).sum(axis=(2, 3))


def pixel_subsamples(psf: np.ndarray, star_sci: tuple[float, float], size: int = 80) -> np.ndarray:
    """(size, size, SUBSAMPLE, SUBSAMPLE) photons in each sub-sample of each pixel, indexed
    ``[y, x, sy, sx]`` (sub-sample offsets ``(k + 0.5) / SUBSAMPLE - 0.5`` pixels), for unit
    incident flux; their sum over the last two axes is :func:`pixel_image`."""
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
    return (values * area_sr).reshape(size, size, SUBSAMPLE, SUBSAMPLE)


# ----------------------------------------------------------------------------------------
# Detector and noise
# ----------------------------------------------------------------------------------------


def ipc_kernel() -> np.ndarray:
    """(3, 3) inter-pixel capacitance: 0.6 % to each edge neighbour, 0.06 % to each corner;
    sums to one (conserves charge)."""
    edge, corner = 0.006, 0.0006
    kernel = np.array([[corner, edge, corner], [edge, 0.0, edge], [corner, edge, corner]])
    kernel[1, 1] = 1.0 - kernel.sum()
    return kernel


def ipc(image: np.ndarray) -> np.ndarray:
    """``image`` through :func:`ipc_kernel` (zero beyond the subarray)."""
    return ndimage.convolve(image, ipc_kernel(), mode="constant", cval=0.0)


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
# Raw ramps (--ramps): charge collection with a physical brighter-fatter effect
# ----------------------------------------------------------------------------------------


def load_detector_maps(path: Path | None, shape: tuple[int, int] = (80, 80)) -> dict:
    """The detector's pixel calibration: flat, intra-pixel response, dark, non-linearity
    and IPC kernel.

    ``path``: a base-model ``.npz`` read with NumPy alone (its arrays are the calibration
    of the detector that model describes, as a laboratory's reference files would be);
    ``None``: an ideal detector (unit flat and response, no dark, this script's 3 x 3 IPC,
    ``NONLINEARITY_PER_E`` everywhere). Shapes: flat, dark (e- per group), nonlinearity
    (1/e-) (ny, nx); ipc (k, k), summing to one; intra (5,): the coefficients of
    ``1 + c . (x, y, x^2, x y, y^2)`` over a pixel's offsets ``x, y`` in [-1/2, 1/2].
    """
    if path is None:
        return {
            "flat": np.ones(shape),
            "intra": np.zeros(5),
            "dark_e_per_group": np.zeros(shape),
            "nonlinearity": np.full(shape, NONLINEARITY_PER_E),
            "ipc": ipc_kernel(),
        }
    with np.load(path, allow_pickle=False) as data:
        return {
            "flat": np.asarray(data[".ramp.flat"], float),
            "intra": np.asarray(data[".ramp.intra_pixel.coefficients"], float),
            "dark_e_per_group": np.asarray(data[".read.dark_e_per_group"], float),
            "nonlinearity": np.asarray(data[".read.nonlinearity"], float),
            "ipc": np.asarray(data[".read.ipc_kernel"], float),
        }


def intra_pixel_weights(coefficients: np.ndarray) -> np.ndarray:
    """(SUBSAMPLE, SUBSAMPLE) sensitivity of each sub-sample ``[sy, sx]``, mean one: the
    quadratic response evaluated at the sub-sample centres."""
    offsets = (np.arange(SUBSAMPLE) + 0.5) / SUBSAMPLE - 0.5
    y, x = np.meshgrid(offsets, offsets, indexing="ij")
    response = 1.0 + np.tensordot(np.stack([x, y, x**2, x * y, y**2], -1), coefficients, 1)
    return response / response.mean()


def bfe_coefficients() -> np.ndarray:
    """(2 R + 1, R) weights ``c[n + R, m]`` of the charge in the pixel ``m`` pixels beyond a
    boundary (``m = 0``: the pixel that shares it) and ``n`` pixels along it.

    The weight is the boundary-normal field at the boundary's midpoint, at the depth
    ``BFE_DEPTH_PIX`` below the collecting surface, of a point charge at that pixel's
    centre: ``(m + 1/2) / ((m + 1/2)^2 + n^2 + h^2)^(3/2)``, normalised to one for the
    pixel next to the boundary (``m = n = 0``).
    """
    r = BFE_RADIUS_PIX
    n = np.arange(-r, r + 1)[:, None]
    m = np.arange(r)[None, :] + 0.5
    c = m / (m**2 + n**2 + BFE_DEPTH_PIX**2) ** 1.5
    return c / c[r, 0]


def _field_sum(charge: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """(..., ny, nx - 1): ``sum_{n, m} c[n, m] (Q[y + n, x + 1 + m] - Q[y + n, x - m])`` for
    the boundary between pixels ``x`` and ``x + 1`` of each row ``y`` (zero charge beyond
    the subarray)."""
    r = coefficients.shape[1]
    ny, nx = charge.shape[-2:]
    pad = [(0, 0)] * (charge.ndim - 2) + [(r, r), (r, r)]
    q = np.pad(charge, pad)
    out = np.zeros((*charge.shape[:-2], ny, nx - 1))
    for i, n in enumerate(range(-r, r + 1)):
        rows = q[..., r + n : r + n + ny, :]
        for m in range(r):
            plus = rows[..., r + 1 + m : r + nx + m]
            minus = rows[..., r - m : r - m + nx - 1]
            out += coefficients[i, m] * (plus - minus)
    return out


def migration_rates(
    charge: np.ndarray, edge_x: np.ndarray, edge_y: np.ndarray, strength: float
) -> np.ndarray:
    """(..., ny, nx) e-/s gained by each pixel from boundaries moved by the charge.

    The boundary between two pixels moves away from the side holding more charge (its
    field repels the arriving photo-electrons) by ``strength`` (pixels per electron) times
    the field sum of :func:`_field_sum`; the photo-electrons arriving in the strip it
    swept change pixel: ``displacement x edge rate density``. ``edge_x`` (ny, nx - 1): the
    photon rate per pixel of width (e-/s) at each boundary between columns; ``edge_y``
    (ny - 1, nx) between rows. Charge is conserved: what one pixel gains its neighbour
    loses.
    """
    c = bfe_coefficients()
    shift_x = strength * _field_sum(charge, c)  # +: the boundary moves into x + 1
    shift_y = strength * np.swapaxes(_field_sum(np.swapaxes(charge, -1, -2), c), -1, -2)
    flow_x = shift_x * edge_x  # e-/s from pixel x + 1 into pixel x
    flow_y = shift_y * edge_y
    gain = np.zeros(charge.shape)
    gain[..., :, :-1] += flow_x
    gain[..., :, 1:] -= flow_x
    gain[..., :-1, :] += flow_y
    gain[..., 1:, :] -= flow_y
    return gain


def edge_densities(subsamples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Photon rates per pixel width at the boundaries between columns (ny, nx - 1) and rows
    (ny - 1, nx): the mean of the sub-sample strips on either side of each boundary,
    times ``SUBSAMPLE`` (a strip is 1 / SUBSAMPLE of a pixel wide)."""
    last_col = subsamples[:, :-1, :, -1].sum(axis=-1)
    first_col = subsamples[:, 1:, :, 0].sum(axis=-1)
    last_row = subsamples[:-1, :, -1, :].sum(axis=-1)
    first_row = subsamples[1:, :, 0, :].sum(axis=-1)
    return 0.5 * SUBSAMPLE * (last_col + first_col), 0.5 * SUBSAMPLE * (last_row + first_row)


def migrated_charge(
    subsamples_e_s: np.ndarray, integration_s: float, strength: float, steps: int = 96
) -> np.ndarray:
    """(ny, nx) electrons that :func:`migration_rates` moves into (+) or out of (-) each
    pixel over an integration of ``integration_s``, without noise: the charge collected
    with the effect minus without it (forward Euler in ``steps`` steps).
    ``subsamples_e_s``: (ny, nx, S, S) rates after the detector's sensitivities."""
    rate = subsamples_e_s.sum(axis=(2, 3))
    edge_x, edge_y = edge_densities(subsamples_e_s)
    dt = integration_s / steps
    charge = np.zeros(rate.shape)
    for _ in range(steps):
        charge = charge + (rate + migration_rates(charge, edge_x, edge_y, strength)) * dt
    return charge - rate * integration_s


def simulate_ramps(
    subsamples_e_s: np.ndarray,
    maps: dict,
    ngroups: int,
    nints: int,
    tgroup_s: float,
    rng: np.random.Generator,
    *,
    bfe_strength: float,
    stripes_dn: float,
    reference_rows: int = 4,
) -> tuple[np.ndarray, dict]:
    """(nints, ngroups, ny, nx) raw counts (uint16, bias included) of an exposure, and a
    record of its physics.

    ``subsamples_e_s``: (ny, nx, S, S) photo-electron rate (e-/s) of each pixel's
    sub-samples before the detector's sensitivities. Each integration starts empty; its
    time is cut into ``SUBSTEPS_PER_GROUP`` steps per group, and in each the pixels
    collect Poisson counts of their rate (flat x intra-pixel response) plus the
    migration of :func:`migration_rates` at the charge collected so far. Each read
    (NFRAMES = 1) sees the charge plus the dark current, through the pixel's own
    quadratic non-linearity (the charge-to-voltage conversion of the pixel's own node), then
    the IPC kernel (the coupling of the nodes' voltages), the gain, a per-pixel bias, a reset
    offset per integration, white read noise (``READ_NOISE_E / sqrt(2)`` per read) and,
    with ``stripes_dn`` > 0, a 1/f offset per column and read; the ADC adds its integral
    non-linearity (``ADC_AMPLITUDE_DN`` sin(2 pi x / 1024)) and rounds. The first
    ``reference_rows`` rows are reference pixels: no light, no dark.
    """
    weights = intra_pixel_weights(maps["intra"])
    sub = subsamples_e_s * weights[None, None] * maps["flat"][:, :, None, None]
    sub[:reference_rows] = 0.0
    rate = sub.sum(axis=(2, 3))
    edge_x, edge_y = edge_densities(sub)
    ny, nx = rate.shape
    dt = tgroup_s / SUBSTEPS_PER_GROUP
    # The maps' dark is a mean per group that may be negative in places (a calibration's
    # noise): drawn as a Gaussian of that mean and of its magnitude as variance.
    dark_mean = np.array(maps["dark_e_per_group"], dtype=float)
    dark_mean[:reference_rows] = 0.0
    bias = BIAS_DN + BIAS_SPREAD_DN * rng.normal(size=(ny, nx))
    charge = np.zeros((nints, ny, nx))
    dark = np.zeros((nints, ny, nx))
    out = np.empty((nints, ngroups, ny, nx), dtype=np.uint16)
    reset = RESET_DN * rng.normal(size=(nints, 1, 1)) + RESET_PIXEL_DN * rng.normal(
        size=(nints, ny, nx)
    )
    for group in range(ngroups):
        for _ in range(SUBSTEPS_PER_GROUP):
            migration = migration_rates(charge, edge_x, edge_y, bfe_strength)
            expected = np.clip(rate + migration, 0.0, None) * dt
            charge += rng.poisson(expected)
        dark += dark_mean + np.sqrt(np.abs(dark_mean)) * rng.normal(size=dark.shape)
        q = charge + dark
        q = q + maps["nonlinearity"] * q**2
        k = maps["ipc"]
        q = ndimage.convolve(q, k[None], mode="constant", cval=0.0)
        dn = q / GAIN_E_PER_DN + bias + reset
        dn = dn + READ_NOISE_E / np.sqrt(2.0) / GAIN_E_PER_DN * rng.normal(size=dn.shape)
        if stripes_dn > 0:
            dn = dn + stripes_dn * rng.normal(size=(nints, 1, nx))
        dn = dn + ADC_AMPLITUDE_DN * np.sin(2.0 * np.pi * dn / ADC_PERIOD_DN)
        out[:, group] = np.clip(np.rint(dn), 0, 65535).astype(np.uint16)
    moved = migrated_charge(sub, ngroups * tgroup_s, bfe_strength)
    peak = float(charge.mean(axis=0).max())
    record = {
        "peak_charge_e": peak,
        "migrated_e_max": float(np.abs(moved).max()),
        "migrated_fraction_of_peak": float(np.abs(moved).max() / peak),
    }
    return out, record


def write_uncal(path: Path, template: Path, targprop: str, ramps: np.ndarray) -> None:
    """An ``_uncal`` file (SCI uint16 (nints, ngroups, ny, nx), GROUPDQ, PIXELDQ) with the
    template's headers, written atomically; PIXELDQ carries the template's reference-pixel
    and DO_NOT_USE flags."""
    with fits.open(template) as hdul:
        primary = hdul[0].header.copy()
        sci_header = hdul["SCI"].header.copy()
        dq = np.asarray(hdul["DQ"].data).astype(np.uint32) & np.uint32(2**31 | 1)
    for key in list(primary):
        if key.startswith("S_") or key.startswith("R_"):  # no pipeline step has run
            del primary[key]
    primary["TARGPROP"] = targprop
    primary["TARGNAME"] = targprop
    primary["HISTORY"] = "Simulated raw ramps by amigo's benchmarks/independent_sim.py."
    for key in ("BUNIT", "BSCALE", "BZERO"):
        sci_header.pop(key, None)
    sci = fits.ImageHDU(ramps, header=sci_header, name="SCI")
    sci.header["BUNIT"] = "DN"
    out = fits.HDUList(
        [
            fits.PrimaryHDU(header=primary),
            sci,
            fits.ImageHDU(np.zeros(ramps.shape, np.uint8), name="GROUPDQ"),
            fits.ImageHDU(dq, name="PIXELDQ"),
        ]
    )
    partial = path.with_suffix(".partial")
    out.writeto(partial, overwrite=True)
    partial.replace(path)


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
    primary["S_CHGMIG"] = "SKIPPED"  # every group of a simulated ramp is in its slope
    sci_header["BUNIT"] = "DN/s"  # what this simulation writes, whatever the template held
    sci_header.pop("PHOTMJSR", None)
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
    maps = None
    if args.ramps:
        maps = load_detector_maps(args.detector_maps)
        truth["ramps"] = {
            "bfe_strength_pix_per_e": args.bfe,
            "detector_maps": str(args.detector_maps) if args.detector_maps else "ideal",
            "read_noise_e_per_read": READ_NOISE_E / np.sqrt(2.0),
            "stripes_dn_per_read": STRIPE_READ_DN if args.effects else 0.0,
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
            flux_dn_s = total_dn_s * (args.cal_flux if targprop == "INDEP-CAL" else 1.0)
            if maps is not None:  # --ramps
                sub = pixel_subsamples(psf, star_sci)
                sub_e_s = sub * (flux_dn_s * GAIN_E_PER_DN / sub.sum())
                ramps, record = simulate_ramps(
                    sub_e_s,
                    maps,
                    ngroups,
                    nints,
                    tgroup,
                    rng,
                    bfe_strength=args.bfe,
                    stripes_dn=STRIPE_READ_DN if args.effects else 0.0,
                )
                name = f"indep_{targprop.split('-')[1].lower()}_{filter_name}_uncal.fits"
                write_uncal(args.out / name, template, targprop, ramps)
                truth["files"][name] = {
                    "filter": filter_name,
                    "star_sci_xy": list(star_sci),
                    "total_e_s": flux_dn_s * GAIN_E_PER_DN,
                    "ngroups": ngroups,
                    "nints": nints,
                    **record,
                }
                continue
            unit = pixel_image(psf, star_sci)
            rate = unit * (flux_dn_s / unit.sum())
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
                "total_dn_s": flux_dn_s,
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
        detections.append((name, fit_s, *_detect(fit_dir, detect_dir)))
    _detection_table(detections, filters, "model")


def _detect(fit_dir: Path, detect_dir: Path) -> tuple[dict, list[dict]]:
    """``amigo detect --no-hmc`` on a fit's science products: companions.json and the
    contrast-limit rows."""
    calvis = sorted(str(p) for p in fit_dir.glob("INDEP-SCI_*_calvis.fits"))
    _amigo("detect", *calvis, "--out", str(detect_dir), "--force", "--no-hmc")
    found = json.loads((detect_dir / "companions.json").read_text())
    with open(detect_dir / "contrast_limits.csv") as stream:
        return found, list(csv.DictReader(stream))


def _detection_table(detections: list[tuple], filters: list[str], what: str) -> None:
    """One row per ``amigo detect`` run: (name, fit seconds, companions.json, limit rows)."""
    print()
    print(f"| {what} | fit (s) | DISCO error scale | grid maximum (local sigma) | companions "
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


def process_and_fit(
    out: Path,
    filters: list[str],
    model: Path | None,
    detectors: tuple[str, ...] = ("full", "linear"),
) -> None:
    """``amigo process`` the raw ramps, then ``amigo fit`` with each of ``detectors``
    (``--detector``; ``--model model`` where given); prints a table per exposure."""
    processed = out / "calslope"
    uncal = sorted(str(p) for p in out.glob("indep_*_uncal.fits"))
    start = time.perf_counter()
    _amigo("process", *uncal, "--out", str(processed), "--force")
    print(f"amigo process: {time.perf_counter() - start:.0f} s for {len(uncal)} files")
    sci = [str(processed / f"indep_sci_{f}_calslope.fits") for f in filters]
    cal = [str(processed / f"indep_cal_{f}_calslope.fits") for f in filters]
    extra = ["--model", str(model)] if model else []
    print("| detector | file | z std | chi2 / dof | rotation (deg) | jitter (mas) "
          "| migration amplitude | fit (s) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    detections = []
    for detector in detectors:
        fit_dir = out / f"fit_ramps_{detector}"
        start = time.perf_counter()
        _amigo("fit", "--sci", *sci, "--cal", *cal, "--out", str(fit_dir), "--force",
               "--detector", detector, *extra)  # fmt: skip
        fit_s = time.perf_counter() - start
        summary = json.loads((fit_dir / "fit_summary.json").read_text())
        for e in summary["exposures"]:
            chi2 = e["chi2"] / e["dof"]
            migration = "-"
            if e.get("migration_amplitude") is not None:
                migration = f"{e['migration_amplitude']:.2f} +- {e['migration_amplitude_err']:.2f}"
                migration += " (applied)" if e.get("migration_applied") else ""
            print(
                f"| {detector} | {e['file']} | {e['zscore_std']:.3f} | {chi2:.3f} | "
                f"{e['rotation_deg']:+.4f} | {e['jitter_mas']:.1f} | {migration} | {fit_s:.0f} |"
            )
        detections.append((detector, fit_s, *_detect(fit_dir, out / f"detect_ramps_{detector}")))
    _detection_table(detections, filters, "detector")


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
    parser.add_argument(
        "--no-simulate", action="store_true", help="fit the files already in --out (with --fit)"
    )
    parser.add_argument(
        "--ramps", action="store_true", help="raw ramps (_uncal) with a brighter-fatter effect"
    )
    parser.add_argument("--bfe", type=float, default=BFE_STRENGTH_PIX_PER_E)
    parser.add_argument(
        "--cal-flux", type=float, default=1.0, help="the calibrator's flux over the template's"
    )
    parser.add_argument(
        "--detector-maps",
        type=Path,
        default=None,
        help="a base-model .npz whose pixel calibration the simulated detector has",
    )
    parser.add_argument(
        "--detectors",
        default="full,linear",
        help="with --ramps --fit: the amigo fit --detector values to run (full,linear,boundary)",
    )
    args = parser.parse_args()
    if not args.no_simulate:
        simulate(args)
    if args.fit and args.ramps:
        detectors = tuple(args.detectors.split(","))
        process_and_fit(args.out, args.filters.split(","), args.detector_maps, detectors)
    elif args.fit:
        fit_and_detect(args.out, args.filters.split(","))


if __name__ == "__main__":
    main()
