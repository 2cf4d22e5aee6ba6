"""Facts about JWST NIRISS in its aperture masking (AMI) mode.

Every number carries a one-line comment naming its source. Nothing here imports JAX:
these are plain Python/NumPy values that the models turn into arrays when they need them.

Frames used throughout amigo
----------------------------
*Detector frame*: the frame of the SCI arrays of JWST products (DMS orientation), with
``x`` along FITS axis 1 (NumPy's last axis, columns) and ``y`` along FITS axis 2 (NumPy's
second-to-last axis, rows). Arrays are indexed ``[..., y, x]``.

*Pupil (mask) frame*: the non-redundant mask projected onto the primary mirror, in
metres: the telescope's V2/V3 frame with V2 reversed (``x = -V2``, ``y = +V3``; see
:func:`pupil_to_v2v3_matrix`), the SIAF's ideal frame before its V3IdlYAngle turn.
Optical-frame angles (the Fraunhofer image of the mask) use the same axes; the detector
sees that image through the linear map :func:`nominal_geometry_matrix`, derived from the
SIAF: V3IdlYAngle, VIdlParity and the linear terms of the science-to-ideal polynomial.
The mask is point-symmetric in intensity, so this frame and its negative give identical
point-source images; the axes (not a transpose or a mirror) are checked on the power
spectrum of real COM 1093 images (tests/test_instrument.py), and the sense of the turn on
real and independently simulated images (docs/geometry.md).

*Sky*: offsets ``(dRA, dDec)`` with ``dRA`` positive to the east; position angles east of
north. With the usual JWST orientation keywords, detector ``+y`` points at position angle
``PA_APER`` (see :mod:`amigo.orientation` and docs/orientation.md).
"""

from __future__ import annotations

import functools
import importlib.util
import itertools
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

# --------------------------------------------------------------------------------------
# The non-redundant mask
# --------------------------------------------------------------------------------------

#: Hole centres (m) in the pupil frame described above, shape (7, 2) as (x, y).
#: Source: the NIRISS NRM as-designed hole table (AMICAL's "g7"; the JWST pipeline's
#: ImPlaneIA heritage), negated (the research code's sign; the image is the same). Axes:
#: ``x = -V2``, ``y = +V3`` (:func:`pupil_to_v2v3_matrix`), verified against COM 1093.
HOLE_CENTRES_M: np.ndarray = np.array(
    [
        [0.00000, 2.64000],
        [2.28631, 0.00000],
        [-2.28631, 1.32000],
        [2.28631, -1.32000],
        [1.14315, -1.98000],
        [-2.28631, -1.32000],
        [-1.14315, -1.98000],
    ]
)
HOLE_CENTRES_M.setflags(write=False)

#: Number of holes in the mask.
N_HOLES: int = 7

#: Flat-to-flat width of each hexagonal hole projected on the primary (m).
#: Source: JDox NIRISS NRM page; confirmed by the AMIGO paper's calibration (not 0.82 m).
HOLE_FLAT_TO_FLAT_M: float = 0.80

#: Diameter of the pupil grid that encloses the mask (m).
#: Source: AMIGO research code pupil diameter (JWST circumscribed pupil, 6.603464 m).
PUPIL_DIAMETER_M: float = 6.603464


@functools.cache
def baseline_pairs() -> tuple[tuple[int, int], ...]:
    """The 21 hole pairs ``(i, j)`` with ``i < j``, in a fixed order used everywhere."""
    return tuple(itertools.combinations(range(N_HOLES), 2))


def baselines_m(holes_m: np.ndarray = HOLE_CENTRES_M) -> np.ndarray:
    """Baseline vectors ``hole_j - hole_i`` (m) for :func:`baseline_pairs`, shape (21, 2)."""
    i, j = np.array(baseline_pairs()).T
    return holes_m[j] - holes_m[i]


# --------------------------------------------------------------------------------------
# Detector geometry
# --------------------------------------------------------------------------------------

#: Pixel scale along detector x (arcsec/pixel). Source: SIAF NIS_AMI1 XSciScale.
PIXEL_SCALE_X_ARCSEC: float = 0.06532556
#: Pixel scale along detector y (arcsec/pixel). Source: SIAF NIS_AMI1 YSciScale.
PIXEL_SCALE_Y_ARCSEC: float = 0.06572261
#: Mean pixel scale (arcsec/pixel). Source: AMIGO research code (0.065524085).
PIXEL_SCALE_ARCSEC: float = 0.065524085

#: Linear part of the NIS_AMI1 science-to-ideal distortion at the reference pixel, in
#: arcsec per pixel: ``[x_idl, y_idl] = M @ [dx, dy]``. The diagonal holds the SIAF
#: per-axis scales; the off-diagonal terms are a 0.24 deg skew of the x axis.
#: Source: the JWST pipeline's WCS (CAL_VER 1.5.3) of the COM 1093 level-2 files, rotated
#: back by PA_APER (identical for all seven files to 1e-6 arcsec/pixel).
SCI_TO_IDEAL_ARCSEC_PER_PIX: np.ndarray = np.array(
    [
        [0.065325, -0.000023],
        [-0.000272, 0.065724],
    ]
)
SCI_TO_IDEAL_ARCSEC_PER_PIX.setflags(write=False)

#: Angle from the V3 axis to the ideal y axis (deg). Source: SIAF NIS_AMI1 V3IdlYAngle
#: (also the V3I_YANG keyword of JWST products).
V3_IDL_Y_ANGLE_DEG: float = 0.56126717
#: Parity of the ideal frame relative to V2/V3. Source: SIAF NIS_AMI1 VIdlParity.
VIDL_PARITY: int = -1

#: Linear terms of the NIS_AMI1 science-to-ideal polynomial at the reference pixel
#: (arcsec per pixel): ``x_idl = X10 dx + X11 dy``, ``y_idl = Y10 dx + Y11 dy`` with
#: ``(dx, dy)`` the science-frame (DMS) pixel offset. Source: SIAF NIS_AMI1 Sci2IdlX10,
#: Sci2IdlX11, Sci2IdlY10, Sci2IdlY11 (PRD PRDOPSSOC-075 as shipped by pysiaf 0.29;
#: tests/test_geometry.py reads them back from pysiaf).
SIAF_SCI_TO_IDEAL_ARCSEC_PER_PIX: np.ndarray = np.array(
    [
        [0.0653249481533922, -1.378360325188185e-05],
        [-0.0002816883065592215, 0.06572261227530646],
    ]
)
SIAF_SCI_TO_IDEAL_ARCSEC_PER_PIX.setflags(write=False)


def pupil_to_v2v3_matrix() -> np.ndarray:
    """(2, 2) matrix taking amigo's pupil (and optical) frame to the telescope's V2/V3 frame.

    amigo's pupil frame is the V2/V3 frame with V2 reversed: ``x = -V2``, ``y = +V3``
    (the NIRISS ideal frame before its :data:`V3_IDL_Y_ANGLE_DEG` rotation; NIRISS has
    ``VIdlParity = -1``). :data:`HOLE_CENTRES_M` are the mask's as-designed hole centres
    in this frame, on the primary mirror (entrance pupil) as seen from the sky. Offsets on
    the sky (angles) and in the pupil transform alike (the Fraunhofer phase ``b . theta``
    is invariant under any orthogonal map applied to both), so the same matrix takes an
    optical-frame angle to a V2/V3 angle.
    """
    return np.array([[-1.0, 0.0], [0.0, 1.0]])


def v2v3_to_ideal_matrix(
    v3_idl_y_angle_deg: float = V3_IDL_Y_ANGLE_DEG, parity: int = VIDL_PARITY
) -> np.ndarray:
    """(2, 2) linear part of the SIAF's V2/V3 -> ideal transform (angles, arcsec).

    The SIAF's ideal -> V2/V3 map is ``V2 = P x cos(t) + y sin(t)``,
    ``V3 = -P x sin(t) + y cos(t)`` (``P`` = VIdlParity, ``t`` = V3IdlYAngle, offsets from
    V2Ref/V3Ref); this returns its inverse.
    """
    t = np.deg2rad(v3_idl_y_angle_deg)
    ideal_to_v2v3 = np.array([[parity * np.cos(t), np.sin(t)], [-parity * np.sin(t), np.cos(t)]])
    return np.linalg.inv(ideal_to_v2v3)


def nominal_geometry_matrix() -> np.ndarray:
    """(2, 2) ``G``: optical-frame offset (in mean pixels, :data:`PIXEL_SCALE_ARCSEC`) ->
    detector (science-frame) offset in pixels, derived from the SIAF (no fitted number).

    The chain: optical frame -> V2/V3 (:func:`pupil_to_v2v3_matrix`), V2/V3 -> ideal
    (:func:`v2v3_to_ideal_matrix`: V3IdlYAngle and VIdlParity), ideal -> science pixels
    (the inverse of :data:`SIAF_SCI_TO_IDEAL_ARCSEC_PER_PIX`). For NIS_AMI1 it turns the
    image by -0.444 deg (clockwise: from +y towards +x) on the detector, with a 0.26 deg
    skew and a y/x anisotropy of 1.0060; see :func:`geometry_parameters` and
    docs/geometry.md.
    """
    to_pixels = np.linalg.inv(SIAF_SCI_TO_IDEAL_ARCSEC_PER_PIX)
    chain = to_pixels @ v2v3_to_ideal_matrix() @ pupil_to_v2v3_matrix()
    return chain * PIXEL_SCALE_ARCSEC


@dataclass(frozen=True)
class Geometry:
    """The detector geometry ``G`` in four numbers (see
    :func:`amigo.model.detector.linear.geometry_matrix` for the exact definition).

    Attributes
    ----------
    rotation_deg
        Mean turn of the image on the detector, positive from +x towards +y
        (counter-clockwise in the DMS display, origin at the bottom left).
    anisotropy
        y/x stretch along the detector axes: a pixel spans ``anisotropy`` times more sky
        along y than along x.
    skew_deg
        The images of the optical +x and +y axes are ``90 + skew_deg`` degrees apart.
    scale
        Magnification relative to :data:`PIXEL_SCALE_ARCSEC` (1: that mean pixel scale).
    """

    rotation_deg: float
    anisotropy: float
    skew_deg: float
    scale: float


def geometry_parameters(matrix: np.ndarray) -> Geometry:
    """Invert :func:`amigo.model.detector.linear.geometry_matrix`: the four numbers of ``G``.

    ``G = s diag(a^1/2, a^-1/2) K`` with ``K``'s columns the unit vectors at angles
    ``phi - kappa/2`` and ``90 + phi + kappa/2``. Writing ``u = s a^1/2``,
    ``w = s a^-1/2``, the columns of ``G`` give ``(G00/u)^2 + (G10/w)^2 = 1`` and
    ``(G01/u)^2 + (G11/w)^2 = 1``, linear in ``1/u^2`` and ``1/w^2``.
    """
    g = np.asarray(matrix, dtype=float)
    lhs = np.array([[g[0, 0] ** 2, g[1, 0] ** 2], [g[0, 1] ** 2, g[1, 1] ** 2]])
    inv_u2, inv_w2 = np.linalg.solve(lhs, np.ones(2))
    u, w = 1.0 / np.sqrt(inv_u2), 1.0 / np.sqrt(inv_w2)
    alpha = np.arctan2(g[1, 0] / w, g[0, 0] / u)  # image of optical +x
    beta = np.arctan2(-g[0, 1] / u, g[1, 1] / w)  # image of optical +y, minus 90 deg
    return Geometry(
        rotation_deg=float(np.rad2deg(0.5 * (alpha + beta))),
        anisotropy=float(u / w),
        skew_deg=float(np.rad2deg(beta - alpha)),
        scale=float(np.sqrt(u * w)),
    )


@functools.cache
def nominal_geometry() -> Geometry:
    """The SIAF-derived geometry of NIS_AMI1 (:func:`nominal_geometry_matrix`)."""
    return geometry_parameters(nominal_geometry_matrix())


#: Instrumental jitter (Gaussian sigma, arcsec). Source: AMIGO paper (~21 mas recovered).
JITTER_SIGMA_ARCSEC: float = 0.0214

# --------------------------------------------------------------------------------------
# The SUB80 subarray and its read-out
# --------------------------------------------------------------------------------------

#: Subarray name, size and first full-frame pixel (1-based). Source: JWST keywords
#: SUBARRAY/SUBSIZE1/2/SUBSTRT1/2 of AMI products (SUB80 starts at x=1045, y=1).
SUBARRAY: str = "SUB80"
SUBARRAY_SIZE: int = 80
SUBARRAY_START_X: int = 1045
SUBARRAY_START_Y: int = 1

#: Number of reference-pixel rows at the bottom of SUB80 (rows 0..3 in NumPy order).
#: Source: NIRISS detector layout (4-pixel reference border; SUB80 touches the bottom edge
#: at SUBSTRT2=1, so its first 4 rows are reference pixels; flagged REFERENCE_PIXEL in DQ).
N_REFERENCE_ROWS: int = 4

#: Frame time = group time of SUB80 with NISRAPID (s). Source: TFRAME/TGROUP keywords.
FRAME_TIME_S: float = 0.07544
GROUP_TIME_S: float = 0.07544

#: Detector gain (electrons per DN). Source: AMIGO paper Table 1 note (~1.6) and research
#: code (1.61).
GAIN_E_PER_DN: float = 1.61


def reference_row_mask(ny: int = SUBARRAY_SIZE, nx: int = SUBARRAY_SIZE) -> np.ndarray:
    """Boolean (ny, nx) mask, True on the reference rows of SUB80 (never use their signal)."""
    mask = np.zeros((ny, nx), dtype=bool)
    mask[:N_REFERENCE_ROWS] = True
    return mask


# --------------------------------------------------------------------------------------
# Filters
# --------------------------------------------------------------------------------------

#: AMI filters and whether amigo is calibrated for them.
#: Source: AMIGO paper Table 'Allowed Filters' (F277W excluded from calibration).
FILTERS: tuple[str, ...] = ("F277W", "F380M", "F430M", "F480M")
CALIBRATED_FILTERS: tuple[str, ...] = ("F380M", "F430M", "F480M")

#: Nominal central wavelengths (m). Source: JDox NIRISS filters (AMIGO paper table).
CENTRAL_WAVELENGTH_M: dict[str, float] = {
    "F277W": 2.771e-6,
    "F380M": 3.825e-6,
    "F430M": 4.285e-6,
    "F480M": 4.815e-6,
}

#: Fraction of the peak throughput that bounds the filter support used for binning.
FILTER_SUPPORT_FRACTION: float = 0.01


class UncalibratedFilterWarning(UserWarning):
    """The filter works but the shipped model is not calibrated for it (F277W)."""


def check_filter(name: str) -> str:
    """Return the canonical filter name; raise ``ValueError`` for a non-AMI filter.

    F277W is accepted with an :class:`UncalibratedFilterWarning`.
    """
    canonical = name.strip().upper()
    if canonical not in FILTERS:
        raise ValueError(f"filter {name!r} is not an AMI filter (expected one of {FILTERS})")
    if canonical not in CALIBRATED_FILTERS:
        warnings.warn(
            f"{canonical} is not calibrated: the AMIGO paper and amigo's base model exclude it",
            UncalibratedFilterWarning,
            stacklevel=2,
        )
    return canonical


def svo_votable(name: str) -> bytes:
    """The SVO Filter Profile Service VOTable of NIRISS filter ``name`` (canonical name).

    The svo-filters package ships these files (Angstrom, filter-only throughput); we read
    them at run time rather than copying curves. The package is located, not imported:
    importing it imports bokeh and astropy.table, seconds per process for nothing we use.
    """
    spec = importlib.util.find_spec("svo_filters")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError("the svo-filters package (a dependency of amigo) is missing")
    folder = Path(next(iter(spec.submodule_search_locations)))
    return (folder / "data" / "filters" / f"NIRISS.{name}").read_bytes()


@functools.cache
def _filter_curve_cached(name: str) -> tuple[np.ndarray, np.ndarray]:
    root = ET.fromstring(svo_votable(name))
    rows = [
        [float(cast(str, td.text)) for td in tr.findall("{*}TD")]
        for tr in root.iter()
        if tr.tag.endswith("TR")
    ]
    table = np.array(rows, dtype=float)
    order = np.argsort(table[:, 0])
    wavelength_m = table[order, 0] * 1e-10
    throughput = np.clip(table[order, 1], 0.0, None)
    wavelength_m.setflags(write=False)
    throughput.setflags(write=False)
    return wavelength_m, throughput


def filter_curve(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Tabulated throughput of an AMI filter.

    Returns
    -------
    wavelength_m, throughput
        1-D arrays of equal length, wavelength in metres (ascending), throughput in [0, 1].
    """
    return _filter_curve_cached(check_filter(name))


def half_power_limits(name: str) -> tuple[float, float]:
    """Wavelengths (m) where the throughput crosses half its peak (linear interpolation)."""
    wavelength, throughput = filter_curve(name)
    half = 0.5 * throughput.max()
    above = np.nonzero(throughput >= half)[0]
    lo, hi = above[0], above[-1]
    blue = np.interp(half, throughput[lo - 1 : lo + 1], wavelength[lo - 1 : lo + 1])
    red = np.interp(half, throughput[hi : hi + 2][::-1], wavelength[hi : hi + 2][::-1])
    return float(blue), float(red)


@dataclass(frozen=True)
class FilterBins:
    """A filter sampled at ``n`` wavelengths.

    Attributes
    ----------
    name
        Filter name.
    wavelengths_m
        (n,) bin centroids (throughput-weighted mean wavelength of each bin), metres.
    weights
        (n,) integrated throughput of each bin, normalised to sum to one.
    edges_m
        (n+1,) bin edges, metres: ``n`` equal-width bins over the filter support (where
        the throughput exceeds :data:`FILTER_SUPPORT_FRACTION` of its peak).
    """

    name: str
    wavelengths_m: np.ndarray
    weights: np.ndarray
    edges_m: np.ndarray

    @property
    def central_wavelength_m(self) -> float:
        """Throughput-weighted mean wavelength of the band (m)."""
        return float(np.sum(self.wavelengths_m * self.weights))


def filter_bins(name: str, n: int = 9) -> FilterBins:
    """Bin an AMI filter curve into ``n`` wavelengths with normalised weights.

    The support is cut into ``n`` equal-width bins; each bin's weight is its integrated
    throughput and its wavelength the throughput-weighted centroid, so the band's mean
    wavelength is preserved exactly.
    """
    name = check_filter(name)
    wavelength, throughput = filter_curve(name)
    return bin_curve(name, wavelength, throughput, n)


def bin_curve(name: str, wavelength_m: np.ndarray, weight: np.ndarray, n: int) -> FilterBins:
    """Bin a weight curve (``wavelength_m`` ascending, metres) into ``n`` wavelengths.

    The support (where ``weight`` is at least :data:`FILTER_SUPPORT_FRACTION` of its peak)
    is cut into ``n`` equal-width bins; each bin's weight is its integrated weight and its
    wavelength the weighted centroid, so the curve's mean wavelength is preserved.
    """
    if n < 1:
        raise ValueError(f"number of wavelengths must be >= 1, got {n}")
    wavelength = np.asarray(wavelength_m, dtype=float)
    curve = np.asarray(weight, dtype=float)
    inside = np.nonzero(curve >= FILTER_SUPPORT_FRACTION * curve.max())[0]
    edges = np.linspace(wavelength[inside[0]], wavelength[inside[-1]], n + 1)
    # Integrate on a fine grid so that bins narrower than the tabulation are still exact.
    fine = np.linspace(edges[0], edges[-1], 200 * n + 1)
    c_fine = np.interp(fine, wavelength, curve)
    which = np.clip(np.searchsorted(edges, fine, side="right") - 1, 0, n - 1)
    total = np.bincount(which, weights=c_fine, minlength=n)
    first_moment = np.bincount(which, weights=c_fine * fine, minlength=n)
    centroids = np.where(
        total > 0, first_moment / np.where(total > 0, total, 1.0), 0.5 * (edges[:-1] + edges[1:])
    )
    return FilterBins(
        name=name,
        wavelengths_m=centroids,
        weights=total / total.sum(),
        edges_m=edges,
    )
