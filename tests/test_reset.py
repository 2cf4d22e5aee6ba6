"""The first group in the likelihood (amigo.model.detector.reset), checked against a brute-force
marginal likelihood of the whole ramp and against the count of photons it uses.

The ramps here come from a few lines of NumPy written for these tests (Poisson
photo-electrons, a per-integration reset offset, Gaussian read noise), not from
amigo's simulator.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from astropy.io import fits

from amigo.io.calslope import CalSlope
from amigo.likelihood.pixels import ImageData
from amigo.model.detector.reset import (
    UNKNOWN_VARIANCE_DN2,
    Superbias,
    estimate_superbias,
    superbias_of,
    with_first_group,
)

GAIN = 1.61  # e-/DN
GROUP_TIME = 0.07544  # s, NISRAPID SUB80


def ramps(rng, nints, ngroups, electrons_per_group, bias, reset_dn, read_dn):
    """(nints, ngroups, ny, nx) DN: reads one group time apart, the first one group time
    after the reset."""
    shape = (nints, ngroups, *np.shape(electrons_per_group))
    electrons = rng.poisson(np.broadcast_to(electrons_per_group, shape))
    reset = reset_dn * rng.standard_normal((nints, 1, *shape[2:]))
    read = read_dn * rng.standard_normal(shape)
    return bias + reset + np.cumsum(electrons, axis=1) / GAIN + read


def calslope(raw: np.ndarray, badpix: np.ndarray | None = None) -> CalSlope:
    """The calslope content of ramps (nints, ng, ny, nx): means over integrations and
    the covariances of those means."""
    n, _, ny, nx = raw.shape

    def mean_and_cov(x):
        mean = x.mean(axis=0)
        dev = x - mean
        cov = np.einsum("nayx,nbyx->abyx", dev, dev) / (n - 1) / n
        return mean, cov

    ramp, ramp_cov = mean_and_cov(raw)
    slope, slope_cov = mean_and_cov(np.diff(raw, axis=1))
    return CalSlope(
        slope_dn=slope,
        slope_cov_dn2=slope_cov,
        slope_support=np.full(slope.shape, float(n)),
        ramp_dn=ramp,
        ramp_cov_dn2=ramp_cov,
        ramp_support=np.full(ramp.shape, float(n)),
        badpix=np.zeros((ny, nx), bool) if badpix is None else badpix,
        badpix_reason=None,
        primary_header=fits.Header(),
        slope_header=fits.Header(),
    )


def test_superbias_from_ramps_with_light_is_unbiased_with_the_stated_error():
    """b_hat = r_1 - mean slope over 3 groups of illuminated ramps: its scatter about the
    true bias over 6400 pixels, in units of its stated error, has std ~1 and mean ~0;
    the inverse-variance combination of two files halves the variance."""
    rng = np.random.default_rng(1)
    bias = 12000.0 + 300.0 * rng.standard_normal((80, 80))
    light = rng.uniform(0.0, 2000.0, (80, 80))
    files = [calslope(ramps(rng, 60, 3, light, bias, 8.0, 10.0)) for _ in range(2)]
    one = superbias_of(files[0])
    z = (one.level_dn - bias) / np.sqrt(one.variance_dn2)
    assert abs(z.mean()) < 0.05
    assert z.std() == pytest.approx(1.0, abs=0.05)
    both = estimate_superbias(files)
    ratio = np.median(both.variance_dn2 / one.variance_dn2)
    assert ratio == pytest.approx(0.5, abs=0.05)
    assert both.n_files == 2


def test_first_group_likelihood_is_the_marginal_of_the_whole_ramp_over_the_reset_level():
    """Brute force: on a few pixels, integrate the Gaussian likelihood of the mean ramp
    (covariance C, reset included) times the superbias prior N(b_hat, s^2) over the
    reset level b numerically, as a function of the rate. Its log differs from the
    reduced image likelihood, -(rate - rate_hat)^2 / 2 var, by a constant; for 3 groups
    and for 1 group (then the first read is the only value)."""
    rng = np.random.default_rng(2)
    for ngroups in (3, 1):
        ny = nx = 16
        raw = ramps(rng, 40, ngroups, rng.uniform(200, 3000, (ny, nx)), 11000.0, 15.0, 12.0)
        product = calslope(raw)
        superbias = Superbias(
            level_dn=np.full((ny, nx), 11000.0) + rng.normal(0, 3.0, (ny, nx)),
            variance_dn2=np.full((ny, nx), 9.0),
        )
        image = ImageData.from_calslope(
            with_first_group(product, superbias), GROUP_TIME, structure="full", leading=1
        )
        times = np.arange(1, ngroups + 1) * GROUP_TIME  # read times after the reset
        for y, x in [(4, 0), (5, 3), (15, 15), (9, 2)]:  # rows 0-3 are reference pixels
            r = product.ramp_dn[:, y, x]
            cov = product.ramp_cov_dn2[:, :, y, x]
            b_hat, s = superbias.level_dn[y, x], np.sqrt(superbias.variance_dn2[y, x])
            bs = b_hat + s * np.linspace(-12, 12, 24001)
            prior = -0.5 * ((bs - b_hat) / s) ** 2

            def log_marginal(rate, r=r, cov=cov, bs=bs, prior=prior, times=times):
                resid = r[None] - bs[:, None] - rate * times[None]
                chi2 = np.einsum("bi,bi->b", resid, np.linalg.solve(cov, resid.T).T)
                log_terms = prior - 0.5 * chi2
                peak = log_terms.max()
                return peak + np.log(np.trapezoid(np.exp(log_terms - peak), bs))

            rate_hat, sigma = image.data[y, x], image.error[y, x]
            reference = log_marginal(rate_hat)
            for k in (-3.0, -1.0, 0.5, 2.0):
                rate = rate_hat + k * sigma
                assert log_marginal(rate) - reference == pytest.approx(-0.5 * k * k, abs=1e-6)


def test_the_first_group_adds_its_photons_to_the_fisher_information():
    """Photon-dominated pixels, 2 groups, a superbias from 2000 dark integrations: the
    information on each pixel's count rate (1 / error^2 of the reduced image) matches
    the analytic count of photons used, N_p = rate * NINTS * n_used * t_g (Poisson:
    Var(rate) = rate / (NINTS n_used t_g)), with n_used = NGROUPS with the first group
    and NGROUPS - 1 without: twice the information at two groups. The rates' scatter
    about the truth, in units of the stated errors, has std ~1 (the gain is real)."""
    rng = np.random.default_rng(3)
    ny = nx = 40
    ngroups, nints = 2, 400
    bias = 12000.0 + 300.0 * rng.standard_normal((ny, nx))
    electrons = np.full((ny, nx), 8000.0)  # per group: photon noise ~56 DN per read
    reset_dn, read_dn = 3.0, 2.0
    dark = calslope(ramps(rng, 2000, ngroups, np.zeros((ny, nx)), bias, reset_dn, read_dn))
    superbias = estimate_superbias([dark])
    science = calslope(ramps(rng, nints, ngroups, electrons, bias, reset_dn, read_dn))
    used = np.zeros((ny, nx), bool)
    used[4:] = True
    rate_dn_s = electrons[0, 0] / GAIN / GROUP_TIME
    information = {}
    for first, product in ((False, science), (True, with_first_group(science, superbias))):
        image = ImageData.from_calslope(product, GROUP_TIME, "full", leading=int(first))
        n_used = ngroups if first else ngroups - 1
        # Poisson information on the rate in DN/s: (NINTS n_used t_g) / (rate / gain)
        analytic = nints * n_used * GROUP_TIME * GAIN / rate_dn_s
        measured = np.mean(1.0 / image.error[used] ** 2)
        assert measured == pytest.approx(analytic, rel=0.04)
        z = (image.data[used] - rate_dn_s) / image.error[used]
        assert z.std() == pytest.approx(1.0, abs=0.06)
        information[first] = measured
    assert information[True] / information[False] == pytest.approx(2.0, rel=0.05)


def test_unknown_superbias_gives_back_the_slopes_likelihood():
    """Pixels without a superbias (UNKNOWN_VARIANCE_DN2), or without a first group, get
    the slopes-only rate."""
    rng = np.random.default_rng(4)
    product = calslope(ramps(rng, 50, 3, np.full((16, 16), 1000.0), 10000.0, 10.0, 10.0))
    unknown = Superbias(np.zeros((16, 16)), np.full((16, 16), UNKNOWN_VARIANCE_DN2))
    slopes = ImageData.from_calslope(product, GROUP_TIME, "full")
    first = ImageData.from_calslope(
        with_first_group(product, unknown), GROUP_TIME, "full", leading=1
    )
    used = slopes.mask
    np.testing.assert_allclose(first.data[used], slopes.data[used], rtol=1e-6)
    np.testing.assert_allclose(first.error[used], slopes.error[used], rtol=1e-6)
    # a pixel whose first group is undefined keeps its slopes, with or without a superbias
    known = Superbias(np.full((16, 16), 10000.0), np.full((16, 16), 1.0))
    ramp = product.ramp_dn.copy()
    ramp[0, 9, 5] = np.nan
    holed = dataclasses.replace(product, ramp_dn=ramp)
    image = ImageData.from_calslope(with_first_group(holed, known), GROUP_TIME, "full", leading=1)
    assert image.mask[9, 5]
    assert image.data[9, 5] == pytest.approx(slopes.data[9, 5], rel=1e-6)
    assert image.error[9, 10] < 0.9 * slopes.error[9, 10]  # its neighbour gains


def test_pooled_structure_keeps_the_first_groups_own_variance():
    """With few integrations (pooled covariance) the first value's variance (reset noise
    and the superbias' error on top of the slopes') is not averaged with the slopes'."""
    rng = np.random.default_rng(5)
    product = calslope(ramps(rng, 12, 4, np.full((16, 16), 50.0), 10000.0, 40.0, 10.0))
    superbias = Superbias(np.full((16, 16), 10000.0), np.full((16, 16), 25.0))
    extended = with_first_group(product, superbias)
    image = ImageData.from_calslope(extended, GROUP_TIME, "pooled", leading=1)
    slopes = ImageData.from_calslope(product, GROUP_TIME, "pooled")
    used = image.mask
    # reset noise 40 DN >> read 10 DN: the first value adds little, never a worse rate
    gain = (slopes.error[used] / image.error[used]) ** 2
    assert np.all(gain >= 1.0) and np.median(gain) < 1.1
