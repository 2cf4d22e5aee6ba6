"""Grid search and limits, against brute-force and SciPy calculations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import optimize, stats

from amigo.companions import observables as obs
from amigo.companions.fit import block_residuals
from amigo.companions.grid import Grid, contrast_grid, grid_statistics, sigma_from_chi2
from amigo.companions.limits import (
    COMBINED,
    absil_limit,
    azimuthal_profile,
    combine_filters,
    contrast_limits,
    photon_limit_dmag,
    ruffio_upper_limit,
)
from detect_helpers import write_sim_calvis, write_sim_oifits


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def _chi2(dataset, position, contrast, background=None):
    offsets = [position] if background is None else [*background[0], position]
    flux = [contrast] if background is None else [*background[1], contrast]
    r = block_residuals(dataset, jnp.asarray(offsets, float), jnp.asarray(flux, float)[:, None])
    return float(sum(jnp.sum(x**2) for x in r))


def _minimum(chi2):
    """Brute-force minimum of a chi2 over one flux ratio in (-0.3, 0.3) (SciPy, bounded)."""
    return optimize.minimize_scalar(
        chi2, bounds=(-0.3, 0.3), method="bounded", options={"xatol": 1e-10}
    )


@pytest.mark.parametrize("kind", ["calvis", "oifits"])
def test_grid_contrast_is_the_chi2_minimum(tmp_path, kind):
    """Each grid point's contrast, error and chi2 gain equal a brute-force 1-D minimisation."""
    rng = np.random.default_rng(11)
    if kind == "calvis":
        path = write_sim_calvis(
            tmp_path / "s_F480M_calvis.fits",
            "F480M",
            [(250.0, 150.0, 0.01), (-400.0, -90.0, 0.004)],
            rng,
        )
    else:
        path = write_sim_oifits(tmp_path / "s.oifits", rng, (250.0, 150.0, 0.01))
    dataset = obs.Dataset.from_blocks([obs.load(path)])
    grid = Grid.square(500.0, 100.0)
    background = ([(-400.0, -90.0)], [0.004])  # one companion in the background scene
    result = contrast_grid(dataset, grid, np.array(background[0]), np.array(background[1])[:, None])
    m = result.maps[0]
    chi2_0 = _chi2(dataset, (0.0, 0.0), 0.0, background)
    for iy, ix in [(7, 8), (3, 1), (5, 9), (1, 4)]:
        position = (grid.x_mas[ix], grid.y_mas[iy])
        solution = _minimum(lambda c, p=position: _chi2(dataset, p, c, background))
        assert m.contrast[iy, ix] == pytest.approx(solution.x, abs=1e-6 + 1e-4 * abs(solution.x))
        assert m.dchi2[iy, ix] == pytest.approx(chi2_0 - solution.fun, rel=1e-5, abs=1e-6)
        # sigma = (d2 chi2 / dc2 / 2)^-1/2 by finite differences.
        h = 1e-4
        curvature = (
            _chi2(dataset, position, solution.x + h, background)
            - 2 * solution.fun
            + _chi2(dataset, position, solution.x - h, background)
        ) / h**2
        assert m.sigma[iy, ix] == pytest.approx((curvature / 2) ** -0.5, rel=2e-2)


def test_grid_solved_again_for_new_error_scales(tmp_path):
    """The search solves a grid again for new error scales from the statistics it made
    once (no product with the DISCO matrix): each point then equals a brute-force
    minimisation of the chi2 with the amplitude and phase groups scaled differently."""
    rng = np.random.default_rng(13)
    path = write_sim_calvis(tmp_path / "s_F430M_calvis.fits", "F430M", [(250.0, 150.0, 0.01)], rng)
    dataset = obs.Dataset.from_blocks([obs.load(path)])
    assert dataset.n_groups == 2
    grid = Grid.square(500.0, 100.0)
    statistics = grid_statistics(dataset, grid)
    contrast_grid(dataset, grid, statistics=statistics)  # unit scales first, as the search
    scales = np.array([1.7, 0.6])
    m = contrast_grid(dataset, grid, group_scales=scales, statistics=statistics).maps[0]
    fresh = contrast_grid(dataset, grid, group_scales=scales).maps[0]
    np.testing.assert_allclose(m.dchi2, fresh.dchi2, rtol=1e-12, atol=1e-12)
    (scale_vector,) = dataset.scale_vectors(scales)

    def chi2(position, c):
        (r,) = block_residuals(dataset, jnp.asarray([position], float), jnp.full((1, 1), c))
        return float(jnp.sum((r / scale_vector) ** 2))

    chi2_0 = chi2((0.0, 0.0), 0.0)
    assert m.chi2_background == pytest.approx(chi2_0, rel=1e-12)
    for iy, ix in [(7, 8), (3, 1), (5, 9)]:
        position = (grid.x_mas[ix], grid.y_mas[iy])
        solution = _minimum(lambda c, p=position: chi2(p, c))
        assert m.contrast[iy, ix] == pytest.approx(solution.x, abs=1e-6 + 1e-4 * abs(solution.x))
        assert m.dchi2[iy, ix] == pytest.approx(chi2_0 - solution.fun, rel=1e-5, abs=1e-6)


def test_combined_map_is_the_grey_companions_chi2_minimum(tmp_path):
    """The combined map of two filters equals a brute-force minimisation of both filters'
    chi2 over one flux ratio shared by the filters; its curve counts both filters'
    photons and gives separations in lambda / D."""
    rng = np.random.default_rng(12)
    blocks = [
        obs.load(write_sim_calvis(tmp_path / f"s_{f}_calvis.fits", f, [(250.0, 150.0, c)], rng))
        for f, c in (("F380M", 0.012), ("F480M", 0.008))
    ]
    dataset = obs.Dataset.from_blocks(blocks)
    grid = Grid.square(500.0, 100.0)
    result = contrast_grid(dataset, grid)
    combined = combine_filters(result.maps)

    def chi2(position, c):
        r = block_residuals(dataset, jnp.asarray([position], float), jnp.full((1, 2), c))
        return float(sum(jnp.sum(x**2) for x in r))

    chi2_0 = chi2((0.0, 0.0), 0.0)
    for iy, ix in [(7, 8), (3, 1), (5, 9)]:
        position = (grid.x_mas[ix], grid.y_mas[iy])
        solution = _minimum(lambda c, p=position: chi2(p, c))
        assert combined.contrast[iy, ix] == pytest.approx(solution.x, abs=2e-5)
        # Each filter's chi2 taken as quadratic in c about its own minimum: 0.2 % here.
        assert combined.dchi2[iy, ix] == pytest.approx(chi2_0 - solution.fun, rel=5e-3, abs=1e-3)
    assert combined.n_obs == sum(m.n_obs for m in result.maps)
    curves = contrast_limits(
        result,
        photon_counts={"F380M": 1e8, "F480M": 3e8},
        wavelengths_m={"F380M": 3.8e-6, "F480M": 4.8e-6},
    )
    assert [c.filter_name for c in curves] == ["F380M", "F480M", COMBINED]
    assert curves[2].photon_limit_dmag == pytest.approx(photon_limit_dmag(4e8))
    lambda_d_mas = 4.3e-6 / 6.603464 * 180 / np.pi * 3600e3  # 134.3 mas
    np.testing.assert_allclose(curves[2].sep_lambda_d, curves[2].sep_mas / lambda_d_mas)
    # The grey combination is deeper than either filter where both see the companion's
    # absence equally (the companion-free outer annulus of the grid).
    assert curves[2].ruffio_dmag[-1] > max(c.ruffio_dmag[-1] for c in curves[:2])


def test_sigma_from_chi2():
    x = np.array([0.0, 1.0, 9.0, 25.0, 40.0])
    np.testing.assert_allclose(sigma_from_chi2(x, 1), np.sqrt(x))
    expected = stats.norm.isf(stats.chi2.sf(x, 3) / 2)
    np.testing.assert_allclose(sigma_from_chi2(x, 3)[1:], expected[1:], rtol=1e-9)
    big = sigma_from_chi2(np.array([1e4, 4e4]), 3)
    assert np.all(np.isfinite(big)) and big[1] > big[0] > 90


def test_grid_geometry():
    grid = Grid.square(1000.0, 10.0)
    assert grid.shape == (201, 201)
    valid = grid.valid(94.0)
    assert not valid[100, 100] and valid[100, 0] and not valid[0, 0]


def test_ruffio_limit_is_a_truncated_normal_quantile():
    c = np.array([-3e-4, 0.0, 2e-4, 1e-3])
    s = np.array([1e-4, 2e-4, 1e-4, 5e-4])
    q = stats.norm.cdf(3.0)
    expected = stats.truncnorm.ppf(q, (0 - c) / s, np.inf, loc=c, scale=s)
    np.testing.assert_allclose(ruffio_upper_limit(c, s, q), expected, rtol=1e-8)


def test_absil_limit_solves_the_exact_chi2_test(tmp_path):
    """The quadratic Absil limit equals a root-finding on the exact model's chi2."""
    path = write_sim_calvis(
        tmp_path / "n_F430M_calvis.fits", "F430M", [], np.random.default_rng(12)
    )
    dataset = obs.Dataset.from_blocks([obs.load(path)])
    grid = Grid.square(400.0, 100.0)
    m = contrast_grid(dataset, grid).maps[0]
    n, chi2_0 = m.n_obs, m.chi2_background
    target = stats.chi2.isf(2 * stats.norm.sf(3.0), n)
    for iy, ix in [(1, 2), (4, 0), (3, 3)]:
        position = (grid.x_mas[ix], grid.y_mas[iy])
        exact = optimize.brentq(
            lambda c, p=position: n * _chi2(dataset, p, c) / chi2_0 - target, 1e-6, 0.5
        )
        limit = absil_limit(m.contrast[iy, ix], m.sigma[iy, ix], chi2_0, n)
        assert limit == pytest.approx(exact, rel=0.02)


def test_photon_rule_and_azimuthal_profile():
    assert photon_limit_dmag(1e8) == pytest.approx(7.5)
    radius = np.array([[1.0, 2.0], [3.0, 4.0]])
    values = np.array([[1.0, 3.0], [5.0, 7.0]])
    centres, mean, std, count = azimuthal_profile(
        radius, values, np.ones((2, 2), bool), np.array([0.5, 2.5, 4.5])
    )
    np.testing.assert_allclose(centres, [1.5, 3.5])
    np.testing.assert_allclose(mean, [2.0, 6.0])
    np.testing.assert_allclose(std, [1.0, 1.0])
    np.testing.assert_array_equal(count, [2, 2])
