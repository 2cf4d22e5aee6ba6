"""Facts about JWST NIRISS in its aperture masking (AMI) mode.

Every number carries a one-line comment naming its source. Nothing here imports JAX:
these are plain Python/NumPy values that the models turn into arrays when they need them.

Frames used throughout amigo
----------------------------
*Detector frame*: the frame of the SCI arrays of JWST products (DMS orientation), with
``x`` along FITS axis 1 (NumPy's last axis, columns) and ``y`` along FITS axis 2 (NumPy's
second-to-last axis, rows). Arrays are indexed ``[..., y, x]``.

*Pupil (mask) frame*: the non-redundant mask projected onto the primary mirror, in
metres, with ``+x`` and ``+y`` along detector ``+x`` and ``+y`` (the frame in which the
Fraunhofer image of the mask is the detector image, before the small detector rotation
and anisotropy of :data:`DETECTOR_ROTATION_DEG` / :data:`DETECTOR_ANISOTROPY`). The mask
is point-symmetric in intensity, so this frame and its negative give identical point-source
images; we fixed the sign by the convention of the authors' research code and checked the
axes (not a transpose or a mirror) on the power spectrum of real COM 1093 images.

*Sky*: offsets ``(dRA, dDec)`` with ``dRA`` positive to the east; position angles east of
north. With the usual JWST orientation keywords, detector ``+y`` points at position angle
``PA_APER`` (see :mod:`amigo.orientation` and docs/orientation.md).
"""

from __future__ import annotations

import functools
import itertools
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from importlib import resources

import numpy as np

# --------------------------------------------------------------------------------------
# The non-redundant mask
# --------------------------------------------------------------------------------------

#: Hole centres (m) in the pupil frame described above, shape (7, 2) as (x, y).
#: Source: NIRISS NRM design as used by the AMIGO authors' research code (the negative of
#: AMICAL's "g7" table); axes verified against COM 1093 power spectra (tests/test_instrument).
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

#: Rotation of the detector pixel grid relative to the optical (pupil-frame) image (deg).
#: Source: AMIGO paper, 'Linear Detector Model' (~0.56 deg; research code +0.561 deg).
DETECTOR_ROTATION_DEG: float = 0.561
#: y/x anisotropy of the detector pixel grid relative to the optical image.
#: Source: AMIGO research code (1.00765; paper ~1.0077).
DETECTOR_ANISOTROPY: float = 1.00765

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


@functools.cache
def _filter_curve_cached(name: str) -> tuple[np.ndarray, np.ndarray]:
    # The svo-filters package ships the SVO Filter Profile Service VOTables (Angstrom,
    # filter-only throughput); we read them at run time rather than copying curves.
    resource = resources.files("svo_filters") / "data" / "filters" / f"NIRISS.{name}"
    root = ET.fromstring(resource.read_bytes())
    rows = [
        [float(td.text) for td in tr.findall("{*}TD")]
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
    if n < 1:
        raise ValueError(f"number of wavelengths must be >= 1, got {n}")
    name = check_filter(name)
    wavelength, throughput = filter_curve(name)
    inside = np.nonzero(throughput >= FILTER_SUPPORT_FRACTION * throughput.max())[0]
    edges = np.linspace(wavelength[inside[0]], wavelength[inside[-1]], n + 1)
    # Integrate on a fine grid so that bins narrower than the tabulation are still exact.
    fine = np.linspace(edges[0], edges[-1], 200 * n + 1)
    t_fine = np.interp(fine, wavelength, throughput)
    which = np.clip(np.searchsorted(edges, fine, side="right") - 1, 0, n - 1)
    weight = np.bincount(which, weights=t_fine, minlength=n)
    first_moment = np.bincount(which, weights=t_fine * fine, minlength=n)
    centroids = np.where(
        weight > 0, first_moment / np.where(weight > 0, weight, 1.0), 0.5 * (edges[:-1] + edges[1:])
    )
    return FilterBins(
        name=name,
        wavelengths_m=centroids,
        weights=weight / weight.sum(),
        edges_m=edges,
    )
