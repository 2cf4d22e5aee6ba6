"""Likelihoods against scipy's multivariate normal (an independent implementation)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal, norm

from amigo.likelihood.pixels import ImageData, PixelData, SlopeNoise, chi2, residuals

pytestmark = pytest.mark.usefixtures("x64")


def random_covariances(m, ny, nx, rng):
    """Slope covariances like real ones: photon variance on the diagonal, read noise
    -r^2 between adjacent slopes and 2 r^2 added on the diagonal."""
    photon = rng.uniform(10, 1000, (ny, nx))
    read = rng.uniform(5, 15, (ny, nx))
    cov = np.zeros((m, m, ny, nx))
    for i in range(m):
        cov[i, i] = photon + 2 * read**2
        if i + 1 < m:
            cov[i, i + 1] = cov[i + 1, i] = -(read**2)
    return cov


def test_slope_log_likelihood_matches_scipy():
    rng = np.random.default_rng(0)
    m, ny, nx = 4, 5, 6
    cov = random_covariances(m, ny, nx, rng)
    bad = np.zeros((ny, nx), bool)
    bad[0, :3] = True
    data = rng.normal(100, 10, (m, ny, nx))
    model = rng.normal(100, 10, (m, ny, nx))
    noise = SlopeNoise.from_covariance(cov, bad)
    expected = sum(
        multivariate_normal(model[:, y, x], cov[:, :, y, x]).logpdf(data[:, y, x])
        for y in range(ny)
        for x in range(nx)
        if not bad[y, x]
    )
    assert float(noise.log_likelihood(jnp.asarray(model), jnp.asarray(data))) == pytest.approx(
        expected, rel=1e-12
    )
    assert noise.n_values == m * (ny * nx - 3)


def test_diagonal_option_ignores_correlations():
    rng = np.random.default_rng(1)
    m, ny, nx = 3, 2, 2
    cov = random_covariances(m, ny, nx, rng)
    data = rng.normal(0, 30, (m, ny, nx))
    noise = SlopeNoise.from_covariance(cov, diagonal=True)
    sigma = np.sqrt(np.diagonal(cov.transpose(2, 3, 0, 1), axis1=2, axis2=3)).transpose(2, 0, 1)
    expected = norm(0, sigma).logpdf(data).sum()
    assert float(noise.log_likelihood(jnp.zeros_like(data), jnp.asarray(data))) == pytest.approx(
        expected, rel=1e-12
    )


def test_zscores_are_unit_normal_under_the_noise_model():
    rng = np.random.default_rng(2)
    m, ny, nx = 5, 20, 20
    cov = random_covariances(m, ny, nx, rng)
    chol = np.linalg.cholesky(cov.transpose(2, 3, 0, 1))
    draws = np.einsum("yxij,yxj->iyx", chol, rng.normal(size=(ny, nx, m)))
    z = np.asarray(SlopeNoise.from_covariance(cov).zscores(jnp.zeros((m, ny, nx)), draws))
    assert z.std() == pytest.approx(1.0, abs=0.05)
    # Correlations are removed: adjacent whitened slopes are uncorrelated.
    assert abs(np.corrcoef(z[:, 0], z[:, 1])[0, 1]) < 0.1


def test_non_positive_or_non_finite_covariances_are_dropped():
    rng = np.random.default_rng(3)
    cov = random_covariances(2, 3, 3, rng)
    cov[:, :, 0, 0] = np.nan
    cov[0, 1, 1, 1] = cov[1, 0, 1, 1] = 10 * cov[0, 0, 1, 1]  # not positive definite
    noise = SlopeNoise.from_covariance(cov)
    assert 0 not in noise.pixels and 4 not in noise.pixels and len(noise.pixels) == 7


def test_image_chi2_matches_direct_sum():
    rng = np.random.default_rng(4)
    data = rng.normal(0, 1, (8, 8))
    model = rng.normal(0, 1, (8, 8))
    err = rng.uniform(0.5, 2, (8, 8))
    usable = rng.uniform(size=(8, 8)) > 0.2
    image = ImageData(np.where(usable, data, 0.0), np.where(usable, err, 1.0), usable)
    pixels = PixelData.from_image(image, dtype=jnp.float64)
    expected = (((data - model) / err)[usable] ** 2).sum()
    assert float(chi2(jnp.asarray(model), pixels)) == pytest.approx(expected, rel=1e-12)
    assert float(jnp.abs(residuals(jnp.asarray(model), pixels)[~usable]).max()) == 0.0


def test_pooled_structure_is_unbiased_with_few_integrations():
    """With n = 8 integrations of m = 6 slopes the sample covariance's inverse is biased
    by (n - 1)/(n - m - 2) = 7x (Wishart); the pooled estimate gives chi2/m ~ 1."""
    rng = np.random.default_rng(7)
    m, npix, n = 6, 3000, 8
    true = np.zeros((m, m, npix))
    photon = rng.uniform(10, 1000, npix)
    read2 = 10.0**2  # one read noise for the detector
    for i in range(m):
        true[i, i] = photon + 2 * read2
        if i + 1 < m:
            true[i, i + 1] = true[i + 1, i] = -read2
    chol = np.linalg.cholesky(true.transpose(2, 0, 1))
    samples = np.einsum("pij,kpj->kpi", chol, rng.normal(size=(n, npix, m)))  # (n, npix, m)
    mean = samples.mean(axis=0)
    centred = samples - mean
    sample_cov_of_mean = np.einsum("kpi,kpj->ijp", centred, centred) / (n - 1) / n
    data = mean.T.reshape(m, 1, npix)
    zero = np.zeros_like(data)
    cov = sample_cov_of_mean.reshape(m, m, 1, npix)
    chi2 = {}
    for structure in ("full", "pooled"):
        noise = SlopeNoise.from_covariance(cov, structure=structure)
        z = np.asarray(noise.zscores(jnp.asarray(zero), jnp.asarray(data)))
        chi2[structure] = float((z**2).mean())
    assert chi2["full"] > 3.0  # the bias the structured estimate avoids
    assert chi2["pooled"] == pytest.approx(1.0, abs=0.15)  # ~1.1: its variances use n*m values


def _calslope(slopes, cov, badpix, support=100):
    from astropy.io import fits

    from amigo.io.calslope import CalSlope

    m, ny, nx = slopes.shape
    return CalSlope(
        slope_dn=slopes,
        slope_cov_dn2=cov,
        slope_support=np.full(slopes.shape, support),
        ramp_dn=np.zeros((m + 1, ny, nx)),
        ramp_cov_dn2=np.zeros((m + 1, m + 1, ny, nx)),
        ramp_support=np.full((m + 1, ny, nx), support),
        badpix=badpix,
        badpix_reason=None,
        primary_header=fits.Header(),
        slope_header=fits.Header(),
    )


def test_calslope_reduction_is_the_generalised_least_squares_rate():
    """The linear-detector image of a calslope file: per pixel, the GLS rate and its
    variance, checked against a direct solve; and the z-scores of a model image give the
    full slope-level chi2 (reduction term included)."""
    rng = np.random.default_rng(5)
    m, ny, nx, group_time = 4, 16, 16, 0.0754
    a = rng.normal(size=(ny * nx, m, m))
    cov = np.einsum("nij,nkj->nik", a, a) + 0.5 * np.eye(m)  # SPD per pixel
    slopes = rng.normal(50.0, 5.0, (ny * nx, m))
    badpix = np.zeros((ny, nx), bool)
    badpix[6, 7] = True
    product = _calslope(
        slopes.T.reshape(m, ny, nx), cov.transpose(1, 2, 0).reshape(m, m, ny, nx), badpix
    )
    image = ImageData.from_calslope(product, group_time, structure="full")
    one = np.ones(m)
    model = rng.normal(50.0, 5.0, (ny, nx)) / group_time
    expected_chi2 = 0.0
    for p in range(ny * nx):
        y, x = divmod(p, nx)
        if y < 4 or badpix[y, x]:  # reference rows and flagged pixels are dropped
            assert not image.mask[y, x]
            continue
        inv_one = np.linalg.solve(cov[p], one)
        information = one @ inv_one
        rate = inv_one @ slopes[p] / information
        assert image.data[y, x] == pytest.approx(rate / group_time, rel=1e-10)
        assert image.error[y, x] == pytest.approx(1 / np.sqrt(information) / group_time, rel=1e-10)
        r = slopes[p] - model[y, x] * group_time
        expected_chi2 += r @ np.linalg.solve(cov[p], r)
    z = image.zscores(model)
    assert z.size == image.n_pixels * m
    assert float(z @ z) == pytest.approx(expected_chi2, rel=1e-10)
