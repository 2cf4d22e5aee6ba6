"""Visibility models and observables, against independent NumPy calculations."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import special

from amigo import niriss
from amigo.companions import observables as obs
from amigo.companions.models import airy_amplitude, disc_visibility, scene_visibility
from amigo.io.calvis import read_calvis, write_calvis
from amigo.io.oifits import read_oifits
from detect_helpers import (
    MAS,
    binary_v2_cp,
    binary_visibility,
    oifits_baselines,
    write_sim_calvis,
    write_sim_oifits,
)


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def test_airy_amplitude_matches_scipy_bessel():
    x = np.linspace(1e-6, 12.0, 400)
    np.testing.assert_allclose(airy_amplitude(jnp.asarray(x)), 2 * special.j1(x) / x, atol=1e-10)


def test_scene_visibility_is_the_fourier_transform_of_the_sky():
    """A pixelated disc + point companion, Fourier-summed pixel by pixel, per wavelength."""
    rng = np.random.default_rng(0)
    uv = rng.uniform(-5, 5, size=(12, 2))
    lams = np.array([3.9e-6, 4.3e-6, 4.7e-6])
    weights = np.array([0.2, 0.5, 0.3])
    diameter, offset, contrast = 40.0, np.array([230.0, -140.0]), 0.03
    # Sky image: a uniform disc (flux 1) sampled on a fine grid, plus a point companion.
    step = 0.5
    axis = np.arange(-25, 25 + step, step)
    x, y = np.meshgrid(axis, axis)
    disc = (np.hypot(x, y) <= diameter / 2).astype(float)
    xs = np.concatenate([x[disc > 0], [offset[0]]]) * MAS
    ys = np.concatenate([y[disc > 0], [offset[1]]]) * MAS
    flux = np.concatenate([np.full(int(disc.sum()), 1.0 / disc.sum()), [contrast]])
    expected = np.zeros(len(uv), complex)
    for lam, w in zip(lams, weights, strict=True):
        phase = -2j * np.pi * (np.outer(uv[:, 0], xs) + np.outer(uv[:, 1], ys)) / lam
        expected += w * (np.exp(phase) @ flux) / flux.sum()
    wl = np.broadcast_to(lams, (len(uv), 3))
    ww = np.broadcast_to(weights, (len(uv), 3))
    got = scene_visibility(
        jnp.asarray(uv),
        jnp.asarray(wl),
        jnp.asarray(ww),
        jnp.asarray([offset]),
        jnp.asarray([contrast]),
        diameter,
    )
    # The pixelated disc differs from the exact one at the 1e-3 level.
    np.testing.assert_allclose(np.asarray(got), expected, atol=2e-3)
    disc_only = disc_visibility(jnp.asarray(uv), jnp.asarray(wl), jnp.asarray(ww), diameter)
    assert np.all(np.asarray(disc_only) < 1.0)


def test_sign_convention_east_companion():
    """OIFITS convention: with u east, a companion east gives arg V < 0 for small u dRA."""
    lam = np.full((1, 1), 4.8e-6)
    u_east = jnp.asarray([[1.0, 0.0]])
    vis = scene_visibility(
        u_east, jnp.asarray(lam), jnp.ones((1, 1)), jnp.asarray([[100.0, 0.0]]), jnp.asarray([0.01])
    )
    phase = np.angle(np.asarray(vis))[0]
    expected = np.angle(1 + 0.01 * np.exp(-2j * np.pi * 1.0 * 100 * MAS / 4.8e-6))
    assert phase == pytest.approx(expected, rel=1e-9)
    assert phase < 0


def test_oifits_observables_match_independent_v2_and_closure_phases(tmp_path):
    rng = np.random.default_rng(3)
    companion = (180.0, -260.0, 0.05)
    path = write_sim_oifits(tmp_path / "b.oifits", rng, companion, cp_error_rad=1e-9, v2_error=1e-9)
    block = obs.from_oifits(read_oifits(path), band_samples=7)
    vis = scene_visibility(
        block.uv_m,
        block.wavelengths_m,
        block.weights,
        jnp.asarray([companion[:2]]),
        jnp.asarray([companion[2]]),
    )
    raw = np.asarray(block.raw(vis))
    holes, triangles = oifits_baselines()
    _, _, v2, _, _, cp = binary_v2_cp(holes, triangles, 4.817e-6, 2.98e-7, *companion)
    # The file stores float32 wavelengths: agreement to ~1e-7 relative.
    np.testing.assert_allclose(raw[:21], v2, atol=1e-6)
    np.testing.assert_allclose(raw[21:], cp, atol=1e-6)
    # The data read back are the same observables (noise 1e-9).
    np.testing.assert_allclose(np.asarray(block.data_raw), np.concatenate([v2, cp]), atol=1e-6)


def test_closure_phase_covariance_from_shared_baselines(tmp_path):
    path = write_sim_oifits(tmp_path / "n.oifits", np.random.default_rng(4), None)
    oi = read_oifits(path)
    cov = obs.baseline_closure_covariance(oi.t3.stations, oi.t3.wavelength_m, oi.t3.error_rad)
    values = np.linalg.eigvalsh(cov)
    nonzero = values[values > 1e-9 * values.max()]
    # 21 baselines - 6 piston differences = 15 independent closure phases, each carrying
    # N_holes / 3 times the variance of one closure phase.
    assert nonzero.size == 15
    np.testing.assert_allclose(nonzero, 7.0 / 3.0 * oi.t3.error_rad[0] ** 2, rtol=1e-9)
    block = obs.from_oifits(oi)
    assert block.n_obs == 21 + 15
    assert block.kinds == (0,) * 21 + (1,) * 15


def test_closure_phase_covariance_without_stations_and_of_several_exposures(tmp_path):
    """Without STA_INDEX the shared baselines are found from the triangles' coordinates
    (the same covariance as from the stations); a file listing its triangles twice (two
    exposures) keeps 30 independent combinations, not the 15 of one shared set of
    baseline phases."""
    from dataclasses import replace

    path = write_sim_oifits(tmp_path / "n.oifits", np.random.default_rng(4), None)
    t3 = read_oifits(path).t3
    legs = np.stack(
        [np.column_stack([t3.u1_m, t3.v1_m]), np.column_stack([t3.u2_m, t3.v2_m])], axis=1
    )
    by_stations = obs.baseline_closure_covariance(t3.stations, t3.wavelength_m, t3.error_rad)
    by_coordinates = obs.baseline_closure_covariance(None, t3.wavelength_m, t3.error_rad, legs)
    np.testing.assert_allclose(by_coordinates, by_stations, rtol=0, atol=1e-20)
    twice = {
        name: np.concatenate([getattr(t3, name)] * 2)
        for name in (
            "u1_m",
            "v1_m",
            "u2_m",
            "v2_m",
            "wavelength_m",
            "bandwidth_m",
            "phase_rad",
            "error_rad",
            "stations",
        )
    }
    # Two exposures (their own labels), or one listing its triangles twice: 30 either way.
    for exposure in (np.repeat([0, 1], len(t3.error_rad)), None):
        for stations in (twice["stations"], None):
            doubled = replace(t3, **{**twice, "stations": stations, "exposure": exposure})
            block = obs.from_oifits(replace(read_oifits(path), vis2=None, t3=doubled))
            assert block.n_obs == 30, (stations is None, exposure is None)
    # A flagged entry of the first exposure does not shift the second one's baselines:
    # the same covariance as the two exposures' own, with that entry left out.
    keep = np.ones(2 * len(t3.error_rad), bool)
    keep[3] = False
    labels = np.repeat([0, 1], len(t3.error_rad))[keep]
    legs2 = np.concatenate([legs, legs])[keep]
    flagged = obs.baseline_closure_covariance(
        None, twice["wavelength_m"][keep], twice["error_rad"][keep], legs2, labels
    )
    whole = obs.baseline_closure_covariance(
        None, twice["wavelength_m"], twice["error_rad"], np.concatenate([legs, legs]),
        np.repeat([0, 1], len(t3.error_rad)),
    )  # fmt: skip
    np.testing.assert_allclose(flagged, whole[np.ix_(keep, keep)], atol=1e-20)
    # Coordinates rounded to a millimetre in the file: still one baseline each.
    rounded = obs.baseline_closure_covariance(
        None, t3.wavelength_m, t3.error_rad, np.round(legs, 3)
    )
    np.testing.assert_allclose(rounded, by_stations, atol=1e-20)


def test_calvis_observables_match_independent_projection(tmp_path):
    rng = np.random.default_rng(5)
    companion = (-320.0, 60.0, 0.02)
    path = write_sim_calvis(
        tmp_path / "s_F430M_calvis.fits", "F430M", [companion], rng, error=1e-12
    )
    calvis = read_calvis(path)
    block = obs.load(path)
    assert block.linear
    vis = scene_visibility(
        block.uv_m,
        block.wavelengths_m,
        block.weights,
        jnp.asarray([companion[:2]]),
        jnp.asarray([companion[2]]),
    )
    # Independent: offsets in the uv frame from the stored matrix, visibilities at the
    # stored uv points, then the stored DISCO matrix.
    offset_uv = calvis.sky_to_uv @ np.array(companion[:2])
    expected_vis = binary_visibility(
        calvis.uv_m, calvis.wavelengths_m, calvis.weights, [offset_uv], [companion[2]]
    )
    log_vis = np.concatenate([np.log(np.abs(expected_vis)), np.angle(expected_vis)])
    np.testing.assert_allclose(
        np.asarray(block.predicted(vis)), calvis.disco_matrix @ log_vis, atol=1e-12
    )


def test_predicted_scenes_are_each_scenes_prediction(tmp_path):
    """The batched prediction of the posterior predictive figure: each row is
    :meth:`Observables.predicted` of its scene alone (two companions, three scenes)."""
    rng = np.random.default_rng(6)
    path = write_sim_calvis(tmp_path / "s_F480M_calvis.fits", "F480M", [(150.0, -40.0, 0.05)], rng)
    block = obs.load(path)
    offsets = rng.normal(0.0, 200.0, (3, 2, 2))
    contrasts = 10.0 ** rng.uniform(-3.0, -1.0, (3, 2))
    with jax.enable_x64(True):
        batched = np.asarray(obs.predicted_scenes(block, offsets, contrasts, 0.0))
        for k in range(3):
            vis = scene_visibility(
                block.uv_m, block.wavelengths_m, block.weights, offsets[k], contrasts[k]
            )
            single = np.asarray(block.predicted(vis))
            scale = np.abs(single).max()
            np.testing.assert_allclose(batched[k], single, rtol=1e-10, atol=1e-12 * scale)


def test_silent_uv_points_are_the_largest_weak_set_within_the_bound():
    rng = np.random.default_rng(11)
    n_obs, n_uv = 40, 30
    design = rng.normal(size=(n_obs, 2 * n_uv))
    weak = rng.choice(n_uv, 12, replace=False)
    scale = 10.0 ** rng.uniform(-6, -1, size=12)  # weak points of many strengths
    design[:, weak] *= scale
    design[:, n_uv + weak] *= scale
    errors = rng.uniform(0.5, 2.0, n_obs)
    tolerance = 0.05
    silent = obs.silent_uv_points(design, errors, tolerance)
    whitened = design / errors[:, None]
    both = np.concatenate([silent, silent])
    assert np.linalg.norm(whitened[:, both]) <= tolerance
    # Maximal: the next weakest point would break the bound.
    power = np.sum(whitened[:, :n_uv] ** 2, axis=0) + np.sum(whitened[:, n_uv:] ** 2, axis=0)
    nxt = np.argmin(np.where(silent, np.inf, power))
    assert np.sum(power[silent]) + power[nxt] > tolerance**2
    assert 0 < silent.sum() < 12 and set(np.flatnonzero(silent)) <= set(weak)
    # What it bounds: the whitened observables of any L move by at most tolerance |L_D|.
    for _ in range(5):
        log_vis = rng.normal(size=2 * n_uv)
        change = whitened[:, both] @ log_vis[both]
        assert np.linalg.norm(change) <= tolerance * np.linalg.norm(log_vis[both])


def test_calvis_points_beyond_the_splodges_are_left_out_within_the_bound(tmp_path):
    """A calvis file whose matrix spans knots the DISCOs barely weigh (as a fit's knot grid
    beyond the mask's transfer function): reading it leaves them out, takes the search's
    longest baseline where the information ends, and predicts every DISCO as the whole
    matrix does."""
    rng = np.random.default_rng(8)
    companion = (-150.0, 90.0, 0.05)
    path = write_sim_calvis(tmp_path / "s_F480M_calvis.fits", "F480M", [companion], rng)
    calvis = read_calvis(path)
    n_uv, n_far = calvis.uv_m.shape[0], 40
    far = rng.uniform(-9.0, 9.0, size=(n_far, 2))
    far[0] = (9.0, 9.0)  # the longest baseline of the file
    weights = 1e-8 * rng.normal(size=(calvis.n_obs, 2, n_far))  # whitened: ~5e-6
    d = calvis.disco_matrix
    matrix = np.concatenate([d[:, :n_uv], weights[:, 0], d[:, n_uv:], weights[:, 1]], axis=1)
    wide = tmp_path / "wide_F480M_calvis.fits"
    as_read = {f.name: getattr(calvis, f.name) for f in dataclasses.fields(calvis)}
    as_read.update(disco_matrix=matrix, uv_m=np.concatenate([calvis.uv_m, far]))
    write_calvis(wide, **as_read)
    block = obs.load(wide)
    every = obs.from_calvis(read_calvis(wide), str(wide), silent_tolerance=0.0)
    assert block.n_uv == n_uv and every.n_uv == n_uv + n_far
    longest = np.max(np.hypot(*(every.uv_m.T)))  # (9, 9) m, on the sky
    # The search's B_max is where the information ends, whatever points the file lists
    # (the far ones carry ~1e-10 of it) and whichever of them are read.
    reach = obs.information_radius_m(calvis.uv_m @ calvis.sky_to_uv, d, calvis.errors)
    assert block.max_baseline_m == every.max_baseline_m == pytest.approx(reach, abs=1e-9)
    assert reach < 0.8 * longest
    assert np.max(np.hypot(*(block.uv_m.T))) < 0.8 * longest
    offsets, contrasts = jnp.asarray([companion[:2]]), jnp.asarray([companion[2]])
    vis = scene_visibility(every.uv_m, every.wavelengths_m, every.weights, offsets, contrasts)
    z_all = every.residuals(vis)
    z = block.residuals(
        scene_visibility(block.uv_m, block.wavelengths_m, block.weights, offsets, contrasts)
    )
    far_vis = np.asarray(vis)[n_uv:]  # the appended points, the ones left out
    log_far = np.concatenate([np.log(np.abs(far_vis)), np.angle(far_vis)])
    bound = obs.SILENT_UV_TOLERANCE * np.linalg.norm(log_far)
    assert 0 < np.linalg.norm(np.asarray(z) - np.asarray(z_all)) <= bound


def test_select_kinds_keeps_one_type(tmp_path):
    path = write_sim_calvis(tmp_path / "s_F380M_calvis.fits", "F380M", [], np.random.default_rng(6))
    phase = obs.load(path, observables="phase")
    assert set(phase.kinds) == {1} and phase.n_obs == 15
    amp = obs.load(path, observables="amplitude")
    assert set(amp.kinds) == {0} and amp.n_obs == 14
    assert niriss.baselines_m().shape == (amp.n_uv, 2)


def test_the_information_radius_ends_with_the_points_that_carry_information():
    """A hand count: four points at 1, 2, 3 and 9 m carrying 50, 30, 19.5 and 0.5 % of
    the whitened information: 99 % lies within 3 m, all of it within 9."""
    uv = np.array([[1.0, 0.0], [0.0, 2.0], [3.0, 0.0], [0.0, 9.0]])
    power = np.array([0.5, 0.3, 0.195, 0.005])
    design = np.concatenate([np.diag(np.sqrt(power)), np.zeros((4, 4))], axis=1)
    errors = np.ones(4)
    assert obs.information_radius_m(uv, design, errors, 0.99) == 3.0
    assert obs.information_radius_m(uv, design, errors, 0.999) == 9.0
    assert obs.information_radius_m(uv, 2.0 * design, 2.0 * errors, 0.5) == 1.0
