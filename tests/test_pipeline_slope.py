"""amigo.model.detector.pipeline_slope against the JWST pipeline's own ramp fitting (stcal).

Every test simulates ramps with numpy, fits them with stcal's ``ramp_fit_data`` (algorithm
``OLS_C``, weighting ``optimal``: what the jwst ``ramp_fit`` step runs) and with
:func:`pipeline_slopes` (float64), and compares all eight products: the per-integration
SCI, VAR_POISSON, VAR_RNOISE, ERR (``_rateints``) and the exposure's (``_rate``). stcal
computes in double from float32 inputs and writes float32, so agreement is expected at
float32 rounding (~6e-8 relative); the tests allow ``RTOL = 1e-6``. The measured maximum
relative differences (over all eight products) are quoted in each test's docstring.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip(
    "stcal",
    reason="stcal (the JWST pipeline's ramp fitting) is not installed; pip install stcal",
)

import jax
import jax.numpy as jnp
from stcal.ramp_fitting.ramp_fit import ramp_fit_data
from stcal.ramp_fitting.ramp_fit_class import RampData

from amigo.model.detector.pipeline_slope import (
    CHARGE_LOSS_THRESHOLD_DN,
    MODEL_READ_NOISE_CDS_DN,
    SNR_POWERS,
    charge_loss_groups,
    fixsen_weights,
    pipeline_group_slope,
    pipeline_slopes,
    segment_snr,
    snr_power,
)

#: The JWST DQ bits stcal's RampData needs (stdatamodels' dqflags.pixel values).
DQ_FLAGS = {
    "DO_NOT_USE": 1,
    "SATURATED": 2,
    "JUMP_DET": 4,
    "PERSISTENCE": 32,
    "CHARGELOSS": 128,
    "NO_GAIN_VALUE": 524288,
    "UNRELIABLE_SLOPE": 16777216,
}
TFRAME = 0.07544  # SUB80 NISRAPID frame (= group) time, s
GAIN = 1.61  # e/DN
READ_NOISE = 11.0  # DN, CDS (CRDS READNOISE convention)
RTOL = 1e-6
#: (nints, ngroups, ny, nx) of most comparisons: one shape, one compilation
SHAPE = (3, 6, 6, 6)
INTEG_KEYS = (("slope", "slope"), ("var_poisson", "var_poisson"))
INTEG_KEYS += (("var_rnoise", "var_rnoise"), ("err", "err"))
RATE_KEYS = (("rate", "slope"), ("rate_var_poisson", "var_poisson"))
RATE_KEYS += (("rate_var_rnoise", "var_rnoise"), ("rate_err", "err"))


def _detector(rng, ny, nx):
    """Per-pixel read noise (DN, CDS) and gain (e/DN), float32 as CRDS stores them."""
    read_noise = (READ_NOISE * rng.uniform(0.9, 1.1, (ny, nx))).astype(np.float32)
    gain = (GAIN * rng.uniform(0.95, 1.05, (ny, nx))).astype(np.float32)
    return read_noise, gain


def _simulate(rng, nints, ngroups, flux_dn, read_noise, gain, nframes=1, bend=None):
    """Ramps (nints, ngroups, ny, nx) float32 DN: Poisson charge, read noise per group.

    ``flux_dn`` is DN per group; ``bend(k)`` (k = group index + 1) maps the linear
    expected charge ``flux_dn * k`` to the recorded one (None: linear).
    """
    k = np.arange(1, ngroups + 1)[None, :, None, None]
    expected = flux_dn * k if bend is None else bend(flux_dn * k)
    increments = np.diff(expected, axis=1, prepend=0.0)
    electrons = rng.poisson(np.broadcast_to(increments * gain, (nints, *increments.shape[1:])))
    charge = np.cumsum(electrons, axis=1) / gain
    noise = rng.normal(0.0, 1.0, charge.shape) * read_noise / np.sqrt(2.0 * nframes)
    return (charge + noise).astype(np.float32)


def _stcal(
    ramps,
    saturated,
    *,
    tgroup,
    tframe,
    nframes,
    groupgap,
    read_noise,
    gain,
    dark=None,
    suppress=True,
    chargeloss=False,
):
    """stcal's OLS_C optimal-weighting fit: (rate dict, rateints dict). ``chargeloss``:
    the flagged groups are CHARGELOSS + DO_NOT_USE (the charge-migration step's flags,
    with the original group DQ handed over as jwst's ramp_fit step does) instead of
    SATURATED."""
    ny, nx = ramps.shape[2:]
    ramp_data = RampData()
    flag = DQ_FLAGS["CHARGELOSS"] | DQ_FLAGS["DO_NOT_USE"] if chargeloss else DQ_FLAGS["SATURATED"]
    groupdq = np.where(saturated, flag, 0).astype(np.uint8)
    dark = np.zeros((ny, nx)) if dark is None else np.broadcast_to(dark, (ny, nx))
    ramp_data.set_arrays(
        np.ascontiguousarray(ramps, dtype=np.float32),
        groupdq,
        np.zeros((ny, nx), np.uint32),
        np.ascontiguousarray(dark, dtype=np.float32),
        orig_gdq=groupdq.copy() if chargeloss else None,
    )
    ramp_data.set_meta(
        name="NIRISS",
        frame_time=tframe,
        group_time=tgroup,
        groupgap=groupgap,
        nframes=nframes,
        drop_frames1=None,
    )
    ramp_data.algorithm = "OLS_C"
    ramp_data.set_dqflags(DQ_FLAGS)
    ramp_data.start_row = 0
    ramp_data.num_rows = ny
    ramp_data.suppress_one_group_ramps = suppress
    # ramp_fit_data scales its read-noise argument in place: hand it copies
    rate, rateints, _ = ramp_fit_data(
        ramp_data,
        False,
        np.array(read_noise, np.float32, copy=True),
        np.array(gain, np.float32, copy=True),
        "OLS_C",
        "optimal",
        "1",
    )
    return rate, rateints


def _ours(ramps, saturated, *, tgroup, tframe, nframes, read_noise, gain, dark=0.0, suppress=True):
    with jax.enable_x64(True):
        out = pipeline_slopes(
            np.asarray(ramps, np.float64),
            saturated,
            group_time=tgroup,
            frame_time=tframe,
            nframes=nframes,
            read_noise=np.asarray(read_noise, np.float64),
            gain=np.asarray(gain, np.float64),
            dark_current=np.asarray(dark, np.float64),
            suppress_one_group=suppress,
        )
        return jax.tree.map(np.asarray, out)


def _relative_difference(ours, theirs):
    """Max |ours - theirs| / |theirs| (0/0 = 0); NaN at the same places is required."""
    ours = np.asarray(ours, np.float64)
    theirs = np.asarray(theirs, np.float64)
    np.testing.assert_array_equal(np.isnan(ours), np.isnan(theirs))
    ok = ~np.isnan(theirs)
    diff = np.abs(ours[ok] - theirs[ok])
    scale = np.abs(theirs[ok])
    assert np.all(diff[scale == 0] == 0), "stcal reports 0 where amigo does not"
    rel = diff[scale > 0] / scale[scale > 0]
    return float(rel.max()) if rel.size else 0.0


def _compare(ramps, saturated, stcal_out=None, **kw):
    """Fit with both; return (ours, {product: max relative difference}).

    ``stcal_out``, a dict, receives stcal's products (keys ``rate``, ``rateints``).
    """
    stcal_kw = {key: kw[key] for key in kw if key != "suppress"}
    rate, rateints = _stcal(ramps, saturated, suppress=kw.get("suppress", True), **stcal_kw)
    ours_kw = {key: value for key, value in kw.items() if key != "groupgap"}
    ours = _ours(ramps, saturated, **ours_kw)
    if stcal_out is not None:
        stcal_out.update(rate=rate, rateints=rateints)
    diffs = {}
    for mine, key in INTEG_KEYS:
        diffs[f"rateints.{key}"] = _relative_difference(getattr(ours, mine), rateints[key])
    for mine, key in RATE_KEYS:
        diffs[f"rate.{key}"] = _relative_difference(getattr(ours, mine), rate[key])
    return ours, diffs


def _assert_agree(diffs):
    worst = max(diffs.values())
    assert worst < RTOL, f"max relative difference to stcal {worst:.2e}: {diffs}"
    return worst


def _timing(nframes=1, groupgap=0):
    return {"tframe": TFRAME, "tgroup": (nframes + groupgap) * TFRAME, "nframes": nframes}


def test_flux_levels_span_every_power_bin():
    """(a) Poisson + read noise, 0.1 .. 10^4 DN/group: every S/N bin (P = 0 .. 10) is used.

    Measured max relative difference to stcal: 2.0e-7 (all eight products; the largest
    is VAR_RNOISE, from stcal's float32 product of read noise and gain).
    """
    rng = np.random.default_rng(1)
    nints, ngroups, ny, nx = SHAPE
    read_noise, gain = _detector(rng, ny, nx)
    flux = np.logspace(-1, 4, ny * nx).reshape(ny, nx)
    ramps = _simulate(rng, nints, ngroups, flux, read_noise, gain)
    saturated = np.zeros(ramps.shape, bool)
    ours, diffs = _compare(
        ramps, saturated, **_timing(), groupgap=0, read_noise=read_noise, gain=gain
    )
    used = set(np.unique(ours.power[np.isfinite(ours.power)]).tolist())
    assert used == set(SNR_POWERS), f"power bins used: {sorted(used)}"
    _assert_agree(diffs)


@pytest.mark.parametrize("suppress", [True, False], ids=["suppress1g", "keep1g"])
def test_saturation_from_some_group_on(suppress):
    """(b) Saturation flagged from group s on (s = 0 .. G, per pixel and integration).

    s = 0: no slope; s = 1: one good group (suppressed -> no slope, the jwst default; kept
    -> stcal's y_0 / T1 case); s = 2: the two-group case; one pixel has zero gain.
    Measured max relative difference to stcal: 1.9e-7 (suppressed and kept).
    """
    rng = np.random.default_rng(2)
    nints, ngroups, ny, nx = SHAPE
    read_noise, gain = _detector(rng, ny, nx)
    flux = np.logspace(0, 3.7, ny * nx).reshape(ny, nx)
    ramps = _simulate(rng, nints, ngroups, flux, read_noise, gain)
    gain[0, 0] = 0.0  # a pixel without a gain: no slope anywhere
    start = rng.integers(0, ngroups + 1, size=(nints, ny, nx))
    start[:, 1, :] = ngroups  # some pixels never saturate
    start[:, 2, 0] = 1  # every integration one-group
    saturated = np.arange(ngroups)[None, :, None, None] >= start[:, None]
    ramps = np.where(saturated, np.float32(20000.0), ramps)  # the values stcal ignores
    ours, diffs = _compare(
        ramps,
        saturated,
        **_timing(),
        groupgap=0,
        read_noise=read_noise,
        gain=gain,
        suppress=suppress,
    )
    assert {0, 1, 2, ngroups} <= set(np.unique(ours.ngood).tolist())
    assert np.all(np.isnan(ours.slope[start == 0]))
    assert np.all(np.isnan(ours.slope[:, 0, 0])) and np.isnan(ours.rate[0, 0])
    one_group = (start == 1) & (gain > 0)[None]
    assert np.all(np.isnan(ours.slope[one_group]) == suppress)
    _assert_agree(diffs)


def test_two_and_one_group_exposures():
    """ngroups = 2 (every fit is the two-group difference) and ngroups = 1 (y_0 / T1).

    Measured max relative difference to stcal: 1.9e-7 (2 groups and 1 group).
    """
    rng = np.random.default_rng(3)
    read_noise, gain = _detector(rng, 4, 5)
    flux = np.logspace(0, 3, 20).reshape(4, 5)
    worst = []
    for ngroups in (2, 1):
        ramps = _simulate(rng, 3, ngroups, flux, read_noise, gain)
        saturated = np.zeros(ramps.shape, bool)
        saturated[1, :, 0, 0] = True  # one saturated integration in one pixel
        # a single-group exposure is never suppressed (the jwst step turns the option off)
        _, diffs = _compare(
            ramps,
            saturated,
            **_timing(),
            groupgap=0,
            read_noise=read_noise,
            gain=gain,
            suppress=ngroups > 1,
        )
        worst.append(_assert_agree(diffs))


def _weighted_slopes(ramps, power, tgroup):
    """Slopes (DN/s) of full ramps (nints, ngroups, ny, nx) with Fixsen weights of ``power``."""
    x = np.arange(ramps.shape[1], dtype=np.float64)
    half = (x.size - 1) / 2
    w = np.abs((x - half) / half) ** power
    lever = w * (x - np.sum(w * x) / np.sum(w))
    lever = lever / np.sum(lever * x)
    return np.tensordot(lever, np.asarray(ramps, np.float64), axes=(0, 1)) / tgroup


def test_nonlinear_ramps_and_what_the_weights_change():
    """(c) Ramps bent by a few per cent (a stand-in for the brighter-fatter effect).

    A quadratic bend (3 % low at the last group) and a saturating exponential (Q (1 -
    exp(-x / Q)), 3.5 % low), with noise: amigo agrees with stcal to 1.5e-7 (both).
    What the S/N-chosen weights change there: on these noisy ramps the pipeline's slopes
    differ from unweighted least squares by up to 2.6 % and 2.8 % (pixels with P > 0: a
    different estimator of the same rate, with different noise), so the weights are needed to
    reproduce ``_rateints`` at all. The *expected* slope barely depends on them: the weights
    are symmetric about the middle group, so for a pure quadratic every P gives the same
    noise-free slope (to 1e-15), and the exponential's higher terms move it by only 2.8e-5
    between P = 0 and P = 10.
    """
    rng = np.random.default_rng(4)
    nints, ngroups, ny, nx = SHAPE
    read_noise, gain = _detector(rng, ny, nx)
    flux = np.logspace(1.5, 3.5, ny * nx).reshape(ny, nx)
    last = ngroups * flux
    bends = {
        "quadratic": lambda linear: linear * (1 - 0.03 * linear / last),
        # 1 - (1 - e^-u) / u ~ u / 2 = 3.5 % at u = 1/14
        "exponential": lambda linear: 14.0 * last * -np.expm1(-linear / (14.0 * last)),
    }
    for bend in bends.values():
        ramps = _simulate(rng, nints, ngroups, flux, read_noise, gain, bend=bend)
        products = {}
        ours, diffs = _compare(
            ramps,
            np.zeros(ramps.shape, bool),
            stcal_out=products,
            **_timing(),
            groupgap=0,
            read_noise=read_noise,
            gain=gain,
        )
        _assert_agree(diffs)
        weighted = ours.power > 0
        assert weighted.sum() > nints * ny * nx // 2
        unweighted = _weighted_slopes(ramps, 0.0, TFRAME)
        stcal_slope = products["rateints"]["slope"]
        change = np.abs(unweighted / stcal_slope - 1)[weighted]
        assert change.max() > 1e3 * RTOL  # the weights matter for the measured slopes

    # noise-free: the slope for each power against the unweighted one
    k = np.arange(1, ngroups + 1)[None, :, None, None]
    shifts = {}
    for name, bend in bends.items():
        ramp = bend(flux[None, None] * k)
        fits = np.array([_weighted_slopes(ramp, p, TFRAME) for p in SNR_POWERS])
        shifts[name] = np.max(np.abs(fits / fits[0] - 1))
    assert shifts["quadratic"] < 1e-12
    assert 1e-5 < shifts["exponential"] < 1e-4


def test_nframes_groupgap_and_dark_current():
    """(d)+(e) NFRAMES = 4, GROUPGAP = 1, AVERAGE_DARK_CURRENT > 0, one-group ramps kept.

    stcal scales the CDS read noise by 1/sqrt(2 NFRAMES) (S/N, weights, VAR_RNOISE) and
    divides a lone first group by T1 = (NFRAMES + 1) TFRAME / 2; the dark current adds to
    the median rate in VAR_POISSON. Measured max relative difference to stcal: 1.6e-7.
    """
    rng = np.random.default_rng(5)
    nframes, groupgap = 4, 1
    nints, ngroups, ny, nx = SHAPE
    read_noise, gain = _detector(rng, ny, nx)
    flux = np.logspace(-0.5, 3.5, ny * nx).reshape(ny, nx)
    ramps = _simulate(rng, nints, ngroups, flux, read_noise, gain, nframes=nframes)
    start = rng.integers(1, ngroups + 1, size=(nints, ny, nx))
    saturated = np.arange(ngroups)[None, :, None, None] >= start[:, None]
    dark = rng.uniform(0.0, 5.0, (ny, nx)).astype(np.float32)
    ours, diffs = _compare(
        ramps,
        saturated,
        **_timing(nframes, groupgap),
        groupgap=groupgap,
        read_noise=read_noise,
        gain=gain,
        dark=dark,
        suppress=False,
    )
    assert 1 in set(np.unique(ours.ngood).tolist())
    _assert_agree(diffs)
    # and the read-noise variance really is that of the NFRAMES-averaged group noise
    n = ours.ngood
    sigma = read_noise / np.sqrt(2 * nframes)
    tgroup = (nframes + groupgap) * TFRAME
    expected = 12 * sigma**2 / (tgroup**2 * np.maximum(n**3 - n, 1))
    np.testing.assert_allclose(ours.var_rnoise[n >= 2], expected[n >= 2], rtol=1e-12)
    one_group_time = (nframes + 1) * TFRAME / 2
    expected = np.broadcast_to(2 * sigma**2 / one_group_time**2, n.shape)
    np.testing.assert_allclose(ours.var_rnoise[n == 1], expected[n == 1], rtol=1e-12)


@pytest.mark.parametrize("tgroup", [0.001, 0.009], ids=["all_over", "integrations_over"])
def test_variance_ceiling(tgroup):
    """(e) A variance >= 1e6 (DN/s)^2 is reported as 0, and so is the slope built on it.

    Two groups 1 ms apart: VAR_RNOISE ~ 1e8 (DN/s)^2 per integration and for the exposure;
    stcal writes 0 for it, and its slopes (read-noise-weighted sums times the *reported*
    variance) are 0 too. 9 ms apart: ~1.5e6 per integration (slope 0 in ``_rateints``) but
    ~7.5e5 for the two-integration exposure, whose rate is the real one. amigo does the
    same. Measured max relative difference to stcal: 0 (1 ms), 1.6e-7 (9 ms).
    """
    rng = np.random.default_rng(6)
    read_noise, gain = _detector(rng, 3, 3)
    ramps = _simulate(rng, 2, 2, np.full((3, 3), 50.0), read_noise, gain)
    ours, diffs = _compare(
        ramps,
        np.zeros(ramps.shape, bool),
        tframe=tgroup,
        tgroup=tgroup,
        nframes=1,
        groupgap=0,
        read_noise=read_noise,
        gain=gain,
    )
    assert np.all(ours.var_rnoise == 0) and np.all(ours.slope == 0)
    if tgroup < 0.005:
        assert np.all(ours.rate == 0) and np.all(ours.rate_var_rnoise == 0)
    else:
        assert np.all(ours.rate != 0) and np.all(ours.rate_var_rnoise > 0)
    _assert_agree(diffs)


def test_float32_and_traced_arguments():
    """Default precision (float32): agrees with stcal to 1.2e-7 (measured); TGROUP traced.

    The slope's derivative with respect to TGROUP is -slope / TGROUP.
    """
    rng = np.random.default_rng(7)
    read_noise, gain = _detector(rng, 4, 4)
    ramps = _simulate(rng, 2, 5, np.logspace(1.5, 3, 16).reshape(4, 4), read_noise, gain)
    _, rateints = _stcal(
        ramps,
        np.zeros(ramps.shape, bool),
        tgroup=TFRAME,
        tframe=TFRAME,
        nframes=1,
        groupgap=0,
        read_noise=read_noise,
        gain=gain,
    )

    def total_and_slopes(tgroup):
        out = pipeline_slopes(ramps, group_time=tgroup, read_noise=read_noise, gain=gain)
        return jnp.sum(out.slope), out.slope

    (_, slope), dt = jax.jit(jax.value_and_grad(total_and_slopes, has_aux=True))(
        jnp.float32(TFRAME)
    )
    assert slope.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(slope), rateints["slope"], rtol=2e-5)
    # d slope / d TGROUP = -slope / TGROUP
    np.testing.assert_allclose(dt, -np.sum(rateints["slope"]) / TFRAME, rtol=1e-4)


def test_gradient_matches_finite_differences(x64):
    """d(products)/d(ramp) in float64 against central differences (1e-3 DN steps).

    All eight products (slopes, both variances, ERR, per integration and for the exposure)
    over ramps in several S/N bins with partial saturation; the slope's gradient is also
    the fixed-weight Fixsen fit's, w_k (k - kbar) / sum w (k - kbar)^2 / TGROUP.
    Measured: the gradient agrees with the differences to 5.6e-8 relative per element
    (8.6e-10 of the largest element; ERR's square root makes the differences inexact).
    """
    rng = np.random.default_rng(8)
    nints, ngroups, ny, nx = 2, 5, 2, 3
    read_noise, gain = _detector(rng, ny, nx)
    flux = np.array([[0.5, 30.0, 300.0], [3.0, 100.0, 2000.0]])
    ramps = _simulate(rng, nints, ngroups, flux, read_noise, gain).astype(np.float64)
    saturated = np.zeros(ramps.shape, bool)
    saturated[0, 3:, 1, 2] = True
    saturated[1, 4:, 0, 1] = True
    coefficients = rng.normal(size=(8, nints, ny, nx))
    weights = [c if k < 4 else c[0] for k, c in enumerate(coefficients)]  # rate: (ny, nx)
    kw = {"group_time": TFRAME, "read_noise": read_noise, "gain": gain}

    def products(r):
        out = pipeline_slopes(r, saturated, **kw)
        return tuple(out[:8]), (out.ngood, out.power)

    def loss(r):
        values, _ = products(r)
        return sum(jnp.sum(w * q) for w, q in zip(weights, values, strict=True))

    # one compilation for all the Jacobians, one for all the perturbed losses
    jacobians, (ngood, power) = jax.jit(jax.jacrev(products, has_aux=True))(jnp.asarray(ramps))
    ngood, power = np.asarray(ngood), np.asarray(power)
    grad = sum(
        np.tensordot(w, np.asarray(j), axes=w.ndim) for w, j in zip(weights, jacobians, strict=True)
    )
    step = 1e-3
    shifts = np.zeros((ramps.size, *ramps.shape))
    shifts[(np.arange(ramps.size), *np.unravel_index(np.arange(ramps.size), ramps.shape))] = step
    perturbed = jnp.asarray(np.concatenate([ramps + shifts, ramps - shifts]))
    values = np.asarray(jax.jit(jax.vmap(loss))(perturbed))
    numeric = ((values[: ramps.size] - values[ramps.size :]) / (2 * step)).reshape(ramps.shape)
    np.testing.assert_allclose(grad, numeric, rtol=1e-6, atol=1e-9 * np.abs(numeric).max())
    assert np.all(grad[saturated] == 0)  # excluded groups do not move anything

    # the slope's gradient is the weighted fit's, for the weights in force
    slope_jacobian = np.asarray(jacobians[0])
    k = np.arange(ngroups)
    for i, y, x in np.ndindex(nints, ny, nx):
        n = int(ngood[i, y, x])
        p = float(power[i, y, x]) if n >= 3 else 0.0
        half = (n - 1) / 2
        w = np.where(k < n, np.abs((k - half) / half) ** p, 0.0)
        kbar = np.sum(w * k) / np.sum(w)
        expected = w * (k - kbar) / np.sum(w * (k - kbar) ** 2) / TFRAME
        np.testing.assert_allclose(
            slope_jacobian[i, y, x, i, :, y, x], expected, rtol=1e-9, atol=1e-12
        )
    assert len(set(power[ngood >= 3].tolist())) >= 3  # several weightings exercised


def test_power_table_and_weights():
    """stcal's S/N -> exponent table at its edges (an edge belongs to the upper bin), the
    S/N formula, and the weights |(k - m)/m|^P (P = 0: unweighted; odd n: middle 0)."""

    @jax.jit
    def helpers():
        snr = jnp.array([0.0, 4.99, 5.0, 9.99, 10.0, 19.99, 20.0, 49.99, 50.0, 99.99, 100.0, 1e4])
        weights = fixsen_weights(jnp.array([5, 4, 2, 6]), jnp.array([1.0, 0.0, 10.0, 3.0]), 6)
        # g D / sqrt(sigma_e^2 + g D): D = 100 DN, sigma = 5 DN, g = 2 -> 200 / sqrt(300)
        snr_value = segment_snr(jnp.array([100.0, -5.0]), 5.0, 2.0)
        return snr_power(snr), weights, snr_value

    powers, weights, snr_value = (np.asarray(a) for a in helpers())
    np.testing.assert_allclose(powers, [0, 0, 0.4, 0.4, 1, 1, 3, 3, 6, 6, 10, 10], rtol=1e-7)
    np.testing.assert_allclose(
        weights,
        [
            [1, 0.5, 0, 0.5, 1, 0],
            [1, 1, 1, 1, 0, 0],
            [1, 1, 0, 0, 0, 0],
            [1, 0.6**3, 0.2**3, 0.2**3, 0.6**3, 1],
        ],
        rtol=1e-6,
    )
    np.testing.assert_allclose(snr_value, [200 / np.sqrt(300), 0.0], rtol=1e-6)


def _charge_migration_flags(ramps, threshold=CHARGE_LOSS_THRESHOLD_DN):
    """The jwst charge_migration step's flags, written from its documentation: in each
    integration the first group above ``threshold`` and every later one, in the pixel
    and its four edge neighbours (no flags for ramps of 1 or 2 groups)."""
    _, ngroups, ny, nx = ramps.shape
    flags = np.zeros(ramps.shape, bool)
    if ngroups < 3:
        return flags
    for i, g, y, x in zip(*np.nonzero(ramps > threshold), strict=True):
        for dy, dx in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)):
            if 0 <= y + dy < ny and 0 <= x + dx < nx:
                flags[i, g:, y + dy, x + dx] = True
    return flags


def test_charge_migration_flags_against_stcal():
    """Newer pipelines (jwst >= 1.14, ``S_CHGMIG``) flag groups above 25,000 DN as
    CHARGELOSS + DO_NOT_USE; stcal then fits the leading unflagged groups. On noisy ramps
    bent 3.5 % low at their last group (the brighter-fatter effect's sign), rates 600 to
    6,000 DN per group over 8 groups, so that most pixels cross the threshold in some
    group: amigo's estimator with those groups masked gives stcal's slopes and Poisson
    variances to 1.2e-7 (measured). (stcal counts CHARGELOSS groups in the read-noise
    variance; amigo takes errors from the file, not from this estimator.)"""
    rng = np.random.default_rng(11)
    nints, ngroups, ny, nx = 3, 8, 6, 6
    read_noise, gain = _detector(rng, ny, nx)
    flux = np.linspace(600.0, 6000.0, ny * nx).reshape(ny, nx)
    last = ngroups * flux
    ramps = _simulate(
        rng, nints, ngroups, flux, read_noise, gain,
        bend=lambda linear: 14.0 * last * -np.expm1(-linear / (14.0 * last)),
    )  # fmt: skip
    flags = _charge_migration_flags(ramps)
    ngood = np.argmin(np.concatenate([~flags, np.zeros_like(flags[:, :1])], axis=1), axis=1)
    assert 0.3 < np.mean(ngood < ngroups) < 0.95  # most pixels cut, at several groups
    assert len(np.unique(ngood)) >= 4
    rate, rateints = _stcal(
        ramps, flags, **_timing(), groupgap=0, read_noise=read_noise, gain=gain, chargeloss=True
    )
    ours = _ours(ramps, flags, **_timing(), read_noise=read_noise, gain=gain)
    diffs = {
        "rateints.slope": _relative_difference(ours.slope, rateints["slope"]),
        "rateints.var_poisson": _relative_difference(ours.var_poisson, rateints["var_poisson"]),
        "rate.slope": _relative_difference(ours.rate, rate["slope"]),
    }
    _assert_agree(diffs)


def test_charge_loss_groups_emulate_the_step():
    """:func:`charge_loss_groups` from a level-2 rate image gives, for a noise-free
    linear ramp, the leading groups the step leaves unflagged, read from frames: each
    group the mean of its NFRAMES frames, read one frame time apart after the reset, with
    GROUPGAP frames dropped between groups (NISRAPID, and a 4-frame pattern with a gap)."""
    yy, xx = np.mgrid[:12, :12]
    rate = 9.0e4 * np.exp(-((yy - 5.3) ** 2 + (xx - 6.1) ** 2) / 6.0)  # DN/s
    for nframes, groupgap, ngroups in ((1, 0, 10), (4, 1, 6)):
        timing = _timing(nframes, groupgap)
        start = np.arange(ngroups) * (nframes + groupgap)  # first frame of each group
        frame_times = (start[:, None] + np.arange(nframes)[None] + 1) * TFRAME
        ramps = (rate[None] * frame_times.mean(axis=1)[:, None, None])[None]
        flags = _charge_migration_flags(ramps)
        expected = np.maximum(np.sum(~flags[0], axis=0), 2)
        used = charge_loss_groups(rate, ngroups, timing["tgroup"], TFRAME, nframes)
        np.testing.assert_array_equal(used, expected)
        assert used.min() < ngroups and np.sum(used < ngroups) > 10  # the core is cut
    assert np.all(charge_loss_groups(rate, 2, TFRAME, TFRAME) == 2)  # 2 groups: no flags


def test_model_slope_with_the_steps_groups_against_stcal():
    """The model side: :func:`pipeline_group_slope` of a noise-free bent ramp, with the
    groups :func:`charge_loss_groups` leaves, is stcal's slope of that ramp with the
    step's flags, to 8.5e-8 (measured). What the flags change: the same ramps fitted over
    all groups are 0.4-1.6 % lower in the pixels cut (measured), tens of errors of a
    bright level-2 pixel: without this a full-detector fit of a newer file is biased
    exactly in the core."""
    ngroups, ny, nx = 9, 5, 5
    flux = np.linspace(1500.0, 5000.0, ny * nx).reshape(ny, nx)  # DN per group
    last = ngroups * flux
    k = np.arange(1, ngroups + 1)[None, :, None, None]
    ramps = 14.0 * last * -np.expm1(-(flux * k) / (14.0 * last))
    flags = _charge_migration_flags(ramps)
    gain = np.full((ny, nx), GAIN, np.float32)
    read_noise = np.full((ny, nx), MODEL_READ_NOISE_CDS_DN, np.float32)
    _, rateints = _stcal(
        ramps.astype(np.float32), flags, **_timing(), groupgap=0, read_noise=read_noise,
        gain=gain, chargeloss=True,
    )  # fmt: skip
    stcal_slope = rateints["slope"][0] * TFRAME
    used = np.sum(~flags[0], axis=0)
    # the rate image the pipeline writes, through the emulation: the same groups
    np.testing.assert_array_equal(
        charge_loss_groups(rateints["slope"][0], ngroups, TFRAME, TFRAME), np.maximum(used, 2)
    )
    differences = np.diff(ramps[0], axis=0, prepend=0.0)[1:]
    with jax.enable_x64(True):
        ours = np.asarray(pipeline_group_slope(differences, TFRAME, GAIN, 1, used))
        full = np.asarray(pipeline_group_slope(differences, TFRAME, GAIN, 1))
    assert _relative_difference(ours, stcal_slope) < 2e-7
    cut = used < ngroups
    assert cut.sum() > 5
    change = 1.0 - full[cut] / ours[cut]
    assert 0.003 < change.min() and change.max() < 0.02


def test_no_saturation_map_is_every_group_usable():
    """``saturated=None`` (every group usable, its count written as a constant) gives what
    an all-false map gives through the prefix count: the same groups and weights, and the
    same products to float32 rounding (XLA simplifies arithmetic on a constant count
    differently: measured, within 9e-8 here; for three integrations of 12 groups of 80 x 80
    pixels the integrations' equal and the exposure's within 4e-7)."""
    rng = np.random.default_rng(12)
    read_noise, gain = _detector(rng, 3, 4)
    ramps = _simulate(rng, 2, 6, np.logspace(0.5, 3.5, 12).reshape(3, 4), read_noise, gain)
    kw = {"group_time": TFRAME, "read_noise": read_noise, "gain": gain}
    implicit = pipeline_slopes(ramps, **kw)
    explicit = pipeline_slopes(ramps, np.zeros(ramps.shape, bool), **kw)
    assert implicit.ngood.dtype == explicit.ngood.dtype
    np.testing.assert_array_equal(np.asarray(implicit.ngood), 6)
    np.testing.assert_array_equal(np.asarray(implicit.power), np.asarray(explicit.power))
    for a, b in zip(implicit, explicit, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-6)
    with jax.enable_x64(True):  # the count's integer type follows JAX's default, as the sum's
        wide = pipeline_slopes(ramps.astype(np.float64), **kw)
        summed = pipeline_slopes(ramps.astype(np.float64), np.zeros(ramps.shape, bool), **kw)
        assert wide.ngood.dtype == summed.ngood.dtype == np.int64
