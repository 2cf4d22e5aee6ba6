"""The Absil test's signal subspace (amigo.companions.subspace) against a separate
computation of a companion's signal, and its defining property: observables that no
companion moves do not change the limit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from amigo.companions import observables as obs
from amigo.companions.grid import Grid, contrast_grid, inner_working_angle_mas
from amigo.companions.limits import contrast_limits
from amigo.companions.models import disc_visibility, point_phasors
from amigo.companions.subspace import (
    SIGNAL_ENERGY_KEPT,
    signal_basis,
    signal_spaces,
    signal_vectors,
)
from amigo.io.calvis import read_calvis
from detect_helpers import binary_visibility, write_sim_calvis, write_sim_oifits


def _positions(grid: Grid, iwa_mas: float) -> np.ndarray:
    x, y = np.meshgrid(grid.x_mas, grid.y_mas)
    valid = grid.valid(iwa_mas)
    return np.stack([x[valid], y[valid]], axis=-1)


def test_signal_vectors_match_a_finite_difference_of_the_binary_model(tmp_path):
    """The whitened first-order signal of a companion against the test helpers' own
    binary visibility (plain NumPy), differenced at a flux ratio of 1e-7."""
    path = write_sim_calvis(
        tmp_path / "s_calvis.fits", "F430M", [], np.random.default_rng(3), splodge_radius_m=0.4
    )
    block = obs.load(path)
    calvis = read_calvis(path)
    sky = np.array([[120.0, -35.0], [-260.0, 310.0], [0.0, 95.0]])
    mine = signal_vectors([block], sky)
    c = 1e-7
    for row, theta in zip(mine, sky, strict=True):
        # The file's uv frame: offsets in it are S theta_sky.
        vis = binary_visibility(
            calvis.uv_m,
            calvis.wavelengths_m,
            calvis.weights / calvis.weights.sum(),
            (theta @ np.asarray(calvis.sky_to_uv).T)[None],
            np.array([c]),
        )
        log_vis = np.concatenate([np.log(np.abs(vis)), np.angle(vis)])
        theirs = calvis.disco_matrix @ log_vis / c / calvis.errors
        np.testing.assert_allclose(row, theirs, rtol=1e-5, atol=1e-5 * np.abs(theirs).max())


def test_the_basis_keeps_every_positions_signal_and_noise_has_k_degrees_of_freedom(tmp_path):
    rng = np.random.default_rng(5)
    block = obs.load(
        write_sim_calvis(tmp_path / "s_calvis.fits", "F480M", [], rng, splodge_radius_m=0.4)
    )
    grid = Grid.square(450.0, 15.0)
    signals = signal_vectors([block], _positions(grid, inner_working_angle_mas([block])))
    basis, kept = signal_basis(signals)
    k, n = basis.shape[1], block.n_obs
    assert 0 < k < n
    np.testing.assert_allclose(basis.T @ basis, np.eye(k), atol=1e-10)
    captured = np.sum((signals @ basis) ** 2, axis=1) / np.sum(signals**2, axis=1)
    assert captured.min() >= SIGNAL_ENERGY_KEPT - 1e-12
    assert kept == pytest.approx(captured.min())
    # One direction fewer loses more than the tolerance somewhere: k is the fewest.
    fewer = np.sum((signals @ basis[:, :-1]) ** 2, axis=1) / np.sum(signals**2, axis=1)
    assert fewer.min() < SIGNAL_ENERGY_KEPT
    # Unit-variance noise projected on k orthonormal directions: chi2 with k dof.
    noise = rng.normal(size=(4000, n))
    chi2 = np.sum((noise @ basis) ** 2, axis=1)
    assert stats.kstest(chi2, stats.chi2(k).cdf).pvalue > 1e-3


def test_observables_no_companion_moves_leave_the_absil_limit_unchanged(tmp_path):
    """The same file with 300 observables appended that no sky changes (pure noise): the
    test on every observable loses depth, the subspace's does not move."""
    companion = [(180.0, -120.0, 0.01)]
    files = [
        write_sim_calvis(
            tmp_path / f"{name}_F480M_calvis.fits",
            "F480M",
            companion,
            np.random.default_rng(8),
            splodge_radius_m=0.4,
            silent_rows=extra,
        )
        for name, extra in (("plain", 0), ("padded", 300))
    ]
    grid = Grid.square(450.0, 30.0)
    curves, spaces = [], []
    for path in files:
        dataset = obs.Dataset.from_blocks([obs.load(path)])
        offsets, fluxes = np.array([[180.0, -120.0]]), np.array([[0.01]])
        result = contrast_grid(dataset, grid, offsets, fluxes)
        space = signal_spaces(dataset, grid, offsets, fluxes, np.ones(dataset.n_groups))
        spaces.append(space["F480M"])
        curves.append(contrast_limits(result, signal_spaces=space)[0])
    plain, padded = spaces
    assert padded.n_obs == plain.n_obs + 300
    assert padded.dof == plain.dof < plain.n_obs
    assert padded.chi2_background == pytest.approx(plain.chi2_background, rel=1e-6)
    np.testing.assert_allclose(curves[1].absil_map_dmag, curves[0].absil_map_dmag, atol=1e-6)
    assert curves[0].absil_dof == plain.dof and curves[0].n_obs == plain.n_obs
    assert np.all(curves[1].absil_all_dmag < curves[0].absil_all_dmag)
    # Fewer degrees of freedom, a lower threshold: deeper than the test on every
    # observable (the same estimates and errors enter both).
    assert np.all(curves[0].absil_dmag > curves[0].absil_all_dmag)


def test_the_grey_companions_subspace_is_found_in_the_filters_coordinates(tmp_path):
    """All filters together: the span of a grey companion's signals side by side, found
    from each filter's subspace coordinates, is that of the full signals side by side,
    and smaller than the filters' dimensions summed."""
    rng = np.random.default_rng(21)
    blocks = [
        obs.load(
            write_sim_calvis(tmp_path / f"s_{f}_calvis.fits", f, [], rng, splodge_radius_m=0.4)
        )
        for f in ("F380M", "F480M")
    ]
    dataset = obs.Dataset.from_blocks(blocks)
    grid = Grid.square(400.0, 20.0)
    spaces = signal_spaces(dataset, grid, None, None, np.ones(dataset.n_groups))
    combined = spaces["combined"]
    assert combined.dof < spaces["F380M"].dof + spaces["F480M"].dof
    assert combined.n_obs == sum(b.n_obs for b in blocks)
    positions = _positions(grid, inner_working_angle_mas(blocks))
    full = np.concatenate([signal_vectors([b], positions) for b in blocks], axis=1)
    brute, _ = signal_basis(full)
    assert abs(brute.shape[1] - combined.dof) <= 2
    # The residuals' chi2 in it: the full residuals projected on the brute-force basis.
    residuals = np.concatenate(
        [np.asarray(b.residuals(np.ones(b.n_uv, dtype=complex))) for b in blocks]
    )
    assert combined.chi2_background == pytest.approx(
        float(np.sum((brute.T @ residuals) ** 2)), rel=0.05
    )


def test_signal_vectors_on_v2_and_closure_phases_about_a_resolved_star(tmp_path):
    """OIFITS V2 (exponential rows) and closure phases (a projection) about a 40-mas
    disc: the signal against a finite difference of the block's own residuals for a
    disc plus a companion of flux ratio 1e-7, written out here."""
    with jax.enable_x64(True):  # as amigo detect runs: a difference at 1e-7 needs it
        block = obs.load(
            write_sim_oifits(tmp_path / "s.oifits", np.random.default_rng(8), companion=None)
        )
        assert np.any(np.asarray(block.exp_rows))
        diameter, c = 40.0, 1e-7
        sky = np.array([[150.0, 40.0], [-90.0, -210.0]])
        mine = signal_vectors([block], sky, primary_diameter_mas=diameter)
        uv, wl, w = (jnp.asarray(a) for a in (block.uv_m, block.wavelengths_m, block.weights))
        disc = disc_visibility(uv, wl, w, diameter)
        for row, theta in zip(mine, sky, strict=True):
            phasor = point_phasors(uv, wl, w, jnp.asarray(theta))
            moved = block.residuals((disc + c * phasor) / (1.0 + c))
            theirs = (np.asarray(moved) - np.asarray(block.residuals(disc + 0j))) / c
            np.testing.assert_allclose(row, theirs, rtol=1e-4, atol=1e-4 * np.abs(theirs).max())
