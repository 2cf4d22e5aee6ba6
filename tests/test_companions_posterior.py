"""NUTS's potential in float32: the same posterior density, at half the cost.

The float32 evaluation (``Dataset.single_precision``) is only worth having if every
large product really runs in float32 (one float64 constant in the scene promotes the rest
of the program back to float64), and only safe if its value and gradient agree with the
float64 potential far below what moves a sample.
"""

from __future__ import annotations

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from amigo.companions import observables as obs
from amigo.companions.posterior import _potential
from detect_helpers import write_sim_calvis

TRUTH = (-323.4, 59.9, 0.0188)


def _dataset(tmp_path) -> obs.Dataset:
    rng = np.random.default_rng(3)
    blocks = [
        obs.load(
            write_sim_calvis(tmp_path / f"S_{f}_calvis.fits", f, [TRUTH], rng, splodge_radius_m=0.4)
        )
        for f in ("F380M", "F480M")
    ]
    return obs.Dataset.from_blocks(blocks)


def _point(dataset: obs.Dataset):
    """Unconstrained coordinates a little off the truth, and the priors' boxes."""
    k, f, g = 1, dataset.n_filters, dataset.n_groups
    bounds = {
        "dra": (np.full(k, TRUTH[0] - 75.0), np.full(k, TRUTH[0] + 75.0)),
        "ddec": (np.full(k, TRUTH[1] - 75.0), np.full(k, TRUTH[1] + 75.0)),
        "log10c": (np.full((k, f), -3.0), np.full((k, f), -1.0)),
        "scale": (np.full(g, 0.01), np.full(g, 100.0)),
    }
    z = {
        "dra": jnp.full(k, 0.01),
        "ddec": jnp.full(k, -0.02),
        "log10c": jnp.full((k, f), 0.1),
        "scale": jnp.full(g, -4.6),
    }
    return z, bounds


def _matrix_products(jaxpr) -> list:
    """The dtypes of every dot_general with an operand of over 1000 elements (recursing
    into sub-programs)."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            if max(np.prod(v.aval.shape) for v in eqn.invars) > 1000:
                found.append(tuple(str(v.aval.dtype) for v in eqn.invars))
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            found.extend(_matrix_products(sub))
    return found


def test_the_float32_potential_agrees_and_runs_in_float32(tmp_path):
    with jax.enable_x64(True):
        dataset = _dataset(tmp_path)
        z, bounds = _point(dataset)
        single = dataset.single_precision()

        def value_and_gradient(d):
            return jax.value_and_grad(lambda q: _potential(q, d, bounds, 0.0))(z)

        v64, g64 = value_and_gradient(dataset)
        v32, g32 = value_and_gradient(single)
        # chi2 / 2 of ~1800 observables: float32 residuals round it by ~1e-4.
        assert abs(float(v32) - float(v64)) < 1e-2
        for name in g64:
            scale = float(jnp.max(jnp.abs(g64[name])))
            assert float(jnp.max(jnp.abs(g32[name] - g64[name]))) < 1e-3 * scale + 1e-3
        program = jax.make_jaxpr(jax.value_and_grad(lambda q: _potential(q, single, bounds, 0.0)))(
            z
        )
        products = _matrix_products(program.jaxpr)
        assert products, "the observable matrices' products were not found"
        assert all(d == ("float32", "float32") for d in products), products
        # and the float64 dataset's stay float64 (nothing narrows it by accident)
        program = jax.make_jaxpr(jax.value_and_grad(lambda q: _potential(q, dataset, bounds, 0.0)))(
            z
        )
        assert all(d == ("float64", "float64") for d in _matrix_products(program.jaxpr))


def test_the_design_is_stored_without_its_zero_quarter(tmp_path):
    """A calvis file's DISCO amplitudes do not depend on arg V: stored without that zero
    half, the products are the whole matrix's (to rounding) and read a quarter less."""
    with jax.enable_x64(True):
        block = _dataset(tmp_path).blocks[0]
        rng = np.random.default_rng(5)
        full = block.design
        n_cols = full.shape[1]
        n_amplitudes = sum(k == 0 for k in block.kinds)
        assert n_amplitudes > 0 and block.design_head.shape[0] == n_amplitudes
        assert block.design_head.size + block.design_tail.size == full.size - n_amplitudes * (
            n_cols // 2
        )
        log_vis = rng.normal(size=(3, n_cols))
        np.testing.assert_allclose(
            np.asarray(block.linear_part(jnp.asarray(log_vis))),
            log_vis @ full.T,
            rtol=1e-12,
            atol=1e-12 * np.abs(log_vis @ full.T).max(),
        )
        # select_kinds keeps the parts consistent with the rows it keeps
        phases = obs.select_kinds(block, ["phase"])
        np.testing.assert_array_equal(phases.design, full[np.asarray(block.kinds) == 1])
