"""1/f column stripes of level-2 images (amigo.likelihood.stripes): the whitening against a
dense covariance, the estimate of their width, and a fit through the public API."""

from __future__ import annotations

import numpy as np
import pytest

import amigo
from amigo.likelihood.stripes import column_gains, decorrelate, decorrelate_rows, stripe_sigma


def _image_noise(rng, shape=(80, 80)):
    """Per-pixel errors (DN/s) of a star-like image and a mask with holes."""
    y, x = np.indices(shape)
    error = 1.0 + 20.0 * np.exp(-((y - 40) ** 2 + (x - 42) ** 2) / 60.0)
    mask = rng.random(shape) > 0.05
    mask[:4] = False  # reference rows
    return error, mask


def test_decorrelate_whitens_the_columns_covariance_exactly():
    """``|P r|^2``, ``(P J) . (P r)`` equal ``r^T C^-1 r`` and ``J^T C^-1 r`` with the dense
    covariance ``C = diag(err^2) + tau^2 1 1^T`` of every column's used pixels."""
    rng = np.random.default_rng(0)
    error, mask = _image_noise(rng, (12, 7))
    inverse_sigma = np.where(mask, 1.0 / error, 0.0)
    tau = 0.8
    gains = column_gains(inverse_sigma, tau)
    r, j = rng.standard_normal((2, 12, 7)) * error
    pr = decorrelate(r * inverse_sigma, inverse_sigma, gains)
    pj = decorrelate(j * inverse_sigma, inverse_sigma, gains)
    quadratic = cross = 0.0
    for c in range(7):
        used = mask[:, c]
        cov = np.diag(error[used, c] ** 2) + tau**2
        quadratic += r[used, c] @ np.linalg.solve(cov, r[used, c])
        cross += j[used, c] @ np.linalg.solve(cov, r[used, c])
    assert np.sum(pr**2) == pytest.approx(quadratic, rel=1e-12)
    assert np.sum(pj * pr) == pytest.approx(cross, rel=1e-12)
    assert np.all(pr[~mask] == 0.0)
    # No stripes: nothing changes; many rows in place: the same as one by one.
    np.testing.assert_array_equal(decorrelate(pr, inverse_sigma, 0.0 * gains), pr)
    rows = rng.standard_normal((130, 12 * 7))
    expected = decorrelate(rows.reshape(130, 12, 7), inverse_sigma, gains).reshape(130, -1)
    decorrelate_rows(rows, inverse_sigma.ravel(), gains, chunk=64)
    np.testing.assert_allclose(rows, expected, rtol=1e-13, atol=1e-13)


def test_stripe_sigma_finds_stripes_and_no_false_ones():
    """White noise: no stripes in 40 of 40 images; stripes of 0.5 sigma: measured within
    15 %; a smooth offset across the columns (a starting model's error) is not taken for
    stripes."""
    rng = np.random.default_rng(1)
    error, mask = _image_noise(rng)
    inverse_sigma = np.where(mask, 1.0 / error, 0.0)
    star = (40.0, 42.0)
    found = [
        stripe_sigma(rng.standard_normal((80, 80)) * error, inverse_sigma, star) for _ in range(40)
    ]
    assert found == [0.0] * 40
    x = np.arange(80)
    smooth = 0.8 * np.cos(2 * np.pi * x / 40.0)[None, :]  # 0.8 DN/s, 40-pixel period
    assert stripe_sigma(rng.standard_normal((80, 80)) * error + smooth, inverse_sigma, star) < 0.2
    estimates = []
    for _ in range(10):
        stripes = 0.5 * rng.standard_normal(80)[None, :]
        noise = rng.standard_normal((80, 80)) * error
        estimates.append(stripe_sigma(noise + stripes, inverse_sigma, star))
    assert np.mean(estimates) == pytest.approx(0.5, rel=0.15)


def test_a_fit_marginalises_the_stripes_it_measures(tmp_path):
    """A simulated level-2 pair, the science image with 1/f column stripes (0.6 DN/s per
    column, over 0.3-2 DN/s of pixel noise), through ``amigo.fit``: their width is
    measured and marginalised, the calibrator's (none) is 0; the science image's z-scores
    whitened for them are at the noise, the plain ones are not."""
    from amigo.model.image import Instrument, save_instrument
    from jwst_files import nominal_star, write_level2

    model = tmp_path / "nominal.eqx"
    save_instrument(Instrument.nominal(n_wavelengths=3), model)
    image = nominal_star("F480M")
    error = np.sqrt(np.maximum(image, 0.0) / 80.0 + 0.1)
    rng = np.random.default_rng(3)
    tau = 0.6
    files = {}
    for role, obs, width in (("sci", "001", tau), ("cal", "002", 0.0)):
        stripes = width * rng.standard_normal(80)[None, :]
        files[role] = write_level2(
            tmp_path / f"{role}_cal.fits",
            image + error * rng.standard_normal(image.shape) + stripes,
            error,
            overrides={"FILTER": "F480M", "TARGPROP": f"STAR-{role}", "OBSERVTN": obs},
        )
    fitted = amigo.fit(
        [files["sci"]], [files["cal"]], tmp_path / "out", model=model, knots=27, knot_spacing=0.5
    )
    science, calibrator = fitted.summary["exposures"]
    assert science["column_stripes_dn_s"] == pytest.approx(tau, rel=0.3)
    assert calibrator["column_stripes_dn_s"] == 0.0
    assert calibrator["zscore_std_whitened"] == calibrator["zscore_std"]
    assert science["zscore_std_whitened"] == pytest.approx(1.0, abs=0.05)
    assert science["zscore_std"] > 1.1
