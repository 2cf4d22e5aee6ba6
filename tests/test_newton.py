"""The Levenberg-Marquardt pieces of amigo.newton against direct linear algebra."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from amigo.fitting import FitParams
from amigo.model import ExposureParams, OpticsParams, SourceParams
from amigo.newton import Layout, _Solver


def _params(rng, n_exposures=3, n_targets=2, n_amp=4, n_phase=5):
    return FitParams(
        exposures=ExposureParams(
            jnp.asarray(rng.normal(size=(n_exposures, 2)), jnp.float32),
            jnp.asarray(rng.normal(size=n_exposures), jnp.float32),
        ),
        sources=SourceParams(
            jnp.asarray(rng.normal(size=(n_targets, n_amp)), jnp.float32),
            jnp.asarray(rng.normal(size=(n_targets, n_phase)), jnp.float32),
            jnp.asarray(rng.normal(size=n_targets), jnp.float32),
        ),
        optics=OpticsParams(
            jnp.asarray(rng.normal(size=(7, 10)), jnp.float32), jnp.asarray(1.5, jnp.float32)
        ),
    )


def test_layout_round_trip_and_local_indices():
    rng = np.random.default_rng(0)
    params = _params(rng)
    layout = Layout.of(params)
    vector = layout.pack(params)
    assert vector.shape == (layout.size,) == (3 * 3 + 2 + 71 + 2 * 9,)
    back = layout.pack(layout.unpack(params, vector + 1.0))
    np.testing.assert_allclose(back, vector + 1.0, rtol=1e-6)
    # Exposure 2 of target 1: its position, flux, its target's slope and latents.
    local = layout.local(2, 1)
    p = layout.unpack(params, vector)
    np.testing.assert_allclose(vector[local[:2]], np.asarray(p.exposures.position_arcsec[2]))
    assert vector[local[2]] == pytest.approx(float(p.exposures.log_flux[2]))
    assert vector[local[3]] == pytest.approx(float(p.sources.slope_per_um[1]))
    latent = np.concatenate([p.sources.amp[1], p.sources.phase[1]])
    np.testing.assert_allclose(vector[local[4:]], latent)
    np.testing.assert_allclose(vector[layout.optics[:-1]], np.ravel(p.optics.zernikes_nm))


def test_undamped_step_is_the_newton_step_and_degeneracies_get_none():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(30, 6)) * np.array([1e3, 1, 1e-2, 5, 1, 1])  # mixed units
    fisher, grad = a.T @ a, rng.normal(size=6)
    np.testing.assert_allclose(_Solver(fisher)(grad, 0.0), np.linalg.solve(fisher, grad), rtol=1e-8)
    # Two exactly degenerate parameters (one column duplicated): no step along the
    # degenerate direction, and the step solves the system on the rest.
    b = np.column_stack([a, a[:, 1]])
    fisher = b.T @ b
    grad = b.T @ rng.normal(size=30)
    d = _Solver(fisher)(grad, 0.0)
    np.testing.assert_allclose(fisher @ d, grad, rtol=1e-6, atol=1e-8 * np.abs(grad).max())
    assert d[1] * np.sqrt(fisher[1, 1]) == pytest.approx(d[6] * np.sqrt(fisher[6, 6]), rel=1e-6)
    # Damping shortens the step.
    assert np.linalg.norm(_Solver(fisher)(grad, 10.0)) < np.linalg.norm(d)
