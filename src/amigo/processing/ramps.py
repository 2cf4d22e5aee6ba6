"""Raw ramps -> slopes: the only calibration amigo applies to raw data (paper, 'Data Processing
Pipeline').

For each pixel of an exposure of ``N`` integrations of ``G`` groups this module

1. corrects the ADC integral non-linearity: ``x = raw - 2 sin(2 pi raw / 1024)`` DN, with
   ``raw`` the raw count *including* the bias (the error is periodic in raw counts);
2. marks the groups that cannot be used: saturated (``raw >= saturation_dn``, or a GROUPDQ
   ``SATURATED`` flag), or flagged ``DO_NOT_USE`` / ``DROPOUT`` in GROUPDQ; such a group
   and every later group of that integration are dropped;
   optionally (``ProcessSettings.one_over_f = "stripes"``, the ``amigo process`` default)
   removes the 1/f column stripes, per integration and group difference, measured on the
   faint pixels (:func:`remove_stripes`; docs/process.md, "1/f noise");
3. rejects outliers along the integration axis, first on the ramps, group by group, then on
   the slopes (group differences), slope by slope, at ``nsigma`` robust standard deviations
   from a robust centre (median and 1.4826 x MAD). A rejected ramp value or slope removes
   the rest of that integration's ramp (see "The clipping rule" below);
4. averages the kept values over integrations and estimates the covariance of those means,
   for the ramps (``G`` values per pixel) and the slopes (``G - 1``), with support counts;
5. builds a bad-pixel map.

The clipping rule
-----------------
A cosmic ray adds a step to a ramp: every group after the hit is offset by the same amount.
The slope that straddles the hit is the one to reject, and all ramp values after it are
offset, so a rejected slope removes the rest of that integration's ramp (the paper's rule).
We apply the same rule to a rejected ramp value: a ramp value is an outlier when a large
step happened at or before that group, and the steps' later groups may fall back inside the
(wider, photon-noise-broadened) band of later groups, so keeping them would bias the ramp
means. The consequence, used throughout, is that **the kept groups of every integration
form a prefix** ``0 .. L_i - 1`` of its ramp (``0 <= L_i <= G``), and its kept slopes are
``0 .. L_i - 2``.

Means and covariance of the mean
--------------------------------
With pairwise deletion: for groups ``g, h`` let ``K_gh`` be the integrations where both are
kept (for prefixes, ``K_gh = K_max(g,h)``) and ``N_gh`` its size. Then::

    mean_g      = (1 / N_gg) sum_{K_gg} x_g
    C_gh        = sum_{K_gh} (x_g - m_g|h)(x_h - m_h|g) / (N_gh - 1)     (m_g|h: mean over K_gh)
    cov_mean_gh = C_gh N_gh / (N_gg N_hh)

which is the exact covariance of two sample means sharing ``N_gh`` integrations, given the
kept sets. Read noise makes adjacent slopes of one integration anti-correlated (``-sigma_read^2``),
so ``SLOPE_COV`` is a full matrix per pixel.

The clipping bands are centred on medians of the same data, so they move with it, and the
scatter of a clipped mean exceeds that formula: for a single band at 3 sigma by 5 % for
many integrations, and by 8-18 % in our 4-group simulations. :func:`clipping_influence`
adds this first-order effect (derived for Gaussian noise) to the reported covariances;
docs/process.md gives the derivation and the Monte Carlo check.

Streaming, and why it equals the in-memory algorithm
----------------------------------------------------
The only quantities that couple integrations are the clipping thresholds (per pixel, group
and slope: centre and scale), the 1/f :class:`StripeModel` when stripes are removed, and
the sums behind the means and covariances. We compute the stripe model and the thresholds
first, from a *threshold sample*: at most :attr:`ProcessSettings.max_sample_ints`
integrations spread evenly over the exposure (all of them when the exposure is small). Once
the thresholds are fixed, whether integration ``i`` keeps group ``g`` depends on integration
``i`` alone, so a second pass over the integrations, chunk by chunk, makes exactly the
decisions that an in-memory implementation with the same thresholds makes, and accumulates
the sums ``sum x_g``, ``sum x_g x_h`` and counts over the kept pairs. Sums are additive, so the
result equals the in-memory one up to floating-point rounding; to keep that rounding small
the values are accumulated relative to the clipping centre (shifted sums, no catastrophic
cancellation). Memory is ``O(G^2 x pixels)`` for the sums plus one chunk and the bounded
sample, independent of ``N``.

All array functions take and return NumPy arrays; axis 0 is the integration and axis 1 the
group, the last two are ``(ny, nx)`` (any trailing pixel shape works).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from amigo import niriss
from amigo.errors import InputError
from amigo.io.calslope import (
    BAD_DQ,
    BAD_LOW_SUPPORT,
    BAD_NO_NOISE,
    BAD_REASONS,
    BAD_REFERENCE,
    BAD_SATURATED,
    calslope_name,
    write_calslope,
)

# --------------------------------------------------------------------------------------
# Constants
# --------------------------------------------------------------------------------------

#: Period (raw counts) and amplitude (DN) of the ADC integral non-linearity.
#: Source: AMIGO paper, 'Data Processing Pipeline' (a 1024-count sinusoid of amplitude 2).
ADC_PERIOD_DN: float = 1024.0
ADC_AMPLITUDE_DN: float = 2.0

#: 1 / Phi^-1(3/4): turns a median absolute deviation into a Gaussian standard deviation.
MAD_TO_SIGMA: float = 1.482602218505602

#: Small-sample consistency factors of 1.4826 MAD for n = 2..9 values (Croux & Rousseeuw
#: 1992, "Time-efficient algorithms for two highly robust estimators of scale"); beyond 9,
#: n / (n - 0.8). Without them a handful of integrations gives a scale ~20 % too small and
#: clips good data at ~2.5 sigma. tests/test_process.py checks them by Monte Carlo.
MAD_SMALL_SAMPLE_FACTOR: dict[int, float] = {
    2: 1.196,
    3: 1.495,
    4: 1.363,
    5: 1.206,
    6: 1.200,
    7: 1.140,
    8: 1.129,
    9: 1.107,
}


def mad_consistency_factor(n: np.ndarray) -> np.ndarray:
    """Factor making ``1.4826 MAD`` of ``n`` Gaussian values unbiased for sigma (1 for n<2)."""
    n = np.asarray(n, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(n > 9, n / (n - 0.8), 1.0)
    for count, value in MAD_SMALL_SAMPLE_FACTOR.items():
        factor = np.where(n == count, value, factor)
    return factor


#: Floor of the robust scale (DN). Raw counts are integers: when more than half of the
#: values of a pixel are equal (very low noise, or few integrations) the MAD is zero, and a
#: tiny scale would reject values that differ from the median by a count or two.
MIN_SCALE_DN: float = 1.0

#: Default saturation level (raw DN). No saturation reference file is available offline
#: (see jwst-formats-and-stack notes), so the only certain saturation is the ADC full scale.
SATURATION_DN: float = 65535.0

#: JWST DQ bits (JWST pipeline definitions).
DQ_DO_NOT_USE: int = 1
DQ_SATURATED: int = 2
DQ_DROPOUT: int = 8
#: GROUPDQ bits that make a group unusable (JUMP_DET is ignored: we find jumps ourselves).
GROUP_DQ_EXCLUDE: int = DQ_DO_NOT_USE | DQ_SATURATED | DQ_DROPOUT

#: Treatments of 1/f noise (:attr:`ProcessSettings.one_over_f`, ``--one-over-f``):
#: ``stripes`` removes each column's offset per integration and group difference
#: (:func:`remove_stripes`), ``none`` leaves the data alone.
ONE_OVER_F_METHODS: tuple[str, ...] = ("none", "stripes")

#: A pixel is a stripe pixel (used to measure its column's 1/f offset) when it is a
#: reference row or its slope (median over the threshold sample, DN per group) is below
#: this. Its signal must be the same in every group difference; the quadratic
#: non-linearity changes a 20 DN/group slope by ~0.01 DN/group over 10 groups.
STRIPE_MAX_SIGNAL_DN: float = 20.0
#: A stripe pixel is left out of an integration's estimate when one of its mean-free
#: slopes lies further than this many of its noise scales from a first estimate of its
#: column's offsets (cosmic rays, telegraph noise) ...
STRIPE_NSIGMA: float = 4.0
#: ... and out of that first estimate when one lies further than this many scales (the
#: stripes included) from zero.
STRIPE_OUTLIER_NSIGMA: float = 8.0
#: Fewest stripe pixels for a column's own estimate; a column with fewer, in some
#: integration, takes the mean of the other columns' offsets (the frame's common mode).
STRIPE_MIN_PIXELS: int = 3
#: Stripe pixels noisier than this times the median of their noise scales (hot, noisy or
#: telegraph pixels) are not used.
STRIPE_MAX_NOISE_RATIO: float = 2.0
#: Integrations of the threshold sample (evenly spread) that :func:`fit_stripe_model`
#: uses: enough for the pixels' scales (MAD of >= 100 values) and the stripes' variance
#: (pooled over all columns), and a bounded cost.
STRIPE_FIT_INTS: int = 100


@dataclass(frozen=True)
class ProcessSettings:
    """Options of the ramp processing (defaults are the paper's).

    Attributes
    ----------
    nsigma
        Clipping threshold in robust standard deviations.
    adc_correction
        Subtract the ADC integral non-linearity sinusoid.
    saturation_dn
        Raw count at and above which a group is saturated.
    min_support
        A pixel is bad when a slope is kept in fewer integrations than
        ``max(min_support, ceil(min_support_fraction * NINTS))``.
    min_support_fraction
        See ``min_support``; a pixel that loses most of its integrations to clipping is
        not behaving like the others (telegraph noise, hot pixel).
    max_saturated_fraction
        A pixel is bad when more than this fraction of its integrations saturate (its
        later-group means would be censored, hence biased); isolated saturations (cosmic
        rays) only drop the rest of their integration.
    max_sample_ints, max_sample_values
        Bounds of the threshold sample: at most this many integrations, and at most this
        many values in all (ints x groups x pixels, float64).
    chunk_values
        Values (ints x groups x pixels) read and processed at a time in the streaming pass.
    covariance_correction
        Add the first-order effect of the data-derived clipping bands to the covariances
        (:func:`clipping_influence`); ``False`` gives the plain covariance of the kept
        values (the paper's estimator, 8-18 % too small in our simulations).
    one_over_f
        Treatment of 1/f noise, one of :data:`ONE_OVER_F_METHODS`: ``"stripes"`` removes
        the column stripes before clipping (:func:`remove_stripes`, docs/process.md
        "1/f noise"). The library default ``"none"`` keeps earlier results unchanged;
        ``amigo process`` defaults to ``"stripes"``.
    stripe_max_signal_dn
        Slope (DN per group) below which a pixel helps measure its column's stripes.
    """

    nsigma: float = 3.0
    adc_correction: bool = True
    saturation_dn: float = SATURATION_DN
    min_support: int = 3
    min_support_fraction: float = 0.5
    max_saturated_fraction: float = 0.01
    max_sample_ints: int = 1024
    max_sample_values: int = 2**23
    chunk_values: int = 2**22
    covariance_correction: bool = True
    one_over_f: str = "none"
    stripe_max_signal_dn: float = STRIPE_MAX_SIGNAL_DN

    def header_cards(self) -> dict[str, tuple[Any, str]]:
        """What a calslope file records of these settings (keyword -> (value, comment)):
        a re-run keeps a product whose header holds the same values
        (:func:`amigo.io.calslope.is_up_to_date`)."""
        return {
            "ADC_CORR": (bool(self.adc_correction), "ADC integral non-linearity corrected"),
            "NSIGCLIP": (float(self.nsigma), "outlier clipping threshold (robust sigma)"),
            "SATLEVEL": (float(self.saturation_dn), "[DN] raw saturation level"),
            "ONEOVERF": (self.one_over_f, "1/f noise: stripes removed, or none"),
        }

    def __post_init__(self) -> None:
        if self.one_over_f not in ONE_OVER_F_METHODS:
            raise ValueError(
                f"one_over_f must be one of {', '.join(ONE_OVER_F_METHODS)}, "
                f"got {self.one_over_f!r}"
            )
        if not self.nsigma > 0:
            raise ValueError(f"nsigma must be positive, got {self.nsigma}")
        if self.min_support < 2:
            raise ValueError("min_support must be >= 2 (a variance needs two values)")
        if self.max_sample_ints < 1 or self.max_sample_values < 1 or self.chunk_values < 1:
            raise ValueError("sample and chunk sizes must be positive")

    def required_support(self, nints: int) -> int:
        """The minimum number of integrations a slope must keep for its pixel to be good."""
        return max(self.min_support, math.ceil(self.min_support_fraction * nints))


# --------------------------------------------------------------------------------------
# Pure array functions
# --------------------------------------------------------------------------------------


def adc_nonlinearity_dn(raw_dn: np.ndarray) -> np.ndarray:
    """ADC integral non-linearity ``2 sin(2 pi raw / 1024)`` (DN) at raw counts ``raw_dn``.

    Whole-number raw counts (the normal case, even as floats) go through a 1024-entry
    table, several times faster than ``np.sin`` on large arrays and equal to it to rounding.
    """
    raw = np.asarray(raw_dn)
    period = int(ADC_PERIOD_DN)
    table = ADC_AMPLITUDE_DN * np.sin(2.0 * np.pi / ADC_PERIOD_DN * np.arange(period))
    if raw.dtype.kind in "iu":
        return table[np.bitwise_and(raw.astype(np.int64), period - 1)]
    if raw.dtype.kind == "f" and raw.size and np.all(np.abs(raw) < 2.0**52):
        counts = raw.astype(np.int64)
        if np.array_equal(counts, raw):
            # Two's complement makes "& 1023" the floor modulo, right for negatives too.
            return table[np.bitwise_and(counts, period - 1)]
    return ADC_AMPLITUDE_DN * np.sin(2.0 * np.pi / ADC_PERIOD_DN * raw)


def correct_adc(raw_dn: np.ndarray) -> np.ndarray:
    """Raw counts corrected for the ADC integral non-linearity (float64, DN)."""
    raw = np.asarray(raw_dn, dtype=np.float64)
    return raw - adc_nonlinearity_dn(raw)


def keep_prefix(mask: np.ndarray, axis: int = 1) -> np.ndarray:
    """``mask`` with everything after the first False along ``axis`` set False too."""
    out = np.array(mask, dtype=bool)  # a copy
    view = np.moveaxis(out, axis, 0)
    # A loop over the (few) groups is much faster than np.logical_and.accumulate here.
    for index in range(1, view.shape[0]):
        view[index] &= view[index - 1]
    return out


def usable_groups(
    raw_dn: np.ndarray, saturation_dn: float = SATURATION_DN, group_dq: np.ndarray | None = None
) -> np.ndarray:
    """Groups that may be used, before any clipping: (n, G, ...) bool, a prefix per ramp.

    A group is unusable when it is saturated (``raw >= saturation_dn`` or GROUPDQ
    SATURATED), flagged DO_NOT_USE or DROPOUT in GROUPDQ, or not finite; it and every later
    group of its integration are dropped.
    """
    raw = np.asarray(raw_dn)
    ok = np.isfinite(raw) & (raw < saturation_dn)
    if group_dq is not None:
        ok &= (np.asarray(group_dq).astype(np.uint32) & GROUP_DQ_EXCLUDE) == 0
    return keep_prefix(ok, axis=1)


def saturated_integrations(
    raw_dn: np.ndarray, saturation_dn: float = SATURATION_DN, group_dq: np.ndarray | None = None
) -> np.ndarray:
    """(n, ...) bool: integrations in which some group of the pixel is saturated."""
    saturated = np.asarray(raw_dn) >= saturation_dn
    if group_dq is not None:
        saturated |= (np.asarray(group_dq).astype(np.uint32) & DQ_SATURATED) != 0
    return np.asarray(saturated.any(axis=1))


def robust_centre_scale(values: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median and Gaussian-equivalent scale (1.4826 MAD, small-sample corrected) along axis 0.

    Parameters
    ----------
    values, mask
        (n, ...) arrays; only entries with ``mask`` True count.

    Returns
    -------
    centre, scale
        (...) arrays; NaN where no value is kept. The scale is floored at
        :data:`MIN_SCALE_DN`.
    """
    values = np.asarray(values, dtype=np.float64)
    masked = np.where(mask, values, np.nan)
    with np.errstate(invalid="ignore"):
        centre = _nanmedian0(masked)
        count = np.sum(mask, axis=0)
        scale = MAD_TO_SIGMA * mad_consistency_factor(count) * _nanmedian0(np.abs(masked - centre))
    return centre, np.maximum(scale, MIN_SCALE_DN, where=np.isfinite(scale), out=scale)


def _nanmedian0(values: np.ndarray) -> np.ndarray:
    """Median along axis 0 ignoring NaN; NaN where a column is all NaN.

    Sorting puts NaN last, so the median of the ``k`` finite values of a column sits at
    ranks ``(k - 1) // 2`` and ``k // 2``; faster than ``np.nanmedian`` on wide arrays.
    """
    n = values.shape[0]
    flat = values.reshape(n, -1).T  # (pixels, n): sort contiguous rows
    ordered = np.sort(flat, axis=1)
    count = np.sum(np.isfinite(flat), axis=1)
    lo = np.clip((count - 1) // 2, 0, max(n - 1, 0))
    hi = np.clip(count // 2, 0, max(n - 1, 0))
    rows = np.arange(flat.shape[0])
    median = 0.5 * (ordered[rows, lo] + ordered[rows, hi])
    median[count == 0] = np.nan
    return median.reshape(values.shape[1:])


@dataclass(frozen=True)
class ClipThresholds:
    """Per-pixel clipping bands (DN): keep ``|x - centre| <= nsigma * scale``.

    Attributes
    ----------
    ramp_centre_dn, ramp_scale_dn
        (G, ny, nx) for the ADC-corrected ramp values of each group.
    slope_centre_dn, slope_scale_dn
        (G - 1, ny, nx) for the group differences.
    nsigma
        The clipping threshold in scales.
    """

    ramp_centre_dn: np.ndarray
    ramp_scale_dn: np.ndarray
    slope_centre_dn: np.ndarray
    slope_scale_dn: np.ndarray
    nsigma: float


def _inside(values: np.ndarray, centre: np.ndarray, scale: np.ndarray, nsigma: float) -> np.ndarray:
    """``|values - centre| <= nsigma * scale``; a NaN band (no data to set it) keeps nothing."""
    half_width = nsigma * scale
    # Two comparisons with precomputed edges: cheaper than |values - centre| on big chunks.
    return (values >= centre - half_width) & (values <= centre + half_width)


def clip_ramps(
    ramps_dn: np.ndarray, usable: np.ndarray, centre: np.ndarray, scale: np.ndarray, nsigma: float
) -> np.ndarray:
    """Stage 1: keep usable ramp values inside their group's band; a prefix per ramp.

    ``ramps_dn`` and ``usable`` are (n, G, ...); ``centre`` and ``scale`` are (G, ...).
    """
    return keep_prefix(usable & _inside(ramps_dn, centre, scale, nsigma), axis=1)


def clip_slopes(
    ramps_dn: np.ndarray,
    keep: np.ndarray,
    centre: np.ndarray,
    scale: np.ndarray,
    nsigma: float,
    slopes_dn: np.ndarray | None = None,
) -> np.ndarray:
    """Stage 2: a slope outside its band drops the rest of the ramp after it.

    Parameters
    ----------
    ramps_dn, keep
        (n, G, ...): ADC-corrected ramps and the stage-1 prefix mask.
    centre, scale
        (G - 1, ...) slope bands.
    slopes_dn
        ``np.diff(ramps_dn, axis=1)`` if the caller has it already.

    Returns
    -------
    (n, G, ...) bool prefix mask: group ``g + 1`` and later are dropped when slope ``g``
    (= group ``g + 1`` minus group ``g``) is kept by stage 1 but outside its band.
    """
    slopes = np.diff(ramps_dn, axis=1) if slopes_dn is None else slopes_dn
    rejected = keep[:, 1:] & ~_inside(slopes, centre, scale, nsigma)
    out = keep.copy()
    # A rejected slope k drops groups k+1.. : keep the prefix of "no rejection so far".
    out[:, 1:] &= keep_prefix(~rejected, axis=1)
    return out


def clip(ramps_dn: np.ndarray, usable: np.ndarray, thresholds: ClipThresholds) -> np.ndarray:
    """Both clipping stages: (n, G, ...) bool, True where a ramp value is kept.

    The slopes kept are ``keep[:, 1:]`` (slope ``g`` needs groups ``g`` and ``g + 1``,
    and kept groups form a prefix).
    """
    t = thresholds
    keep = clip_ramps(ramps_dn, usable, t.ramp_centre_dn, t.ramp_scale_dn, t.nsigma)
    return clip_slopes(ramps_dn, keep, t.slope_centre_dn, t.slope_scale_dn, t.nsigma)


def estimate_thresholds(ramps_dn: np.ndarray, usable: np.ndarray, nsigma: float) -> ClipThresholds:
    """Robust clipping bands from a sample of integrations.

    The ramp bands come from the usable ramp values; the slope bands from the slopes that
    survive stage 1 (the same order as the clipping itself).

    Parameters
    ----------
    ramps_dn, usable
        (n, G, ...) ADC-corrected ramps of the sample and their usable-group mask.
    """
    ramp_centre, ramp_scale = robust_centre_scale(ramps_dn, usable)
    keep = clip_ramps(ramps_dn, usable, ramp_centre, ramp_scale, nsigma)
    slope_centre, slope_scale = robust_centre_scale(np.diff(ramps_dn, axis=1), keep[:, 1:])
    return ClipThresholds(ramp_centre, ramp_scale, slope_centre, slope_scale, float(nsigma))


class MomentSums:
    """Running sums for means and pairwise-deletion covariances of ``k`` variables per pixel.

    Values are accumulated relative to a fixed ``shift`` (the clipping centre), which
    changes nothing in exact arithmetic and keeps ``sum x^2`` from swamping the variance.

    Parameters
    ----------
    shift
        (k, ...) per-variable offsets (DN); NaN entries are treated as 0.
    """

    def __init__(self, shift: np.ndarray) -> None:
        shift = np.nan_to_num(np.asarray(shift, dtype=np.float64))
        self.shift = shift
        k, pixel_shape = shift.shape[0], shift.shape[1:]
        self._pixel_shape = pixel_shape
        npix = int(np.prod(pixel_shape))
        # s1[g, h] = sum over K_gh of (x_g - shift_g); s2[g, h] = sum over K_gh of products.
        self.s1 = np.zeros((k, k, npix))
        self.s2 = np.zeros((k, k, npix))
        self.n = np.zeros((k, k, npix))

    def add(self, values: np.ndarray, keep: np.ndarray) -> None:
        """Add integrations: ``values`` and ``keep`` are (n, k, ...)."""
        n, k = values.shape[:2]
        npix = self.n.shape[-1]  # explicit: k may be 0 (one group has no slope)
        x = np.where(keep, values - self.shift, 0.0).reshape(n, k, npix)
        w = keep.reshape(n, k, npix).astype(np.float64)
        self.s1 += np.einsum("igp,ihp->ghp", x, w)
        self.s2 += np.einsum("igp,ihp->ghp", x, x)
        self.n += np.einsum("igp,ihp->ghp", w, w)

    def result(self) -> Moments:
        """Means, covariances and supports of the kept values (see :class:`Moments`)."""
        k = self.s1.shape[0]
        diag = np.arange(k)
        n_pair = self.n
        n_var = n_pair[diag, diag]
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.s1[diag, diag] / n_var + self.shift.reshape(k, self.n.shape[-1])
            # Co-moment over K_gh with pairwise means: s2 - s1[g|h] s1[h|g] / N_gh.
            comoment = self.s2 - self.s1 * np.swapaxes(self.s1, 0, 1) / n_pair
            cov = comoment / (n_pair - 1.0)
        mean[n_var < 1] = np.nan
        cov[n_pair < 2] = np.nan
        shape = self._pixel_shape
        return Moments(
            mean.reshape(k, *shape), cov.reshape(k, k, *shape), n_pair.reshape(k, k, *shape)
        )


@dataclass(frozen=True)
class Moments:
    """Statistics of ``k`` variables per pixel over the kept integrations.

    Attributes
    ----------
    mean
        (k, ...) means, DN; NaN where nothing was kept.
    cov
        (k, k, ...) covariance between integrations (pairwise deletion), DN^2; NaN where a
        pair was kept in fewer than 2 integrations.
    n_pair
        (k, k, ...) integrations in which both variables were kept.
    """

    mean: np.ndarray
    cov: np.ndarray
    n_pair: np.ndarray

    @property
    def support(self) -> np.ndarray:
        """(k, ...) integrations kept for each variable."""
        return np.diagonal(self.n_pair, axis1=0, axis2=1).transpose(-1, *range(self.mean.ndim - 1))

    def cov_of_mean(self) -> np.ndarray:
        """(k, k, ...) covariance of the means given the kept sets: ``C_gh N_gh/(N_g N_h)``."""
        n = self.support
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.cov * self.n_pair / (n[:, None] * n[None, :])


# --------------------------------------------------------------------------------------
# The clipping-influence correction of the covariance
# --------------------------------------------------------------------------------------

#: Relative standard deviation of 1.4826 MAD for Gaussian data, times sqrt(n): the MAD has
#: an asymptotic efficiency of 36.75 %, so sd(s)/sigma = 1 / sqrt(2 x 0.3675 n).
MAD_RELATIVE_SD_SQRT_N: float = 1.1664


def edge_density_factor(nsigma: float, n_sample: int) -> float:
    """``E[2 k u phi(k u)]`` for ``u`` the estimated/true scale ratio of an ``n``-sample MAD.

    ``2 k phi(k)`` is the rate at which the sum of the kept standardised values of a
    Gaussian moves when a clipping band at ``+-k`` moves (mass ``phi(k)`` gained at one
    edge at value ``k``, lost at the other at ``-k``). The band half-width is ``k s`` with
    ``s`` estimated from ``n`` values, so the effective ``k`` is ``k u``,
    ``u ~ N(1, (1.1664 / sqrt(n))^2)``; we average over ``u`` (Gauss-Hermite). The average
    exceeds ``2 k phi(k)`` noticeably for small ``n`` (0.051 at n = 40 vs 0.027 for k = 3).
    """
    nodes, weights = np.polynomial.hermite_e.hermegauss(40)
    ku = nsigma * np.abs(1.0 + MAD_RELATIVE_SD_SQRT_N / math.sqrt(max(n_sample, 1)) * nodes)
    density = np.exp(-0.5 * ku**2) / math.sqrt(2.0 * math.pi)
    return float(np.sum(weights * 2.0 * ku * density) / np.sum(weights))


def _window_structure(ngroups: int) -> tuple[np.ndarray, np.ndarray]:
    """The 2G-1 clipping variables (G ramps then G-1 slopes) as rows of a map from the ramp,
    and which variables each one's band can remove (``affects[v, w]``: band ``w`` drops
    variable ``v``)."""
    eye = np.eye(ngroups)
    to_ramp = np.vstack([eye, np.diff(eye, axis=0)])  # (2G-1, G)
    nw = 2 * ngroups - 1
    # First ramp group / slope that a rejection by band w removes from its integration.
    first_ramp = [g for g in range(ngroups)] + [k + 1 for k in range(ngroups - 1)]
    first_slope = [g - 1 for g in range(ngroups)] + [k for k in range(ngroups - 1)]
    affects = np.zeros((nw, nw), dtype=bool)
    for w in range(nw):
        for v in range(nw):
            affects[v, w] = v >= first_ramp[w] if v < ngroups else v - ngroups >= first_slope[w]
    return to_ramp, affects


def nearest_psd(cov: np.ndarray) -> np.ndarray:
    """Each (k, k) matrix of ``cov`` (..., k, k) with its negative eigenvalues set to zero.

    Pairwise deletion estimates each element from its own set of integrations, so with few
    integrations the matrix need not be positive semi-definite, and a slope variance
    derived from it (``C_gg + C_hh - 2 C_gh``) can come out negative. Matrices with a
    non-finite element are returned unchanged (NaN stays NaN).
    """
    out = np.array(cov, dtype=np.float64, copy=True)
    finite = np.all(np.isfinite(out), axis=(-2, -1))
    if np.any(finite):
        sym = 0.5 * (out[finite] + np.swapaxes(out[finite], -1, -2))
        values, vectors = np.linalg.eigh(sym)
        out[finite] = (vectors * np.maximum(values, 0.0)[..., None, :]) @ np.swapaxes(
            vectors, -1, -2
        )
    return out


def clipping_influence(
    ramp_cov_dn2: np.ndarray, nints: int, n_sample: int, nsigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Extra covariance of the clipped means caused by data-derived clipping bands.

    The bands are centred on medians of the same data, so they move with it: when the
    median of a variable is high, its band keeps more high values (and, through the
    rest-of-ramp rule, more high values of every later variable). To first order the clipped
    means are ``T_v = mu_v + e_v + sum_w D_vw dc_w`` with ``e_v`` the error of the mean of
    the kept values (the plain covariance), ``dc_w`` the error of the median of band ``w``
    and, for Gaussian data, ``D_vw = E[2 k u phi(k u)] Sigma_vw / Sigma_ww`` when band
    ``w`` can remove variable ``v`` (0 otherwise). With ``Cov(e_v, dc_w) = Sigma_vw / N``
    and ``Cov(dc_w, dc_w') = sigma_w sigma_w' arcsin(rho_ww') / n`` (medians of ``n``
    sample integrations), the added covariance is::

        Delta = (D Sigma + Sigma D^T) / N + D R D^T / n,   R_ww' = sigma_w sigma_w' arcsin(rho)

    Without it the covariance of the mean is too small: by 5 % for one band and many
    integrations, by 8-18 % for 4 groups (N = 40 and 300); tests/test_process.py checks the
    corrected value
    against the scatter of the means over many realisations.

    ``Sigma`` is built from the nearest positive semi-definite version of ``ramp_cov_dn2``
    (:func:`nearest_psd`): pairwise deletion does not guarantee one, and with few
    integrations a negative implied slope variance would make the term NaN.

    Parameters
    ----------
    ramp_cov_dn2
        (G, G, ...) covariance between integrations of the ADC-corrected ramp values.
    nints, n_sample
        Integrations in the exposure and in the threshold sample.
    nsigma
        The clipping threshold.

    Returns
    -------
    delta_ramp, delta_slope
        (G, G, ...) and (G-1, G-1, ...) to add to the covariances of the ramp and slope
        means. NaN where ``ramp_cov_dn2`` is undefined.
    """
    ngroups = ramp_cov_dn2.shape[0]
    pixel_shape = ramp_cov_dn2.shape[2:]
    to_ramp, affects = _window_structure(ngroups)
    cov_r = nearest_psd(np.moveaxis(ramp_cov_dn2.reshape(ngroups, ngroups, -1), -1, 0))
    sigma = to_ramp @ cov_r @ to_ramp.T  # (P, W, W) joint covariance of all bands' variables
    var = np.diagonal(sigma, axis1=1, axis2=2)  # (P, W)
    # A variable without spread (a rank-deficient estimate from two or three integrations)
    # has a band that moves nothing: zero influence and zero correlation, not 0 / 0.
    spread = var > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        safe_var = np.where(spread, var, np.inf)
        influence = edge_density_factor(nsigma, n_sample) * sigma / safe_var[:, None, :] * affects
        sd = np.sqrt(np.where(spread, var, 0.0))
        both = spread[:, :, None] & spread[:, None, :]
        rho = np.where(both, sigma / np.where(both, sd[:, :, None] * sd[:, None, :], 1.0), 0.0)
        rho = np.clip(rho, -1.0, 1.0)
        r = sd[:, :, None] * sd[:, None, :] * np.arcsin(rho)
        cross = influence @ sigma
        delta = (cross + np.swapaxes(cross, 1, 2)) / nints
        delta += influence @ r @ np.swapaxes(influence, 1, 2) / max(n_sample, 1)
    delta = np.moveaxis(delta, 0, -1)
    return (
        delta[:ngroups, :ngroups].reshape(ngroups, ngroups, *pixel_shape),
        delta[ngroups:, ngroups:].reshape(ngroups - 1, ngroups - 1, *pixel_shape),
    )


# --------------------------------------------------------------------------------------
# 1/f noise: column stripes
# --------------------------------------------------------------------------------------


def _mean_free(slopes_dn: np.ndarray) -> np.ndarray:
    """Each pixel's group differences minus their mean over the differences (axis 1)."""
    return slopes_dn - slopes_dn.mean(axis=1, keepdims=True)


def _pixel_scale(values: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """(ny, nx) Gaussian-equivalent scale (1.4826 MAD) of a pixel's ``values`` (n, k, ny,
    nx) over the integrations where ``ok`` (n, ny, nx); NaN where none. Not floored."""
    n, k = values.shape[:2]
    masked = np.where(ok[:, None], values, np.nan).reshape(n * k, *values.shape[2:])
    with np.errstate(invalid="ignore"):
        centre = _nanmedian0(masked)
        count = np.sum(np.isfinite(masked), axis=0)
        return MAD_TO_SIGMA * mad_consistency_factor(count) * _nanmedian0(np.abs(masked - centre))


def stripe_offsets(
    slopes_dn: np.ndarray,
    pixel_ok: np.ndarray,
    weight: np.ndarray,
    scale_dn: np.ndarray,
    limit_dn: np.ndarray,
    nsigma: float = STRIPE_NSIGMA,
    min_pixels: int = STRIPE_MIN_PIXELS,
) -> tuple[np.ndarray, np.ndarray]:
    """Measure the 1/f offset of every column, per integration and group difference.

    SUB80 is read column by column, so 1/f noise adds one offset per column, group and
    integration: vertical stripes. A pixel's signal is the same in every group difference
    of an integration, so its differences minus their mean over the differences (its
    *mean-free slopes*) hold no signal, only noise and its column's offsets minus their
    mean over the differences. A column's offsets are the weighted mean of the mean-free
    slopes of its stripe pixels, computed twice: first over the pixels whose mean-free
    slopes all lie within ``limit_dn`` of zero (gross outliers out), then over those whose
    mean-free slopes all lie within ``nsigma * scale_dn`` of the first mean. The offsets'
    own mean over the differences, ``(f[G-1] - f[0]) / (G - 1)`` for per-group offsets
    ``f``, cannot be measured this way.

    Parameters
    ----------
    slopes_dn
        (n, G-1, ny, nx) group differences of the ADC-corrected ramps, DN per group.
    pixel_ok
        (n, ny, nx) bool: every group of the pixel is usable in that integration.
    weight
        (ny, nx) weight of each stripe pixel, DN^-2 (0: not one).
    scale_dn
        (ny, nx) noise scale of each stripe pixel's mean-free slopes, DN per group.
    limit_dn
        (ny, nx) largest mean-free slope (absolute, DN per group) of a pixel in the first
        mean; it must allow for the stripes themselves.
    nsigma
        Clipping threshold of the second mean, in ``scale_dn``.
    min_pixels
        Fewest kept pixels for a column's own estimate.

    Returns
    -------
    offsets
        (n, G-1, nx) column offsets, DN per group, summing to zero over the differences.
        A column with fewer than ``min_pixels`` kept pixels in an integration gets the
        mean of the other columns' offsets (the frame's common mode; 0 if there are none).
    keep
        (n, ny, nx) bool: the pixels each integration's offsets were computed from.
    """
    slopes = np.asarray(slopes_dn, dtype=np.float64)
    use = np.asarray(pixel_ok, dtype=bool) & (np.asarray(weight) > 0)[None]
    free = _mean_free(slopes)  # a new array: modified in place below
    np.copyto(free, 0.0, where=~use[:, None])  # no NaN from unused pixels

    def average(keep: np.ndarray) -> np.ndarray:
        w = np.where(keep, weight, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.einsum("iyx,ikyx->ikx", w, free) / w.sum(axis=1)[:, None]

    work = np.abs(free)
    keep = use & np.all(work <= limit_dn, axis=1)
    first = np.nan_to_num(average(keep))
    np.subtract(free, first[:, :, None, :], out=work)
    with np.errstate(invalid="ignore"):
        keep &= np.all(np.abs(work, out=work) <= nsigma * scale_dn, axis=1)
    offsets = average(keep)
    own = keep.sum(axis=1) >= max(int(min_pixels), 2)  # (n, nx)
    n_own = own.sum(axis=1)
    common = np.where(own[:, None], offsets, 0.0).sum(axis=2) / np.maximum(n_own, 1)[:, None]
    return np.where(own[:, None], offsets, common[:, :, None]), keep


@dataclass(frozen=True)
class StripeModel:
    """What :func:`remove_stripes` needs to know about an exposure (from the threshold
    sample, :func:`fit_stripe_model`).

    Attributes
    ----------
    weight
        (ny, nx) weights of the stripe pixels, DN^-2: one over the square of their median
        noise scale (0: not a stripe pixel).
    scale_dn
        (ny, nx) noise scale of each pixel's mean-free slopes once the stripes are
        removed, DN per group (for the clipping).
    limit_dn
        (ny, nx) first-pass limit of :func:`stripe_offsets`: :data:`STRIPE_OUTLIER_NSIGMA`
        times the scale of the mean-free slopes with the stripes in, DN per group.
    gain
        (nx,) factor applied to each column's measured offsets (0: nothing removed).
    variance_dn2
        Variance of the true column offsets (mean-free, per difference) estimated from
        the sample, pooled over columns and differences, DN^2; 0 when none is detected.
    noise_dn2
        (nx,) mean variance of each column's measured offsets, DN^2 (NaN: not measured).
    """

    weight: np.ndarray
    scale_dn: np.ndarray
    limit_dn: np.ndarray
    gain: np.ndarray
    variance_dn2: float
    noise_dn2: np.ndarray

    @property
    def active(self) -> bool:
        """Whether :func:`remove_stripes` changes anything."""
        return bool(np.any(self.gain > 0))

    @property
    def pixels_per_column(self) -> np.ndarray:
        """(nx,) stripe pixels in each column."""
        return np.count_nonzero(self.weight > 0, axis=0)


def fit_stripe_model(
    ramps_dn: np.ndarray,
    usable: np.ndarray,
    max_signal_dn: float = STRIPE_MAX_SIGNAL_DN,
    nsigma: float = STRIPE_NSIGMA,
) -> StripeModel:
    """Choose the stripe pixels and the gains of :func:`remove_stripes` from a sample.

    Stripe pixels are the reference rows and the pixels whose slope (the median over the
    sample of the mean group difference) is below ``max_signal_dn``, and whose ``scale``,
    the robust scale of the pixel's mean-free slopes once its column's offsets are removed
    (1.4826 MAD over the sample), is at least :data:`MIN_SCALE_DN` (not dead) and at most
    :data:`STRIPE_MAX_NOISE_RATIO` times the median (not hot or noisy). They all get the
    same weight, ``1 / median scale^2``: their noise is the read noise give or take a few
    per cent, and weights from each pixel's own scale, estimated from the same sample, are
    noisy enough (20 % in scale for 30 integrations of 3 groups) to make the weighted
    mean noisier than equal weights and its noise estimate too small by as much.

    Each column's measured offset ``c = t + e`` is the true offset ``t`` plus the noise
    ``e`` of the average; the gain ``var(t) / (var(t) + var(e))`` (the Wiener factor)
    minimises the error of the removed ``gain * c``: close to 1 when the stripes dominate,
    0 when there are none (nothing is then removed). ``var(e)`` is the variance of the
    mean from the spread of the kept pixels about it (mean over the sample integrations),
    ``var(t)`` the variance of ``c`` over the sample integrations minus ``var(e)``, pooled
    over columns and differences. A column never measured gets the median gain.

    At most :data:`STRIPE_FIT_INTS` integrations of the sample, evenly spread, are used.

    Parameters
    ----------
    ramps_dn, usable
        (n, G, ny, nx) ADC-corrected ramps of the sample (DN) and their usable-group mask.
    max_signal_dn
        Slope (DN per group) below which a pixel is a stripe pixel.
    nsigma
        Clipping threshold of :func:`stripe_offsets`.

    Returns
    -------
    StripeModel
        Inactive (all gains 0) with fewer than 3 groups (one difference: no mean-free
        slope) or fewer than 2 sample integrations.
    """
    ramps = np.asarray(ramps_dn, dtype=np.float64)
    n, ngroups, ny, nx = ramps.shape
    nan_map = np.full((ny, nx), np.nan)
    inactive = StripeModel(np.zeros((ny, nx)), nan_map, nan_map, np.zeros(nx), 0.0, nan_map[0])
    if ngroups < 3 or n < 2:
        return inactive
    rows = np.unique(np.round(np.linspace(0, n - 1, min(n, STRIPE_FIT_INTS))).astype(np.int64))
    n = rows.size
    slopes = np.diff(ramps[rows], axis=1)
    full = np.asarray(usable, dtype=bool)[rows, -1]  # usable groups form a prefix
    with np.errstate(invalid="ignore"):
        level = _nanmedian0(np.where(full, slopes.mean(axis=1), np.nan))
        candidate = np.isfinite(level) & (
            niriss.reference_row_mask(ny, nx) | (level < max_signal_dn)
        )
    free = _mean_free(slopes)

    def weights(scale: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            live = candidate & (scale >= MIN_SCALE_DN)
            if not np.any(live):
                return np.zeros((ny, nx))
            typical = float(np.median(scale[live]))
            live &= scale <= STRIPE_MAX_NOISE_RATIO * typical
        return np.where(live, 1.0 / typical**2, 0.0)

    # The first scale includes the stripes (common to a column): it sets the outlier
    # limit, and weights and clips a first estimate, which is removed for the final scale.
    scale_all = _pixel_scale(free, full)
    limit = STRIPE_OUTLIER_NSIGMA * scale_all
    offsets, _ = stripe_offsets(slopes, full, weights(scale_all), scale_all, limit, nsigma)
    scale = _pixel_scale(free - offsets[:, :, None, :], full)
    weight = weights(scale)
    offsets, keep = stripe_offsets(slopes, full, weight, scale, limit, nsigma)

    # Variance of each column's estimate from the spread of its n kept pixels about it,
    # sum w^2 (x - c)^2 / (sum w)^2 x n / (n - 1), averaged over the differences.
    w = np.where(keep, weight, 0.0)
    count = keep.sum(axis=1)  # (n, nx)
    own = count >= max(STRIPE_MIN_PIXELS, 2)
    resid = np.where(keep[:, None], free - offsets[:, :, None, :], 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        noise = (
            np.einsum("iyx,ikyx->ix", w**2, resid**2)
            / w.sum(axis=1) ** 2
            * count
            / ((ngroups - 1) * (count - 1))
        )
    n_own = own.sum(axis=0)  # (nx,)
    measured = n_own >= 2
    if not np.any(measured):
        return inactive
    values = np.where(own[:, None], offsets, 0.0)[:, :, measured]  # (n, G-1, m)
    mask = own[:, None, measured]
    mean = values.sum(axis=0) / n_own[measured]
    var = (((values - mean) * mask) ** 2).sum(axis=0) / (n_own[measured] - 1)  # (G-1, m)
    noise_col = np.full(nx, np.nan)
    noise_col[measured] = np.where(own, noise, 0.0).sum(axis=0)[measured] / n_own[measured]
    variance = max(0.0, float(np.mean(var - noise_col[measured])))
    gain = np.zeros(nx)
    if variance > 0:
        gain[measured] = variance / (variance + noise_col[measured])
        gain[~measured] = np.median(gain[measured])
    return StripeModel(weight, scale, limit, gain, variance, noise_col)


def remove_stripes(ramps_dn: np.ndarray, usable: np.ndarray, model: StripeModel) -> np.ndarray:
    """Ramps with the 1/f column stripes removed (a new array; the input is unchanged).

    The offsets of every column, integration and group difference
    (:func:`stripe_offsets`, times the column's gain) are subtracted from the group
    differences of every pixel of the column, i.e. their running sum from every ramp value
    after the first group. Each integration is corrected from its own data and the
    exposure's :class:`StripeModel`, so streaming over integrations gives the same result.

    Parameters
    ----------
    ramps_dn
        (n, G, ny, nx) ADC-corrected ramps, DN.
    usable
        (n, G, ny, nx) bool usable-group mask (a prefix per ramp).
    model
        From :func:`fit_stripe_model`.

    Returns
    -------
    (n, G, ny, nx) corrected ramps, DN; the first group and each pixel's total rise
    ``ramp[G-1] - ramp[0]`` are unchanged (the offsets sum to zero over the differences).
    """
    ramps = np.array(ramps_dn, dtype=np.float64)  # a copy
    if not model.active or ramps.shape[1] < 3:
        return ramps
    full = np.asarray(usable, dtype=bool)[:, -1]
    offsets, _ = stripe_offsets(
        np.diff(ramps, axis=1), full, model.weight, model.scale_dn, model.limit_dn
    )
    ramps[:, 1:] -= np.cumsum(offsets * model.gain, axis=1)[:, :, None, :]
    return ramps


# --------------------------------------------------------------------------------------
# The streaming driver
# --------------------------------------------------------------------------------------


class RampSource(Protocol):
    """Where the driver gets integrations from (a file, or arrays in tests)."""

    @property
    def nints(self) -> int: ...

    @property
    def ngroups(self) -> int: ...

    @property
    def frame_shape(self) -> tuple[int, int]: ...

    def chunks(self, size: int) -> Iterable[tuple[np.ndarray, np.ndarray | None]]:
        """Yield ``(raw_dn, group_dq)`` for consecutive blocks of ``<= size`` integrations:
        raw counts (n, G, ny, nx) and GROUPDQ of the same shape or ``None``."""
        ...


@dataclass(frozen=True)
class ArraySource:
    """A :class:`RampSource` over arrays in memory (tests, simulations).

    Attributes
    ----------
    raw_dn
        (N, G, ny, nx) raw counts.
    group_dq
        Optional GROUPDQ flags, same shape.
    """

    raw_dn: np.ndarray
    group_dq: np.ndarray | None = None

    @property
    def nints(self) -> int:
        return int(self.raw_dn.shape[0])

    @property
    def ngroups(self) -> int:
        return int(self.raw_dn.shape[1])

    @property
    def frame_shape(self) -> tuple[int, int]:
        return (int(self.raw_dn.shape[2]), int(self.raw_dn.shape[3]))

    def chunks(self, size: int) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
        for start in range(0, self.nints, size):
            stop = start + size
            dq = None if self.group_dq is None else self.group_dq[start:stop]
            yield self.raw_dn[start:stop], dq


@dataclass(frozen=True)
class SlopeProduct:
    """The result of processing one exposure (the content of a calslope file).

    Attributes
    ----------
    slope_dn
        (G-1, ny, nx) mean group differences, DN per group.
    slope_cov_dn2
        (G-1, G-1, ny, nx) covariance of ``slope_dn``, DN^2.
    slope_support
        (G-1, ny, nx) integrations used for each slope.
    ramp_dn, ramp_cov_dn2, ramp_support
        The same for the ADC-corrected ramp values (G values, bias included).
    badpix
        (ny, nx) bool, True = do not use.
    badpix_reason
        (ny, nx) uint8 bit mask of :data:`BAD_REASONS`.
    settings
        The settings used.
    nints
        Integrations in the exposure.
    n_sample
        Integrations in the threshold sample.
    n_rejected_ramp, n_rejected_slope
        Ramp values / slopes lost to each clipping stage (counting a dropped rest of ramp),
        over all pixels and integrations.
    stripes
        The 1/f stripe correction applied (``settings.one_over_f == "stripes"``), else
        ``None``.
    """

    slope_dn: np.ndarray
    slope_cov_dn2: np.ndarray
    slope_support: np.ndarray
    ramp_dn: np.ndarray
    ramp_cov_dn2: np.ndarray
    ramp_support: np.ndarray
    badpix: np.ndarray
    badpix_reason: np.ndarray
    settings: ProcessSettings
    nints: int
    n_sample: int
    n_rejected_ramp: int
    n_rejected_slope: int
    stripes: StripeModel | None = None

    def header_cards(self) -> dict[str, tuple[Any, str]]:
        """The calslope file's record of this processing (keyword -> (value, comment)):
        the settings, the minimum support, the clipping's sample and losses, the number of
        flagged pixels."""
        return {
            **self.settings.header_cards(),
            "MINSUP": (self.settings.required_support(self.nints), "minimum slope support"),
            "CLIPSAMP": (self.n_sample, "integrations used to set clipping bands"),
            "NREJRAMP": (self.n_rejected_ramp, "ramp values dropped by ramp clipping"),
            "NREJSLOP": (self.n_rejected_slope, "ramp values dropped by slope clipping"),
            "NBADPIX": (int(np.count_nonzero(self.badpix)), "pixels flagged in BADPIX"),
        }

    def reason_counts(self) -> dict[str, int]:
        """Number of bad pixels per reason (a pixel may count under several)."""
        return {
            name: int(np.count_nonzero(self.badpix_reason & bit))
            for bit, name in BAD_REASONS.items()
        }


def sample_indices(nints: int, ngroups: int, npix: int, settings: ProcessSettings) -> np.ndarray:
    """Indices of the threshold sample: evenly spread, at most the settings' bounds."""
    by_values = max(1, settings.max_sample_values // max(1, ngroups * npix))
    k = min(nints, settings.max_sample_ints, by_values)
    return np.unique(np.round(np.linspace(0, nints - 1, k)).astype(np.int64))


def _prepare(
    raw: np.ndarray, dq: np.ndarray | None, settings: ProcessSettings
) -> tuple[np.ndarray, np.ndarray]:
    raw = np.asarray(raw, dtype=np.float64)
    usable = usable_groups(raw, settings.saturation_dn, dq)
    ramps = correct_adc(raw) if settings.adc_correction else raw
    return ramps, usable


def process_ramps(
    source: RampSource,
    settings: ProcessSettings | None = None,
    pixel_dq: np.ndarray | None = None,
    progress: Callable[[Iterable[Any], int, str], Iterable[Any]] | None = None,
) -> SlopeProduct:
    """Process one exposure, streaming over its integrations (see the module docstring).

    Parameters
    ----------
    source
        The integrations (read twice: once for the threshold sample, once for the sums).
    settings
        Processing options.
    pixel_dq
        Optional (ny, nx) PIXELDQ flags; DO_NOT_USE marks the pixel bad.
    progress
        Optional wrapper ``progress(iterable, total, stage)`` around the two chunk loops
        (progress bars); ``stage`` names the pass.

    Returns
    -------
    SlopeProduct
        Means, covariances, supports and the bad-pixel map.
    """
    settings = settings or ProcessSettings()
    nints, ngroups = source.nints, source.ngroups
    ny, nx = source.frame_shape
    if ngroups < 1:
        raise ValueError("no groups")
    if nints < 1:
        raise ValueError("no integrations")
    npix = ny * nx
    chunk = max(1, settings.chunk_values // (ngroups * npix))
    nchunks = -(-nints // chunk)
    wrap = progress or (lambda items, total, stage: items)

    # Pass 1: gather the threshold sample (raw, so the usable mask is computed alike).
    wanted = sample_indices(nints, ngroups, npix, settings)
    sample_raw = np.empty((wanted.size, ngroups, ny, nx))
    sample_dq: np.ndarray | None = None
    start = filled = 0
    for raw, dq in wrap(source.chunks(chunk), nchunks, "clipping bands"):
        stop = start + raw.shape[0]
        lo, hi = np.searchsorted(wanted, [start, stop])
        if hi > lo:
            rows = wanted[lo:hi] - start
            sample_raw[filled : filled + rows.size] = raw[rows]
            if dq is not None:
                if sample_dq is None:
                    sample_dq = np.zeros(sample_raw.shape, dtype=np.uint32)
                sample_dq[filled : filled + rows.size] = dq[rows]
            filled += rows.size
        start = stop
    if start != nints:
        raise ValueError(f"the source gave {start} integrations, expected {nints}")
    sample_ramps, sample_usable = _prepare(sample_raw, sample_dq, settings)
    del sample_raw, sample_dq
    stripes: StripeModel | None = None
    if settings.one_over_f == "stripes":
        stripes = fit_stripe_model(sample_ramps, sample_usable, settings.stripe_max_signal_dn)
        sample_ramps = remove_stripes(sample_ramps, sample_usable, stripes)
    thresholds = estimate_thresholds(sample_ramps, sample_usable, settings.nsigma)
    del sample_ramps, sample_usable

    # Pass 2: clip every integration with the fixed bands and accumulate the sums.
    ramp_sums = MomentSums(thresholds.ramp_centre_dn)
    slope_sums = MomentSums(thresholds.slope_centre_dn)
    n_saturated = np.zeros((ny, nx))
    n_rejected_ramp = n_rejected_slope = 0
    for raw, dq in wrap(source.chunks(chunk), nchunks, "means and covariances"):
        ramps, usable = _prepare(raw, dq, settings)
        if stripes is not None:
            ramps = remove_stripes(ramps, usable, stripes)
        t = thresholds
        keep_ramp = clip_ramps(ramps, usable, t.ramp_centre_dn, t.ramp_scale_dn, t.nsigma)
        slopes = np.diff(ramps, axis=1)
        keep = clip_slopes(
            ramps, keep_ramp, t.slope_centre_dn, t.slope_scale_dn, t.nsigma, slopes_dn=slopes
        )
        n_rejected_ramp += int(np.count_nonzero(usable & ~keep_ramp))
        n_rejected_slope += int(np.count_nonzero(keep_ramp & ~keep))
        ramp_sums.add(ramps, keep)
        slope_sums.add(slopes, keep[:, 1:])
        n_saturated += saturated_integrations(raw, settings.saturation_dn, dq).sum(axis=0)

    ramp_m, slope_m = ramp_sums.result(), slope_sums.result()
    ramp_cov, slope_cov = ramp_m.cov_of_mean(), slope_m.cov_of_mean()
    if settings.covariance_correction:
        delta_ramp, delta_slope = clipping_influence(
            ramp_m.cov, nints, wanted.size, settings.nsigma
        )
        ramp_cov, slope_cov = ramp_cov + delta_ramp, slope_cov + delta_slope
    slope_sup = slope_m.support

    # Support and noise are judged on the values a fit uses: the slopes, or with one group
    # (no slope) its read, which a fit uses less a known superbias (amigo.model.detector.reset).
    used_sup, used_cov = (slope_sup, slope_cov) if ngroups > 1 else (ramp_m.support, ramp_cov)
    reason = np.zeros((ny, nx), dtype=np.uint8)
    reason[niriss.reference_row_mask(ny, nx)] |= BAD_REFERENCE
    reason[used_sup.min(axis=0) < settings.required_support(nints)] |= BAD_LOW_SUPPORT
    if pixel_dq is not None:
        reason[(np.asarray(pixel_dq).astype(np.uint32) & DQ_DO_NOT_USE) != 0] |= BAD_DQ
    reason[n_saturated > settings.max_saturated_fraction * nints] |= BAD_SATURATED
    used_var = np.diagonal(used_cov, axis1=0, axis2=1)  # (ny, nx, G-1), or (ny, nx, 1)
    with np.errstate(invalid="ignore"):
        no_noise = ~np.all(used_var > 0, axis=-1)
    reason[no_noise] |= BAD_NO_NOISE

    return SlopeProduct(
        slope_dn=slope_m.mean,
        slope_cov_dn2=slope_cov,
        slope_support=slope_sup,
        ramp_dn=ramp_m.mean,
        ramp_cov_dn2=ramp_cov,
        ramp_support=ramp_m.support,
        badpix=reason != 0,
        badpix_reason=reason,
        settings=settings,
        nints=nints,
        n_sample=int(wanted.size),
        n_rejected_ramp=n_rejected_ramp,
        n_rejected_slope=n_rejected_slope,
        stripes=stripes,
    )


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FileSource:
    """A :class:`RampSource` streaming an uncal file (validated on construction)."""

    path: Path
    nints: int
    ngroups: int
    frame_shape: tuple[int, int]

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> tuple[FileSource, Any]:
        """Validate ``path`` as raw ramps; return the source and the file's metadata."""
        from amigo.io import jwst

        path = Path(path)
        meta = jwst.read_header(path)
        if meta.kind != "uncal":
            raise InputError(path, f"is a {meta.kind} product, not raw ramps (uncal)")
        shape = tuple(meta.sci_shape)
        return cls(path, int(meta.nints), int(meta.ngroups), (shape[-2], shape[-1])), meta

    def chunks(self, size: int) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
        from amigo.io import jwst

        yield from jwst.iter_ramps(self.path, size, with_dq=True)


def check_usable(path: str | os.PathLike[str], product: SlopeProduct) -> None:
    """Raise :class:`InputError` when no pixel outside the reference rows is usable."""
    light = ~niriss.reference_row_mask(*product.badpix.shape)
    if not np.all(product.badpix[light]):
        return
    reasons = product.badpix_reason[light]
    if np.all(reasons & BAD_SATURATED):
        raise InputError(
            path,
            f"every pixel is saturated (raw counts >= {product.settings.saturation_dn:g} DN "
            f"in more than {product.settings.max_saturated_fraction:.0%} of the integrations)",
        )
    counts = {
        name: int(np.count_nonzero(reasons & bit))
        for bit, name in BAD_REASONS.items()
        if bit != BAD_REFERENCE and np.any(reasons & bit)
    }
    summary = ", ".join(f"{name}: {n}" for name, n in counts.items())
    raise InputError(path, f"no usable pixel ({summary})")


def process_file(
    uncal_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    settings: ProcessSettings | None = None,
    progress: Callable[[Iterable[object], int, str], Iterable[object]] | None = None,
) -> tuple[Path, SlopeProduct]:
    """Process one uncal file into ``out_dir/<stem>_calslope.fits`` (written atomically).

    Raises
    ------
    InputError
        The file is not usable raw ramps (see :func:`amigo.io.jwst.read_header`), or no
        pixel survives (e.g. everything saturated). Nothing is written then.
    """
    from amigo.io import jwst
    from amigo.io.files import fingerprint

    source, meta = FileSource.open(uncal_path)
    pixel_dq = jwst.read_pixel_dq(source.path)
    product = process_ramps(source, settings, pixel_dq=pixel_dq, progress=progress)
    check_usable(source.path, product)
    out = Path(out_dir) / calslope_name(source.path)
    write_calslope(
        out,
        product,
        meta.primary_header,
        meta.sci_header,
        uncal_name=source.path.name,
        uncal_fingerprint=fingerprint(source.path),
    )
    return out, product
