"""Physics and algorithm tests of amigo.processing.ramps, on ramps from an independent generator."""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest
from astropy.io import fits

from amigo import niriss
from amigo.processing.ramps import (
    BAD_DQ,
    BAD_LOW_SUPPORT,
    BAD_NO_NOISE,
    BAD_REFERENCE,
    BAD_SATURATED,
    ArraySource,
    ProcessSettings,
    adc_nonlinearity_dn,
    clip,
    clipping_influence,
    edge_density_factor,
    estimate_thresholds,
    nearest_psd,
    process_ramps,
    robust_centre_scale,
    usable_groups,
)
from ramp_sim import simulate


def _cov_diag(cov: np.ndarray) -> np.ndarray:
    """(k, k, ...) -> (k, ...) diagonal."""
    return np.moveaxis(np.diagonal(cov, axis1=0, axis2=1), -1, 0)


def test_adc_table_equals_the_sinusoid():
    rng = np.random.default_rng(0)
    counts = np.concatenate([np.arange(-3000, 70000, 7), rng.integers(0, 65536, 1000)])
    expected = 2.0 * np.sin(2.0 * np.pi * counts / 1024.0)
    np.testing.assert_allclose(adc_nonlinearity_dn(counts), expected, atol=1e-9)
    np.testing.assert_allclose(adc_nonlinearity_dn(counts.astype(float)), expected, atol=1e-9)
    fractional = rng.uniform(0, 65535, 1000)
    np.testing.assert_allclose(
        adc_nonlinearity_dn(fractional), 2.0 * np.sin(2.0 * np.pi * fractional / 1024.0)
    )


def test_slope_means_agree_with_truth_within_their_errors():
    rng = np.random.default_rng(1)
    flux = rng.uniform(20.0, 2000.0, (40, 40))
    ramps = simulate(
        rng, 150, 5, flux, bias_dn=rng.uniform(9000, 14000, flux.shape), cosmic_rate=0.02
    )
    product = process_ramps(ArraySource(ramps.raw))
    good = ~product.badpix
    assert good.sum() >= 0.95 * (~niriss.reference_row_mask(40, 40)).sum()
    resid = (product.slope_dn - ramps.flux_dn)[:, good]  # (G-1, npix)
    cov = product.slope_cov_dn2[:, :, good]
    z = resid / np.sqrt(_cov_diag(cov))
    assert abs(z.mean()) < 0.06
    assert 0.93 < z.std() < 1.07
    # The full covariance (anti-correlated adjacent slopes included) whitens the residuals.
    chi2 = np.einsum(
        "ip,ijp,jp->p", resid, np.linalg.inv(cov.transpose(2, 0, 1)).transpose(1, 2, 0), resid
    )
    assert 0.93 < chi2.mean() / resid.shape[0] < 1.07


def test_cosmic_rays_are_rejected_with_the_rest_of_their_ramp():
    rng = np.random.default_rng(2)
    flux_dn = 300.0
    flux = np.full((24, 24), flux_dn)
    ramps = simulate(rng, 200, 6, flux, cosmic_rate=0.03, cosmic_dn=(400.0, 3000.0))
    usable = usable_groups(ramps.raw)
    thresholds = estimate_thresholds(ramps.raw, usable, 3.0)
    keep = clip(ramps.raw, usable, thresholds)
    hit = ramps.hit_group >= 0
    n_hits = int(hit.sum())
    assert n_hits > 2000
    groups = np.arange(6)[None, :, None, None]
    after_hit = hit[:, None] & (groups >= ramps.hit_group[:, None])
    assert not np.any(keep & after_hit), "a ramp value after a cosmic ray was kept"
    # Few clean values are lost (3-sigma clipping, rest-of-ramp rule).
    clean = ~hit[:, None] & np.ones_like(keep)
    assert 1.0 - keep[clean].mean() < 0.04
    # Without clipping the slope means are biased by the steps; with it they are not.
    clipped = process_ramps(ArraySource(ramps.raw))
    unclipped = process_ramps(ArraySource(ramps.raw), ProcessSettings(nsigma=1e9))
    rows = ~niriss.reference_row_mask(24, 24)
    sigma = np.sqrt(_cov_diag(clipped.slope_cov_dn2))[:, rows]
    assert abs(((clipped.slope_dn[:, rows] - flux_dn) / sigma).mean()) < 0.1
    assert ((unclipped.slope_dn[:, rows] - flux_dn) / sigma).mean() > 3.0


def _sinusoid_amplitude(x: np.ndarray, residual: np.ndarray) -> float:
    phase = 2.0 * np.pi * x / 1024.0
    design = np.stack([np.sin(phase), np.cos(phase), np.ones_like(x)], axis=1)
    coeffs, *_ = np.linalg.lstsq(design, residual, rcond=None)
    return float(np.hypot(coeffs[0], coeffs[1]))


def test_adc_correction_removes_the_periodic_residual():
    rng = np.random.default_rng(3)
    shape = (32, 32)
    flux = np.full(shape, 37.0)
    bias = rng.uniform(10000.0, 12048.0, shape)  # spread over two ADC periods
    ramps = simulate(rng, 40, 3, flux, bias_dn=bias, read_dn=5.0)
    truth = bias[None] + flux[None] * np.arange(1, 4)[:, None, None]  # mean analog ramp
    amplitudes = {}
    for adc in (False, True):
        product = process_ramps(ArraySource(ramps.raw), ProcessSettings(adc_correction=adc))
        rows = ~product.badpix
        residual = (product.ramp_dn - truth)[:, rows].ravel()
        amplitudes[adc] = _sinusoid_amplitude(truth[:, rows].ravel(), residual)
    assert 1.8 < amplitudes[False] < 2.1  # the simulated 2 DN sinusoid is seen uncorrected
    assert amplitudes[False] / amplitudes[True] >= 4.0


def _scatter_vs_reported(means: np.ndarray, reported: np.ndarray) -> tuple[np.ndarray, ...]:
    """Empirical covariance of the means over pixels (= realisations), the mean reported
    covariance, and the standard error of each empirical element."""
    k = means.shape[0]
    flat = means.reshape(k, -1)
    empirical = np.cov(flat)
    mean_reported = reported.reshape(k, k, -1).mean(axis=-1)
    n = flat.shape[1]
    d = np.diag(empirical)
    stderr = np.sqrt((d[:, None] * d[None, :] + empirical**2) / n)
    return empirical, mean_reported, stderr


@pytest.mark.parametrize(("nints", "side"), [(40, 112), (300, 48)])
def test_reported_covariance_matches_the_scatter_of_the_means(nints, side):
    """Pixels with identical flux are independent realisations of the same exposure."""
    rng = np.random.default_rng(4 + nints)
    flux, read, ngroups = 200.0, 10.0, 4
    ramps = simulate(rng, nints, ngroups, np.full((side, side), flux), read_dn=read, adc=False)
    product = process_ramps(ArraySource(ramps.raw), ProcessSettings(adc_correction=False))
    for means, reported in (
        (product.slope_dn, product.slope_cov_dn2),
        (product.ramp_dn, product.ramp_cov_dn2),
    ):
        empirical, mean_reported, stderr = _scatter_vs_reported(means, reported)
        assert np.all(np.abs(empirical - mean_reported) < 4.0 * stderr + 0.02 * np.abs(empirical))

    # Read noise anti-correlates adjacent slopes: -sigma_read^2 / N (clipping adds ~5-10 %).
    empirical, mean_reported, _ = _scatter_vs_reported(product.slope_dn, product.slope_cov_dn2)
    analytic_adjacent = -(read**2) / nints
    analytic_diag = (flux / niriss.GAIN_E_PER_DN + 2 * read**2) / nints
    for k in range(ngroups - 2):
        assert 0.95 < mean_reported[k, k + 1] / analytic_adjacent < 1.2
        assert 0.95 < empirical[k, k + 1] / analytic_adjacent < 1.25
    assert np.all(
        (np.diag(mean_reported) / analytic_diag > 0.97)
        & (np.diag(mean_reported) / analytic_diag < 1.2)
    )
    # Slopes two apart share no read: uncorrelated.
    assert abs(mean_reported[0, 2]) < 0.05 * analytic_diag


def test_plain_covariance_of_clipped_means_is_too_small():
    """Why the clipping-influence term exists: without it the covariance fails the check."""
    rng = np.random.default_rng(5)
    ramps = simulate(rng, 40, 4, np.full((112, 112), 200.0), adc=False)
    plain = process_ramps(
        ArraySource(ramps.raw), ProcessSettings(adc_correction=False, covariance_correction=False)
    )
    empirical, mean_reported, _ = _scatter_vs_reported(plain.slope_dn, plain.slope_cov_dn2)
    ratio = np.diag(empirical) / np.diag(mean_reported)
    assert np.all(ratio > 1.08), ratio  # the scatter exceeds the plain estimate by 10-20 %


@pytest.mark.parametrize("n", [3, 5, 6, 9, 20, 200])
def test_robust_scale_is_unbiased_for_gaussian_data(n):
    rng = np.random.default_rng(n)
    values = rng.normal(5.0, 70.0, (n, min(200_000, 4_000_000 // n)))  # far above the floor
    _, scale = robust_centre_scale(values, np.ones(values.shape, dtype=bool))
    assert scale.mean() == pytest.approx(70.0, rel=0.01)


def test_edge_density_factor_limits():
    # Many sample integrations: the Gaussian value 2 k phi(k).
    k = 3.0
    assert edge_density_factor(k, 10**9) == pytest.approx(
        2 * k * math.exp(-k * k / 2) / math.sqrt(2 * math.pi), rel=1e-4
    )
    # An uncertain scale makes a band edge fall where the density is higher, on average.
    assert edge_density_factor(k, 40) > 1.5 * edge_density_factor(k, 10**9)


def test_clipping_influence_of_a_single_band():
    """Two groups, uncorrelated reads: check the correction against the hand formula."""
    var0, var1 = 4.0, 9.0
    cov = np.zeros((2, 2, 1, 1))
    cov[0, 0], cov[1, 1] = var0, var1
    n = 500
    delta_ramp, delta_slope = clipping_influence(cov, n, n, 3.0)
    a = edge_density_factor(3.0, n)
    # Ramp 0: its own band only (slope band 0 removes group 1, not group 0).
    # Cross term 2 a var0 / N and median term a^2 var0 (pi/2) / n.
    assert delta_ramp[0, 0, 0, 0] == pytest.approx(2 * a * var0 / n + a**2 * var0 * math.pi / 2 / n)
    # Slope d = x1 - x0 (variance 13) is removed by ramp band 0 (x0), ramp band 1 (x1) and
    # its own band; D = a (Cov(d, y_w) / Var(y_w)) for y_w in (x0, x1, d) = a (-1, 1, 1).
    sigma = np.array([[var0, 0, -var0], [0, var1, var1], [-var0, var1, var0 + var1]])
    d = a * np.array([-1.0, 1.0, 1.0])
    sd = np.sqrt(np.diag(sigma))
    r = np.outer(sd, sd) * np.arcsin(np.clip(sigma / np.outer(sd, sd), -1, 1))
    expected = 2 * d @ sigma[:, 2] / n + d @ r @ d / n
    assert delta_slope[0, 0, 0, 0] == pytest.approx(expected)


def test_nearest_psd_clips_negative_eigenvalues_only():
    rng = np.random.default_rng(11)
    a = rng.normal(size=(5, 4, 4))
    psd = a @ np.swapaxes(a, 1, 2)  # already positive definite: unchanged
    np.testing.assert_allclose(nearest_psd(psd), psd, rtol=1e-12, atol=1e-12)
    # A pairwise-deletion matrix that is not PSD: the implied slope variance
    # C00 + C11 - 2 C01 = 4 + 9 - 2 * 7 = -1 is negative.
    bad = np.array([[[4.0, 7.0], [7.0, 9.0]]])
    fixed = nearest_psd(bad)[0]
    values, vectors = np.linalg.eigh(bad[0])
    expected = values[1] * np.outer(vectors[:, 1], vectors[:, 1])  # the negative one dropped
    np.testing.assert_allclose(fixed, expected, rtol=1e-12)
    assert np.linalg.eigvalsh(fixed).min() > -1e-12
    assert np.isnan(nearest_psd(np.full((1, 2, 2), np.nan))).all()


def test_clipping_influence_is_finite_for_a_pairwise_covariance_that_is_not_psd():
    """Found at 10 integrations of 12 groups: a negative implied slope variance made the
    correction NaN, and a quarter of the pixels were flagged 'no noise'."""
    cov = np.array([[4.0, 7.0], [7.0, 9.0]]).reshape(2, 2, 1, 1)
    delta_ramp, delta_slope = clipping_influence(cov, 10, 10, 3.0)
    assert np.all(np.isfinite(delta_ramp)) and np.all(np.isfinite(delta_slope))


def test_covariance_correction_flags_no_pixel_at_few_integrations():
    rng = np.random.default_rng(12)
    ramps = simulate(rng, 10, 12, np.full((36, 36), 200.0), read_dn=10.0, adc=False)
    flagged = {}
    for correction in (False, True):
        settings = ProcessSettings(adc_correction=False, covariance_correction=correction)
        product = process_ramps(ArraySource(ramps.raw), settings)
        flagged[correction] = (product.badpix_reason & BAD_NO_NOISE) != 0
    # Only pixels without a usable variance in the plain covariance lose it.
    assert not np.any(flagged[True] & ~flagged[False])


# --------------------------------------------------------------------------------------
# Streaming == a plain in-memory implementation written here, integration by integration
# --------------------------------------------------------------------------------------


def _reference(raw, group_dq, pixel_dq, nsigma, n_sample_max, min_support, max_saturated):
    """Per-pixel scalar implementation of the documented algorithm (no covariance term)."""
    nints, ngroups, ny, nx = raw.shape
    n_sample = min(nints, n_sample_max)
    sample = sorted({round(v) for v in np.linspace(0, nints - 1, n_sample)})
    x_all = raw - 2.0 * np.sin(2.0 * np.pi * raw / 1024.0)

    def band(values):
        if not values:
            return math.nan, math.nan
        centre = statistics.median(values)
        n = len(values)
        small = {2: 1.196, 3: 1.495, 4: 1.363, 5: 1.206, 6: 1.2, 7: 1.14, 8: 1.129, 9: 1.107}
        factor = small.get(n, n / (n - 0.8) if n > 9 else 1.0)
        scale = factor * 1.482602218505602 * statistics.median([abs(v - centre) for v in values])
        return centre, max(scale, 1.0)

    def inside(value, c, s):
        return not math.isnan(c) and abs(value - c) <= nsigma * s

    out = {
        key: np.full(shape, np.nan)
        for key, shape in (
            ("slope", (ngroups - 1, ny, nx)),
            ("slope_cov", (ngroups - 1, ngroups - 1, ny, nx)),
            ("ramp", (ngroups, ny, nx)),
            ("ramp_cov", (ngroups, ngroups, ny, nx)),
            ("slope_sup", (ngroups - 1, ny, nx)),
            ("ramp_sup", (ngroups, ny, nx)),
        )
    }
    reason = np.zeros((ny, nx), dtype=np.uint8)
    for y in range(ny):
        for xpix in range(nx):
            x = x_all[:, :, y, xpix]
            usable_len = []
            n_sat = 0
            for i in range(nints):
                length = 0
                while (
                    length < ngroups
                    and raw[i, length, y, xpix] < 65535
                    and (group_dq[i, length, y, xpix] & 11) == 0
                ):
                    length += 1
                usable_len.append(length)
                n_sat += bool(
                    np.any(raw[i, :, y, xpix] >= 65535) or np.any(group_dq[i, :, y, xpix] & 2)
                )
            ramp_bands = [
                band([x[i, g] for i in sample if usable_len[i] > g]) for g in range(ngroups)
            ]

            def ramp_length(i, ramp_bands=ramp_bands, x=x, usable_len=usable_len):
                length = 0
                while length < usable_len[i] and inside(x[i, length], *ramp_bands[length]):
                    length += 1
                return length

            slope_bands = [
                band([x[i, k + 1] - x[i, k] for i in sample if ramp_length(i) > k + 1])
                for k in range(ngroups - 1)
            ]
            lengths = []
            for i in range(nints):
                length = ramp_length(i)
                for k in range(length - 1):
                    if not inside(x[i, k + 1] - x[i, k], *slope_bands[k]):
                        length = k + 1
                        break
                lengths.append(length)
            lengths = np.array(lengths)
            for name, values, offset in (("ramp", x, 0), ("slope", np.diff(x, axis=1), 1)):
                k = values.shape[1]
                sup = np.array([(lengths > g + offset).sum() for g in range(k)])
                out[f"{name}_sup"][:, y, xpix] = sup
                for g in range(k):
                    if sup[g]:
                        out[name][g, y, xpix] = values[lengths > g + offset, g].mean()
                    for h in range(k):
                        both = lengths > max(g, h) + offset
                        if both.sum() >= 2:
                            c = np.cov(values[both, g], values[both, h])[0, 1]
                            out[f"{name}_cov"][g, h, y, xpix] = c * both.sum() / (sup[g] * sup[h])
            if y < 4:
                reason[y, xpix] |= BAD_REFERENCE
            if out["slope_sup"][:, y, xpix].min() < max(min_support, math.ceil(0.5 * nints)):
                reason[y, xpix] |= BAD_LOW_SUPPORT
            if pixel_dq[y, xpix] & 1:
                reason[y, xpix] |= BAD_DQ
            if n_sat > max_saturated * nints:
                reason[y, xpix] |= BAD_SATURATED
            variances = np.diag(out["slope_cov"][:, :, y, xpix])
            if not np.all(variances > 0):
                reason[y, xpix] |= BAD_NO_NOISE
    return out, reason


def test_streaming_equals_in_memory_reference():
    rng = np.random.default_rng(6)
    nints, ngroups, ny, nx = 31, 4, 6, 5
    flux = rng.uniform(10.0, 400.0, (ny, nx))
    raw = simulate(
        rng, nints, ngroups, flux, bias_dn=rng.uniform(9000, 60000, (ny, nx)), cosmic_rate=0.1
    ).raw
    raw[:, 2:, 5, 1] = 65535  # saturates from group 2 on in every integration
    raw[7, 3, 5, 2] = 65535  # one saturated group
    raw[:, :, 4, 4] = 20000  # dead pixel: no noise
    group_dq = np.zeros(raw.shape, dtype=np.uint8)
    group_dq[3, 1, 4, 0] = 1  # DO_NOT_USE
    group_dq[9, 2, 4, 1] = 4  # JUMP_DET: ignored
    group_dq[11:, 0, 4, 3] = 1  # most integrations unusable: low support
    pixel_dq = np.zeros((ny, nx), dtype=np.uint32)
    pixel_dq[5, 3] = 1 | 1024
    settings = ProcessSettings(
        max_sample_ints=9,
        chunk_values=2 * ngroups * ny * nx,
        covariance_correction=False,
        max_saturated_fraction=0.05,
    )
    product = process_ramps(ArraySource(raw, group_dq), settings, pixel_dq=pixel_dq)
    assert product.n_sample == 9
    ref, reason = _reference(raw, group_dq, pixel_dq, 3.0, 9, settings.min_support, 0.05)
    for key, value in (
        ("slope", product.slope_dn),
        ("slope_cov", product.slope_cov_dn2),
        ("ramp", product.ramp_dn),
        ("ramp_cov", product.ramp_cov_dn2),
        ("slope_sup", product.slope_support),
        ("ramp_sup", product.ramp_support),
    ):
        np.testing.assert_allclose(
            value, ref[key], rtol=1e-9, atol=1e-9, equal_nan=True, err_msg=key
        )
    np.testing.assert_array_equal(product.badpix_reason, reason)
    assert reason[5, 1] & BAD_SATURATED and not reason[5, 2] & BAD_SATURATED
    assert reason[4, 4] & BAD_NO_NOISE and reason[4, 3] & BAD_LOW_SUPPORT
    assert reason[5, 3] & BAD_DQ
    # More than half the pixel-integrations with a cosmic ray at 10 %: some were clipped.
    assert product.n_rejected_slope + product.n_rejected_ramp > 0


def test_one_group_keeps_its_read_and_no_slope(tmp_path):
    """NGROUPS = 1: no group difference exists; the read's mean and its covariance are the
    exposure's measurement (fitted less a superbias, amigo.model.detector.reset) and survive the
    calslope file as zero-length SLOPE arrays."""
    from amigo.io.calslope import read_calslope, write_calslope
    from ramp_sim import PRIMARY_KEYWORDS, SCI_KEYWORDS

    rng = np.random.default_rng(21)
    nints, side, flux, read, bias = 50, 80, 300.0, 12.0, 10000.0
    ramps = simulate(rng, nints, 1, np.full((side, side), flux), bias, read_dn=read, adc=False)
    product = process_ramps(ArraySource(ramps.raw), ProcessSettings(adc_correction=False))
    assert product.slope_dn.shape == (0, side, side)
    assert product.slope_cov_dn2.shape == (0, 0, side, side)
    assert product.ramp_dn.shape == (1, side, side)
    light = ~niriss.reference_row_mask(side, side)
    assert not product.badpix[light].any()  # support and noise judged on the read
    # Pixels of equal flux are realisations: the reported variance of the mean read is
    # the scatter of the means, and both are (photons + read noise) / N.
    means = product.ramp_dn[0][light]
    reported = product.ramp_cov_dn2[0, 0][light]
    analytic = (flux / niriss.GAIN_E_PER_DN + read**2) / nints
    assert np.mean(means) == pytest.approx(bias + flux, abs=3 * np.sqrt(analytic / means.size))
    assert np.var(means, ddof=1) / analytic == pytest.approx(1.0, abs=0.1)
    assert np.median(reported) / analytic == pytest.approx(1.0, abs=0.1)

    primary, sci = fits.Header(), fits.Header()
    for key, value in {**PRIMARY_KEYWORDS, "NINTS": nints, "NGROUPS": 1}.items():
        primary[key] = value
    for key, value in SCI_KEYWORDS.items():
        sci[key] = value
    path = write_calslope(tmp_path / "g_calslope.fits", product, primary, sci, uncal_name="g")
    back = read_calslope(path)
    assert back.slope_dn.shape == (0, side, side) and back.slope_cov_dn2.shape == (0, 0, side, side)
    np.testing.assert_allclose(back.ramp_dn, product.ramp_dn, rtol=1e-6)
