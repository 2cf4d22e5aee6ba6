"""1/f column stripes of level-2 images (amigo.likelihood.stripes): the whitening against a
dense covariance, the estimate of their width, and a fit through the public API."""

from __future__ import annotations

import numpy as np
import pytest

import amigo
from amigo.likelihood.stripes import (
    column_whiteners,
    decorrelate,
    decorrelate_rows,
    stripe_covariance,
    stripe_kernel,
)


def _image_noise(rng, shape=(80, 80)):
    """Per-pixel errors (DN/s) of a star-like image and a mask with holes."""
    y, x = np.indices(shape)
    error = 1.0 + 20.0 * np.exp(-((y - 40) ** 2 + (x - 42) ** 2) / 60.0)
    mask = rng.random(shape) > 0.05
    mask[:4] = False  # reference rows
    return error, mask


def _stripes(rng, tau, length, shape=(80, 80)):
    """(ny, nx) stripes: each column a draw of ``N(0, tau^2 exp(-|lag| / length))``."""
    factor = np.linalg.cholesky(tau**2 * stripe_kernel(shape[0], length) + 1e-12 * np.eye(shape[0]))
    return factor @ rng.standard_normal(shape)


@pytest.mark.parametrize("length", [3.0, np.inf])
def test_decorrelate_whitens_the_columns_covariance_exactly(length):
    """``|W r|^2``, ``(W J) . (W r)`` equal ``r^T C^-1 r`` and ``J^T C^-1 r`` with the dense
    covariance ``C = diag(err^2) + tau^2 K`` of every column's used pixels (``K`` the
    exponential kernel, or ones: one offset per column)."""
    rng = np.random.default_rng(0)
    error, mask = _image_noise(rng, (12, 7))
    inverse_sigma = np.where(mask, 1.0 / error, 0.0)
    tau = 0.8
    whiteners = column_whiteners(inverse_sigma[None], tau, length)[0]
    r, j = rng.standard_normal((2, 12, 7)) * error
    pr = decorrelate(r * inverse_sigma, whiteners)
    pj = decorrelate(j * inverse_sigma, whiteners)
    kernel = stripe_kernel(12, length)
    quadratic = cross = 0.0
    for c in range(7):
        used = mask[:, c]
        cov = np.diag(error[used, c] ** 2) + tau**2 * kernel[np.ix_(used, used)]
        quadratic += r[used, c] @ np.linalg.solve(cov, r[used, c])
        cross += j[used, c] @ np.linalg.solve(cov, r[used, c])
    assert np.sum(pr**2) == pytest.approx(quadratic, rel=1e-12)
    assert np.sum(pj * pr) == pytest.approx(cross, rel=1e-12)
    assert np.all(pr[~mask] == 0.0)
    # Symmetric: whitening twice is C^-1 (the fit's gradient relies on it).
    np.testing.assert_allclose(whiteners, np.swapaxes(whiteners, -1, -2), atol=1e-14)
    # No stripes: nothing changes; many rows in place: the same as one by one.
    identity = column_whiteners(inverse_sigma[None], 0.0, length)[0]
    np.testing.assert_array_equal(decorrelate(pr, identity), pr)
    rows = rng.standard_normal((130, 12 * 7))
    expected = decorrelate(rows.reshape(130, 12, 7), whiteners).reshape(130, -1)
    decorrelate_rows(rows, whiteners, chunk=64)
    np.testing.assert_allclose(rows, expected, rtol=1e-13, atol=1e-13)


def test_stripe_covariance_finds_stripes_and_no_false_ones():
    """White noise: stripes found in at most 4 of 180 images (about 1 %: the largest of
    the length grid's significances), whether ERR is right or 10 % off either way (the
    estimate needs no pixel variance); stripes of 0.5 sigma: their width within 15 % and
    their length within a factor 1.5 (10 rows) or long (one offset per column); a smooth
    offset across the columns (a starting model's error) is taken for stripes at under a
    tenth of its amplitude."""
    rng = np.random.default_rng(1)
    error, mask = _image_noise(rng)
    inverse_sigma = np.where(mask, 1.0 / error, 0.0)
    star = (40.0, 42.0)
    found = [
        stripe_covariance(rng.standard_normal((80, 80)) * error * scale, inverse_sigma, star)
        for scale in (0.9, 1.0, 1.1)
        for _ in range(60)
    ]
    false = [f for f in found if f != (0.0, np.inf)]
    assert len(false) <= 4
    x = np.arange(80)
    smooth = 4.0 * np.cos(2 * np.pi * x / 40.0)[None, :]  # 4 DN/s, 40-pixel period
    tau, _ = stripe_covariance(rng.standard_normal((80, 80)) * error + smooth, inverse_sigma, star)
    assert tau < 0.4
    for length, lengths in ((10.0, (10 / 1.5, 10 * 1.5)), (np.inf, (200.0, np.inf))):
        estimates = [
            stripe_covariance(
                rng.standard_normal((80, 80)) * error + _stripes(rng, 0.5, length),
                inverse_sigma,
                star,
            )
            for _ in range(10)
        ]
        taus, ells = np.array(estimates).T
        assert np.mean(taus) == pytest.approx(0.5, rel=0.15)
        assert lengths[0] < np.exp(np.mean(np.log(ells))) <= lengths[1]


def test_a_fit_marginalises_the_stripes_it_measures(tmp_path):
    """A simulated level-2 pair, the science image with 1/f column stripes (0.6 DN/s,
    correlated over 15 rows, over 0.3-2 DN/s of pixel noise), through ``amigo.fit``: their
    width and length are measured and marginalised, the calibrator's (none) is 0; the
    science image's z-scores whitened for them are at the noise, the plain ones are not."""
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
        stripes = _stripes(rng, width, 15.0) if width else 0.0
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
    assert 15.0 / 2 < science["column_stripes_length_pix"] < 15.0 * 2
    assert calibrator["column_stripes_dn_s"] == 0.0
    assert calibrator["column_stripes_length_pix"] is None
    assert calibrator["zscore_std_whitened"] == calibrator["zscore_std"]
    assert science["zscore_std_whitened"] == pytest.approx(1.0, abs=0.05)
    assert science["zscore_std"] > 1.1
