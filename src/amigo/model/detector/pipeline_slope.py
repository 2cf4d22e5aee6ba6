"""The JWST pipeline's ramp-to-slope estimator (stcal ``OLS_C``, "optimal" weighting) in JAX.

The calibration pipeline's ``ramp_fit`` step (``jwst.ramp_fitting`` calling
``stcal.ramp_fitting``, whose default algorithm ``OLS_C`` is the C extension
``slope_fitter.c``) turns each pixel's up-the-ramp groups into a count rate with a
weighted least-squares line whose weights are those of Fixsen et al. (2000, PASP 112,
1350), with an exponent chosen from the ramp's own signal-to-noise ratio. This module
re-expresses that estimator, for one segment per integration (no jumps; saturated groups
excluded), as a JAX function that is jit-able and differentiable with respect to the ramp
values, so that amigo's forward model can be compared with the pipeline's ``_rateints``
(per integration) and ``_rate`` (exposure) products. It was written from a reading of
stcal 1.20 and is checked against it in ``tests/test_pipeline_slope.py``
(docs/pipeline_slope.md gives the measured agreement).

Conventions
-----------
Inputs

* ``ramps``: (nints, ngroups, ny, nx) group values in DN, as the pipeline has them when
  ``ramp_fit`` runs (bias-subtracted, linearised, dark-subtracted). Only differences
  matter, except in the one-good-group case, where the slope is the first group's value
  divided by a time (the pipeline relies on the superbias having been removed).
* ``saturated``: optional boolean mask of the same shape, True where a group must not be
  used (the pipeline's GROUPDQ ``SATURATED`` or ``DO_NOT_USE``). A group is used only if
  it and every earlier group of its integration are unflagged: the pipeline's saturation
  step flags every group after the first saturated one, so its single segment is this
  prefix. (A flag in the middle of an otherwise good ramp would make stcal fit two
  segments; that case, like jumps, is outside this module.)
* ``group_time``: TGROUP (s); ``frame_time``: TFRAME (s), default ``group_time /
  nframes`` (no group gap); ``nframes``: NFRAMES, frames averaged per group. SUB80 with
  NISRAPID, AMI's usual pattern: TGROUP = TFRAME = 0.07544 s, NFRAMES = 1.
* ``read_noise``: DN, scalar or (ny, nx), exactly as the CRDS READNOISE reference file
  gives it, i.e. the noise of a correlated double sample (difference of two frames).
  stcal turns it into the noise of one group by dividing by ``sqrt(2 NFRAMES)`` (one frame
  has ``1/sqrt(2)`` of the CDS noise; a group averages NFRAMES frames), so NFRAMES enters
  the weights' S/N, the read-noise variance, and (through ``frame_time``) the
  one-good-group time.
* ``gain``: e/DN, scalar or (ny, nx) (CRDS GAIN). A pixel whose gain is not positive and
  finite gets NaN slopes and zero variances, as in stcal.
* ``dark_current``: DN/s, scalar or (ny, nx): the dark step's AVERAGE_DARK_CURRENT, added
  to the Poisson variance's rate; 0 when absent (stcal's default).
* ``suppress_one_group``: the jwst step's parameter of that name (default True there and
  here): an integration with exactly one good group gets no slope. With False, such an
  integration gets stcal's one-group special case.

Outputs (:class:`PipelineSlopes`), in the dtype of ``ramps`` (stcal writes float32)

* per integration (nints, ny, nx), the ``_rateints`` extensions: ``slope`` (SCI, DN/s;
  NaN where the integration has no usable slope), ``var_poisson`` (VAR_POISSON,
  (DN/s)^2), ``var_rnoise`` (VAR_RNOISE), ``err`` (ERR, DN/s);
* per exposure (ny, nx), the ``_rate`` extensions: ``rate``, ``rate_var_poisson``,
  ``rate_var_rnoise``, ``rate_err``;
* ``ngood`` (nints, ny, nx): groups fitted; ``power`` (nints, ny, nx): the Fixsen exponent
  used (NaN where the integration had fewer than 3 groups and no exponent matters).

``_cal``/``_calints`` are these rates after the flat field (divided by the FLAT
reference) and photometric calibration; to compare with them apply the same factors.

The estimator
-------------
Let the integration's segment be groups ``k = 0 .. n-1`` with values ``y_k`` (DN).

* **S/N** of the segment, from the data: ``D = y_{n-1} - y_0`` (DN), ``sigma_e`` = read
  noise of one group in electrons (``read_noise * gain / sqrt(2 NFRAMES)``);
  ``S/N = g D / sqrt(sigma_e^2 + g D)``, set to 0 when negative or undefined.
* **Exponent** ``P`` from stcal's table: S/N < 5: 0; < 10: 0.4; < 20: 1; < 50: 3;
  < 100: 6; otherwise 10.
* **Weights** ``w_k = |(k - m) / m|^P`` with ``m = (n - 1) / 2`` (stcal also divides by
  ``sigma_e^2``, which cancels). The weights are non-negative: stcal takes the absolute
  value before the power, so groups on either side of the middle count alike; with
  ``P = 0`` the fit is unweighted, and for ``P > 0`` and odd ``n`` the middle group has
  zero weight. Bright ramps are thus fitted mostly from their end groups, as Fixsen's
  optimal weights for photon-noise-dominated ramps prescribe.
* **Slope** ``= sum w (k - kbar)(y - ybar) / sum w (k - kbar)^2 / TGROUP`` (weighted
  means ``kbar``, ``ybar``), the weighted least-squares line through ``(k, y_k)``.
  Special cases: ``n = 2``: ``(y_1 - y_0) / TGROUP`` (the same number); ``n = 1`` (only
  when not suppressed): ``y_0 / T1`` with ``T1 = (NFRAMES + 1) TFRAME / 2``; ``n = 0``:
  NaN.
* **Poisson variance** ``(R + dark) / (g TGROUP (n - 1))`` (``n = 1``: ``(R + dark) / (g
  T1)``), where ``R`` (DN/s) is the pixel's *median rate*: for each integration the median
  of its first differences over the good groups divided by TGROUP (``y_0 / T1`` for a
  one-group integration; 0 for an integration without a slope), averaged over *all*
  integrations. So each integration's Poisson variance depends on the other integrations'
  data. When ``R <= 0`` only the dark term remains; a variance that is not positive is
  reported as 0.
* **Read-noise variance** ``12 sigma^2 / (TGROUP^2 (n^3 - n))`` with ``sigma = read_noise
  / sqrt(2 NFRAMES)`` (DN; ``n = 1``: ``2 sigma^2 / T1^2``). It is the variance of the
  *unweighted* fit whatever ``P``, as in stcal.
* **ERR** ``= sqrt(var_poisson + var_rnoise)``.
* **Exposure** (``_rate``): ``var_poisson = 1 / sum_i 1/var_poisson_i``, ``var_rnoise = 1 /
  sum_i 1/var_rnoise_i``, and the rate is the average of the integrations' slopes weighted
  by ``1/var_rnoise_i`` (stcal's JP-4318 choice: inverse *read-noise* variance, not inverse
  total variance; with equal segment lengths it is the plain mean), ``err = sqrt(var_poisson
  + var_rnoise)``. Integrations without a slope are left out; without any, NaN and zeros.
* stcal reports a variance of 1e6 (DN/s)^2 or more as 0 (its LARGE_VARIANCE_THRESHOLD);
  so does this module, and a slope (per integration or exposure), being stcal's
  read-noise-weighted sum times the *reported* read-noise variance, is then 0 as in
  stcal. (Not reached by SUB80 ramps: two NISRAPID groups give ~1.4e4 (DN/s)^2.)

Differentiability: the exponent ``P`` is a step function of the data's S/N, so the
estimator is piecewise linear in the ramp; the gradient is that of the slope for the
weights held fixed (the S/N goes through ``jax.lax.stop_gradient``), exact everywhere but
on the bin edges, where the pipeline's estimator itself jumps. The variances depend on the
data only through the median rate (a sort), differentiable almost everywhere.

:func:`pipeline_slopes` is compiled with ``jax.jit`` (``suppress_one_group`` static; every
other argument may be a traced array, so it also runs inside a caller's ``jit``/``grad``).
A new shape of ``ramps`` compiles anew (a few seconds).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

#: stcal's S/N bin edges (lower bounds of every bin but the first) and the Fixsen
#: exponent of each bin (``len(SNR_POWERS) == len(SNR_EDGES) + 1``).
SNR_EDGES: tuple[float, ...] = (5.0, 10.0, 20.0, 50.0, 100.0)
SNR_POWERS: tuple[float, ...] = (0.0, 0.4, 1.0, 3.0, 6.0, 10.0)
#: A variance at or above this ((DN/s)^2) is reported as 0 by stcal.
VARIANCE_CEILING: float = 1.0e6


class PipelineSlopes(NamedTuple):
    """What the pipeline's ramp fit writes, for one exposure (see the module notes)."""

    slope: Float[Array, "nints ny nx"]
    var_poisson: Float[Array, "nints ny nx"]
    var_rnoise: Float[Array, "nints ny nx"]
    err: Float[Array, "nints ny nx"]
    rate: Float[Array, "ny nx"]
    rate_var_poisson: Float[Array, "ny nx"]
    rate_var_rnoise: Float[Array, "ny nx"]
    rate_err: Float[Array, "ny nx"]
    ngood: Int[Array, "nints ny nx"]
    power: Float[Array, "nints ny nx"]


def snr_power(snr: ArrayLike) -> Array:
    """Fixsen exponent ``P`` for a segment's S/N, stcal's table (a step function)."""
    snr = jnp.asarray(snr)
    edges = jnp.asarray(SNR_EDGES, dtype=snr.dtype)
    powers = jnp.asarray(SNR_POWERS, dtype=snr.dtype)
    # bin index = how many edges the S/N has reached (S/N exactly on an edge: upper bin)
    index = jnp.sum(snr[..., None] >= edges, axis=-1)
    return powers[index]


def segment_snr(delta_dn: ArrayLike, read_noise_group_dn: ArrayLike, gain: ArrayLike) -> Array:
    """S/N of a segment whose last minus first group is ``delta_dn``, as stcal rates it.

    ``g D / sqrt(sigma_e^2 + g D)`` in electrons, ``sigma_e = read_noise_group_dn * gain``
    (the noise of one group); 0 when negative, or when the gain is 0 or the radicand is
    not positive.
    """
    signal = jnp.asarray(delta_dn) * gain
    noise_e = jnp.asarray(read_noise_group_dn) * gain
    radicand = noise_e**2 + signal
    ok = (radicand > 0) & (gain != 0)
    snr = signal / jnp.sqrt(jnp.where(ok, radicand, 1.0))
    return jnp.where(ok, jnp.maximum(snr, 0.0), 0.0)


def fixsen_weights(
    ngood: Int[ArrayLike, " *batch"], power: Float[ArrayLike, " *batch"], ngroups: int
) -> Float[Array, "*batch ngroups"]:
    """Weights ``|(k - m)/m|^P`` of groups ``k < ngood`` (0 beyond), ``m = (ngood - 1)/2``.

    The group axis is last. Segments shorter than 2 groups get weights of 1 on their
    group(s) (unused by the estimator).
    """
    ngood = jnp.asarray(ngood)
    power = jnp.asarray(power)
    k = jnp.arange(ngroups, dtype=power.dtype)
    half = jnp.where(ngood >= 2, (ngood.astype(power.dtype) - 1.0) / 2.0, 1.0)[..., None]
    # |x|^0 = 1 (also at x = 0, the middle group of an odd segment): P = 0 is unweighted
    weights = jnp.abs((k - half) / half) ** power[..., None]
    weights = jnp.where(ngood[..., None] >= 2, weights, 1.0)
    return jnp.where(k < ngood[..., None], weights, 0.0)


def _median_of_prefix(values: Array, count: Array) -> Array:
    """Median over axis 1 of the first ``count`` entries (``count >= 1``; else arbitrary)."""
    masked = jnp.where(
        jnp.arange(values.shape[1])[None, :, None, None] < count[:, None], values, jnp.inf
    )
    ordered = jnp.sort(masked, axis=1)
    safe = jnp.maximum(count, 1)
    lower = jnp.take_along_axis(ordered, ((safe - 1) // 2)[:, None], axis=1)[:, 0]
    upper = jnp.take_along_axis(ordered, (safe // 2)[:, None], axis=1)[:, 0]
    return 0.5 * (lower + upper)


def _safe_sqrt(x: Array) -> Array:
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


@partial(jax.jit, static_argnames=("suppress_one_group",))
def pipeline_slopes(
    ramps: Float[ArrayLike, "nints ngroups ny nx"],
    saturated: Bool[ArrayLike, "nints ngroups ny nx"] | None = None,
    *,
    group_time: float | ArrayLike,
    read_noise: float | Float[ArrayLike, "ny nx"],
    gain: float | Float[ArrayLike, "ny nx"],
    nframes: int | ArrayLike = 1,
    frame_time: float | ArrayLike | None = None,
    dark_current: float | Float[ArrayLike, "ny nx"] = 0.0,
    suppress_one_group: bool = True,
) -> PipelineSlopes:
    """The pipeline's (stcal ``OLS_C``, optimal weighting) slopes and variances of a ramp.

    See the module notes for the conventions (units, shapes) and the estimator.
    ``saturated`` marks groups not to use (None: all usable); ``group_time`` is TGROUP
    (s), ``frame_time`` TFRAME (s, default ``group_time / nframes``), ``read_noise`` the
    CRDS READNOISE value (DN, CDS), ``gain`` e/DN, ``dark_current`` DN/s.
    """
    ramps = jnp.asarray(ramps)
    if not jnp.issubdtype(ramps.dtype, jnp.floating):
        ramps = ramps.astype(jnp.result_type(float))
    dtype = ramps.dtype
    ngroups = ramps.shape[1]
    image_shape = ramps.shape[2:]

    # groups fitted: the unflagged prefix of each integration
    if saturated is None:
        # Every group: written as the constant it is. The prefix's cumulative product of
        # an all-true array is a constant too, which XLA folded while compiling: 1.3 s for
        # 12 groups of 80 x 80 pixels, and an error-level "slow operation" message on the
        # user's terminal (2-core AMD EPYC, 2026-12-02). The default integer, as the sum
        # below gives (int64 where x64 is on).
        ngood = jnp.full((ramps.shape[0], *image_shape), ngroups, dtype=int)
    else:
        usable = ~jnp.asarray(saturated, dtype=bool)
        ngood = jnp.sum(jnp.cumprod(usable.astype(jnp.int32), axis=1), axis=1)
    nfloat = ngood.astype(dtype)

    group_time = jnp.asarray(group_time, dtype=dtype)
    nframes_f = jnp.asarray(nframes, dtype=dtype)
    frame_time = group_time / nframes_f if frame_time is None else jnp.asarray(frame_time, dtype)
    # the time stcal divides a lone first group by
    one_group_time = (nframes_f + 1.0) * frame_time / 2.0
    gain = jnp.broadcast_to(jnp.asarray(gain, dtype=dtype), image_shape)
    read_noise = jnp.broadcast_to(jnp.asarray(read_noise, dtype=dtype), image_shape)
    dark_current = jnp.broadcast_to(jnp.asarray(dark_current, dtype=dtype), image_shape)
    good_gain = jnp.isfinite(gain) & (gain > 0)
    safe_gain = jnp.where(good_gain, gain, 1.0)
    # read noise of one group (DN): CDS noise / sqrt(2) per frame, averaged over NFRAMES
    sigma_group = read_noise / jnp.sqrt(2.0 * nframes_f)

    # stcal ignores the option for single-group exposures (as the jwst step does)
    suppress = bool(suppress_one_group) and ngroups > 1
    multi = ngood >= 2
    single = (ngood == 1) & (not suppress)
    valid = (multi | single) & good_gain

    first = ramps[:, 0]
    last = jnp.take_along_axis(ramps, jnp.maximum(ngood - 1, 0)[:, None], axis=1)[:, 0]

    # --- slope -----------------------------------------------------------------------
    # The exponent depends on the data through the S/N: the estimator is piecewise linear
    # in the ramp, constant weights within each S/N bin. The S/N is held out of the
    # gradient, so the gradient is that of the weighted fit for the weights in force.
    snr = segment_snr(jax.lax.stop_gradient(last - first), sigma_group, gain)
    power = jax.lax.stop_gradient(snr_power(snr))
    weights = jax.lax.stop_gradient(fixsen_weights(ngood, power, ngroups))
    weights = jnp.moveaxis(weights, -1, 1)  # (nints, ngroups, ny, nx)
    k = jnp.arange(ngroups, dtype=dtype)[None, :, None, None]
    in_segment = k < nfloat[:, None]
    # relative to the first group (the fitted slope does not depend on the offset)
    y = jnp.where(in_segment, ramps - first[:, None], 0.0)
    sum_w = jnp.sum(weights, axis=1)
    k_mean = jnp.sum(weights * k, axis=1) / jnp.where(sum_w > 0, sum_w, 1.0)
    dk = jnp.where(in_segment, k - k_mean[:, None], 0.0)
    sxx = jnp.sum(weights * dk**2, axis=1)
    sxy = jnp.sum(weights * dk * y, axis=1)
    fitted = sxy / jnp.where(multi, sxx, 1.0) / group_time
    slope = jnp.where(multi, fitted, first / one_group_time)
    slope = jnp.where(valid, slope, jnp.nan)

    # --- median rate (per pixel, over all integrations) --------------------------------
    if ngroups == 1:
        # stcal: mean of y_0 / T1 over the integrations; a saturated one makes it NaN,
        # which then counts as "no positive rate"
        all_ok = jnp.all(ngood == 1, axis=0)
        mean_rate = jnp.mean(jnp.where(ngood == 1, first / one_group_time, 0.0), axis=0)
        median_rate = jnp.where(all_ok, mean_rate, 0.0)
    else:
        differences = jnp.diff(ramps, axis=1) / group_time
        per_integration = _median_of_prefix(differences, ngood - 1)
        per_integration = jnp.where(multi, per_integration, 0.0)
        per_integration = jnp.where(single, first / one_group_time, per_integration)
        # integrations without a rate count as 0 in the average (stcal's NaN -> 0)
        median_rate = jnp.mean(per_integration, axis=0)

    # --- variances per integration ------------------------------------------------------
    rate_term = jnp.where(median_rate > 0, median_rate + dark_current, dark_current)
    poisson_time = jnp.where(multi, group_time * jnp.maximum(nfloat - 1.0, 1.0), one_group_time)
    var_poisson_seg = rate_term[None] / (poisson_time * safe_gain[None])
    n_cubed = jnp.where(multi, nfloat**3 - nfloat, 6.0)
    var_rnoise_seg = jnp.where(
        multi,
        12.0 * sigma_group**2 / (group_time**2 * n_cubed),
        2.0 * sigma_group**2 / one_group_time**2,
    )
    # stcal forms the slope as (slope / var_rnoise) * reported var_rnoise: a read-noise
    # variance over the ceiling (reported as 0) makes the reported slope 0 as well (the
    # exposure sum below still takes the fitted one)
    fitted_slope = slope
    slope = jnp.where(valid & (var_rnoise_seg >= VARIANCE_CEILING), 0.0, slope)
    has_poisson = valid & (var_poisson_seg > 0)
    var_poisson = jnp.where(has_poisson, var_poisson_seg, 0.0)
    var_poisson = jnp.where(var_poisson >= VARIANCE_CEILING, 0.0, var_poisson)
    var_rnoise = jnp.where(valid & (var_rnoise_seg < VARIANCE_CEILING), var_rnoise_seg, 0.0)
    var_total = var_poisson_seg + var_rnoise_seg
    err = jnp.where(valid & (var_total <= VARIANCE_CEILING), _safe_sqrt(var_total), 0.0)

    # --- exposure -----------------------------------------------------------------------
    inv_rnoise = jnp.where(valid, 1.0 / var_rnoise_seg, 0.0)
    inv_poisson = jnp.where(has_poisson, 1.0 / jnp.where(has_poisson, var_poisson_seg, 1.0), 0.0)
    sum_inv_r = jnp.sum(inv_rnoise, axis=0)
    sum_inv_p = jnp.sum(inv_poisson, axis=0)
    rate_var_poisson = jnp.where(sum_inv_p > 0, 1.0 / jnp.where(sum_inv_p > 0, sum_inv_p, 1.0), 0.0)
    rate_var_poisson = jnp.where(
        (rate_var_poisson >= VARIANCE_CEILING) | (rate_var_poisson < 0), 0.0, rate_var_poisson
    )
    rate_var_rnoise = jnp.where(sum_inv_r > 0, 1.0 / jnp.where(sum_inv_r > 0, sum_inv_r, 1.0), 0.0)
    rate_var_rnoise = jnp.where(rate_var_rnoise >= VARIANCE_CEILING, 0.0, rate_var_rnoise)
    # inverse read-noise-variance weighted mean, scaled by the *reported* variance
    weighted_sum = jnp.sum(jnp.where(valid, fitted_slope, 0.0) * inv_rnoise, axis=0)
    any_valid = jnp.any(valid, axis=0)
    rate = jnp.where(any_valid, weighted_sum * rate_var_rnoise, jnp.nan)
    rate_err = jnp.where(any_valid, _safe_sqrt(rate_var_poisson + rate_var_rnoise), 0.0)
    rate_var_poisson = jnp.where(any_valid, rate_var_poisson, 0.0)
    rate_var_rnoise = jnp.where(any_valid, rate_var_rnoise, 0.0)

    power = jnp.where(multi & (ngood >= 3), power, jnp.nan)
    return PipelineSlopes(
        slope=slope.astype(dtype),
        var_poisson=var_poisson.astype(dtype),
        var_rnoise=var_rnoise.astype(dtype),
        err=err.astype(dtype),
        rate=rate.astype(dtype),
        rate_var_poisson=rate_var_poisson.astype(dtype),
        rate_var_rnoise=rate_var_rnoise.astype(dtype),
        rate_err=rate_err.astype(dtype),
        ngood=ngood,
        power=power.astype(dtype),
    )


#: CDS read noise (DN) given to the estimator when it is applied to a *model's* noiseless
#: ramp: it only picks the Fixsen exponent from the ramp's S/N (the simulator's 6.6 DN per
#: read, times sqrt(2) for a difference of two reads), and the exponent barely matters
#: there: the weights are symmetric about the ramp's middle, so a ramp bent by any
#: quadratic gets the same slope whatever the exponent (docs/pipeline_slope.md).
MODEL_READ_NOISE_CDS_DN = 6.6 * 2.0**0.5


def pipeline_group_slope(
    differences_dn: Float[ArrayLike, "m ny nx"],
    group_time: float,
    gain: float,
    nframes: int = 1,
    groups_used: Int[ArrayLike, "ny nx"] | None = None,
) -> Float[Array, "ny nx"]:
    """The pipeline's slope of one noiseless model integration, in DN per group.

    ``differences_dn`` are the model's group differences (``ngroups - 1``, DN per group:
    the ramp summed from zero, the estimator only sees differences); the result is what
    a level-2 image (DN/s) would hold, times ``group_time``, so that it compares with
    the mean group difference a linear detector would give. Differentiable (the S/N
    that picks the weights is held out of the gradient, as in :func:`pipeline_slopes`).
    ``groups_used``: per pixel, the leading groups the pipeline fitted (the rest flagged,
    e.g. by its charge-migration step: :func:`charge_loss_groups`); ``None``: all.
    """
    differences_dn = jnp.asarray(differences_dn)
    ramp = jnp.concatenate([jnp.zeros_like(differences_dn[:1]), jnp.cumsum(differences_dn, axis=0)])
    flagged = None
    if groups_used is not None:
        k = jnp.arange(ramp.shape[0])[:, None, None]
        flagged = (k >= jnp.asarray(groups_used)[None])[None]
    fitted = pipeline_slopes(
        ramp[None],
        flagged,
        group_time=group_time,
        read_noise=MODEL_READ_NOISE_CDS_DN,
        gain=gain,
        nframes=nframes,
    )
    return fitted.slope[0] * group_time


#: The JWST pipeline's ``charge_migration`` step: its ``signal_threshold`` default (DN),
#: jwst's ``ChargeMigrationStep`` spec from jwst 1.12.2 on. A group whose value
#: (superbias-subtracted, linearised, dark-subtracted DN) exceeds it is flagged CHARGELOSS
#: and DO_NOT_USE, with every later group of the integration, in the pixel and its four
#: edge neighbours (the neighbours' rule of jwst 1.14 on; before, a neighbour was flagged
#: only at the groups where the pixel carried no other flag, e.g. not once it saturated);
#: the ramp fit then uses the unflagged leading groups. Integrations of 1 or 2 groups are
#: not flagged. The step records itself as ``S_CHGMIG = 'COMPLETE'`` (from jwst 1.12.0,
#: when ``undersampling_correction`` was renamed; COM 1093's CAL_VER 1.5.3 files predate it).
CHARGE_LOSS_THRESHOLD_DN: float = 25000.0
#: The step's default in jwst 1.12.0 and 1.12.1 (DN).
CHARGE_LOSS_THRESHOLD_1_12_DN: float = 30000.0


def group_times_s(
    ngroups: int, group_time: float, frame_time: float, nframes: int = 1
) -> np.ndarray:
    """(ngroups,) each group's mean time since the reset (s): group ``k`` (from 0) is
    ``k * TGROUP + (NFRAMES + 1) * TFRAME / 2``, the mean of its NFRAMES frames' read
    times (for NISRAPID ``(k + 1) * TGROUP``). A linear ramp of rate ``r`` holds ``r``
    times these (DN, the superbias subtracted)."""
    return np.arange(ngroups) * group_time + (nframes + 1) * frame_time / 2.0


def charge_loss_groups(
    rate_dn_s: Float[np.ndarray, "ny nx"],
    ngroups: int,
    group_time: float,
    frame_time: float,
    nframes: int = 1,
    threshold_dn: float = CHARGE_LOSS_THRESHOLD_DN,
) -> Int[np.ndarray, "ny nx"]:
    """Per pixel, how many leading groups the charge-migration step left to the ramp fit.

    Emulates the step on the ramp a pixel of count rate ``rate_dn_s`` (DN/s, the level-2
    image's; NaN where unknown, counted as dark; ``+inf`` for a pixel over the threshold
    from its first group, e.g. saturated throughout) would have recorded, group by group
    the rate times :func:`group_times_s`: the first group above ``threshold_dn`` and every
    later one are flagged, in the pixel and its four neighbours. Returns ``ngroups``
    where nothing is flagged, never fewer than 2 (a pixel with a slope in the file had at
    least two groups; with the jwst step's default ``suppress_one_group`` a one-group
    pixel has no value to fit). The level-2 rate is the fit of the leading groups and the
    flat field is left out (within a few per cent of 1), so a pixel whose ramp crosses
    the threshold within that much of a group boundary may be one group off.
    """
    rate = np.nan_to_num(np.asarray(rate_dn_s, np.float64), nan=0.0, posinf=np.inf, neginf=0.0)
    if ngroups < 3:
        return np.full(rate.shape, ngroups, dtype=np.int32)
    times = group_times_s(ngroups, group_time, frame_time, nframes)
    level = rate[None] * times[:, None, None]
    # the rate's levels rise with k: the groups below the threshold are a prefix
    below = np.sum(level <= threshold_dn, axis=0)
    used = below.copy()
    used[1:, :] = np.minimum(used[1:, :], below[:-1, :])
    used[:-1, :] = np.minimum(used[:-1, :], below[1:, :])
    used[:, 1:] = np.minimum(used[:, 1:], below[:, :-1])
    used[:, :-1] = np.minimum(used[:, :-1], below[:, 1:])
    return np.maximum(used, 2).astype(np.int32)
