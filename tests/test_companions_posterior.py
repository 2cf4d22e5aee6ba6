"""NUTS's potential in float32: the same posterior density, at half the cost.

The float32 evaluation (``Dataset.single_precision``) is only worth having if every
large product really runs in float32 (one float64 constant in the scene promotes the rest
of the program back to float64), and only safe if its value and gradient agree with the
float64 potential far below what moves a sample.
"""

from __future__ import annotations

import dataclasses
import gc

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

from amigo.companions import observables as obs
from amigo.companions.posterior import _potential
from detect_helpers import sim_dataset

TRUTH = (-323.4, 59.9, 0.0188)


def _dataset(tmp_path) -> obs.Dataset:
    return sim_dataset(tmp_path, ("F380M", "F480M"), [TRUTH], np.random.default_rng(3))


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


def _best_fit(dataset: obs.Dataset):
    """The least-squares companion and the maximum-likelihood error scales at it (fitted
    again with them), as ``amigo detect`` hands them to NUTS."""
    from amigo.companions import fit as fitting

    start = np.log10(np.full((1, dataset.n_filters), TRUTH[2]))
    first = fitting.fit_companions(dataset, np.array([TRUTH[:2]]), start)
    scales = fitting.estimate_scales(dataset, first.offsets_mas, first.contrasts)
    best = fitting.fit_companions(dataset, first.offsets_mas, first.log10_contrasts, scales)
    return best, fitting.estimate_scales(dataset, best.offsets_mas, best.contrasts)


def test_the_first_mass_matrix_is_the_potentials_inverse_hessian(tmp_path):
    """NUTS starts from Laplace's covariance in its own coordinates: built from the
    least-squares covariance and ``s^2 / 2N`` for each error scale, carried through the
    sigmoids; checked against the inverse of the potential's Hessian by automatic
    differentiation, at the same point."""
    from jax.flatten_util import ravel_pytree

    from amigo.companions import posterior

    with jax.enable_x64(True):
        dataset = _dataset(tmp_path)
        best, scales = _best_fit(dataset)
        k, f = best.log10_contrasts.shape
        dra, ddec = best.offsets_mas[:, 0], best.offsets_mas[:, 1]
        bounds = {
            "dra": (dra - 75.0, dra + 75.0),
            "ddec": (ddec - 75.0, ddec + 75.0),
            "log10c": (best.log10_contrasts - 0.7, best.log10_contrasts + 1.3),
            "scale": (np.full(dataset.n_groups, 0.01), np.full(dataset.n_groups, 100.0)),
        }
        start = {"dra": dra, "ddec": ddec, "log10c": best.log10_contrasts, "scale": scales}
        laplace = posterior._laplace_inverse_mass(dataset, best, scales, start, bounds)
        assert laplace is not None
        z0 = {name: jnp.asarray(posterior._from_box(start[name], *bounds[name])) for name in start}
        flat, unravel = ravel_pytree(z0)
        hessian = jax.hessian(lambda v: posterior._potential(unravel(v), dataset, bounds, 0.0))(
            flat
        )
        assert laplace.shape == hessian.shape == (2 * k + k * f + dataset.n_groups,) * 2
        # Each coordinate's curvature: the sigmoids' prior terms (<= 0.5) and the
        # Gauss-Newton approximation (no second derivatives of the residuals) are all
        # the difference, against curvatures of 270 (scales) to 1.4e4 (measured: 0.8 %).
        np.testing.assert_allclose(
            np.diag(np.linalg.inv(laplace)), np.diag(np.asarray(hessian)), rtol=0.015
        )
        # The marginal widths also carry what Laplace's matrix leaves out: an error scale
        # is correlated with the companion where its group alone would move it (the
        # amplitudes' and the phases' chi2 pull the contrast apart at the joint optimum;
        # measured: 2.6 %). NUTS's mass matrix, not the posterior: a mismatch costs
        # leapfrogs, not accuracy (test_laplaces_mass_matrix_needs_only_a_short_warm_up).
        exact = np.linalg.inv(np.asarray(hessian))
        sd_laplace, sd_exact = np.sqrt(np.diag(laplace)), np.sqrt(np.diag(exact))
        np.testing.assert_allclose(sd_laplace, sd_exact, rtol=0.04)
        correlation = laplace / np.outer(sd_laplace, sd_laplace)
        np.testing.assert_allclose(correlation, exact / np.outer(sd_exact, sd_exact), atol=0.25)
        # and the position-contrast block's correlations, the ones that set NUTS's steps
        n_fit = 2 * k + k * f
        np.testing.assert_allclose(
            correlation[:n_fit, :n_fit],
            (exact / np.outer(sd_exact, sd_exact))[:n_fit, :n_fit],
            atol=0.03,
        )


def test_sampling_stops_once_the_errors_percentiles_are_sampled_enough(tmp_path):
    """With an effective-sample target the chains stop at the first check that meets it
    (every parameter's median and error percentiles, R-hat <= 1.01); without one they
    draw all they are asked."""
    from amigo.companions.posterior import R_HAT_STOP, sample_posterior

    with jax.enable_x64(True):
        dataset = _dataset(tmp_path)
        best, scales = _best_fit(dataset)
        settings = dict(num_warmup=100, num_chains=1, seed=1, num_samples=1000)
        stopped = sample_posterior(dataset, best, scales, ess_target=50, **settings)
        n = stopped.num_samples
        # A chunk of 250, then half chunks; one check met the target before 1000.
        assert n in (250, 375, 500, 625, 750, 875)
        assert stopped.samples["dra"].shape == (n, 1)
        assert min(stopped.ess_min, stopped.ess_percentiles_min) >= 50
        assert stopped.r_hat_max <= R_HAT_STOP
        full = sample_posterior(dataset, best, scales, ess_target=0, **settings)
        assert full.num_samples == 1000 and full.samples["dra"].shape == (1000, 1)
        # The same chain, continued: its first draws are the stopped run's.
        np.testing.assert_allclose(full.samples["dra"][:n], stopped.samples["dra"])


def test_laplaces_mass_matrix_needs_only_a_short_warm_up(tmp_path):
    """By default NUTS keeps Laplace's covariance as its mass matrix and its warm-up
    tunes the step size alone (WARMUP_LAPLACE steps); the chain then samples the same
    posterior, as efficiently per draw, as one whose dense mass matrix is adapted over
    WARMUP_ADAPTIVE steps."""
    from amigo.companions.posterior import WARMUP_ADAPTIVE, WARMUP_LAPLACE, sample_posterior

    with jax.enable_x64(True):
        dataset = _dataset(tmp_path)
        best, scales = _best_fit(dataset)
        settings = dict(num_chains=1, seed=2, num_samples=500, ess_target=0)
        kept = sample_posterior(dataset, best, scales, **settings)
        adapted = sample_posterior(dataset, best, scales, laplace_mass=False, **settings)
    assert (kept.num_warmup, kept.mass_matrix) == (WARMUP_LAPLACE, "laplace")
    assert (adapted.num_warmup, adapted.mass_matrix) == (WARMUP_ADAPTIVE, "adapted")
    assert WARMUP_LAPLACE < WARMUP_ADAPTIVE
    for name in ("dra", "ddec", "log10c"):
        a, b = kept.samples[name], adapted.samples[name]
        sd = np.std(b, axis=0)
        # medians within Monte Carlo noise (~0.06 sd each at these ESS), widths within 20 %
        # (measured over two seeds: medians within 0.09 sd, widths within 15 %)
        assert np.all(np.abs(np.median(a, axis=0) - np.median(b, axis=0)) < 0.25 * sd)
        np.testing.assert_allclose(np.std(a, axis=0), sd, rtol=0.2)
    # as many effective draws of the error percentiles (the binding ones), to a factor
    assert kept.ess_percentiles_min > 0.6 * adapted.ess_percentiles_min


@pytest.mark.parametrize("singles", [True, False], ids=["singles-in-threads", "batched"])
def test_fits_side_by_side_take_the_steps_each_takes_alone(tmp_path, monkeypatch, singles):
    """`fit_companions_many` (the search's candidate fits, evaluated one by one in threads
    while few are running, else batched) ends each fit where `fit_companions` ends it
    alone, from starts that converge in different numbers of steps (near the truth, at a
    noise peak, far off); no start gives no fit, and starts of different companion counts
    are refused."""
    from amigo.companions import fit as fitting

    monkeypatch.setattr(fitting, "_singles_up_to", lambda: 8 if singles else 1)
    with jax.enable_x64(True):
        dataset = _dataset(tmp_path)
        scales = np.array([1.3, 0.8, 1.1, 0.9])[: dataset.n_groups]
        f = dataset.n_filters
        starts = [
            (np.array([[TRUTH[0] + 3.0, TRUTH[1] - 2.0]]), np.full((1, f), -1.5)),
            (np.array([[150.0, -220.0]]), np.full((1, f), -3.0)),
            (np.array([[TRUTH[0] + 40.0, TRUTH[1] + 25.0]]), np.full((1, f), -2.5)),
        ]
        for tolerance in (0.0, 1e-3):
            together = fitting.fit_companions_many(
                dataset, starts, scales, chi2_tolerance=tolerance
            )
            alone = [
                fitting.fit_companions(dataset, o, c, scales, chi2_tolerance=tolerance)
                for o, c in starts
            ]
            for a, b in zip(together, alone, strict=True):
                assert a.converged == b.converged
                np.testing.assert_allclose(a.offsets_mas, b.offsets_mas, rtol=0, atol=1e-6)
                np.testing.assert_allclose(a.log10_contrasts, b.log10_contrasts, atol=1e-8)
                np.testing.assert_allclose(a.chi2, b.chi2, rtol=1e-10)
                np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-6, atol=1e-12)
        assert fitting.fit_companions_many(dataset, [], scales) == []
        with pytest.raises(ValueError, match="same number of companions"):
            fitting.fit_companions_many(
                dataset, [starts[0], (np.zeros((2, 2)), np.full((2, f), -2.0))], scales
            )


def test_the_padded_view_is_the_same_posterior(tmp_path):
    """Padded to bucket sizes (inert uv points and observables, padded rows in a group of
    scale 1), the potential's value and gradient are the dataset's own, in float64 and in
    the float32 NUTS evaluates."""
    with jax.enable_x64(True):
        dataset = _dataset(tmp_path)
        z, bounds = _point(dataset)
        for d in (dataset, dataset.single_precision()):
            view = obs.program_view(d)
            for block, padded, rows in zip(d.blocks, view.dataset.blocks, view.rows, strict=True):
                assert padded.n_uv == obs.uv_bucket(block.n_uv) > block.n_uv
                assert padded.n_obs > block.n_obs == rows.size
                assert padded.design_tail.dtype == block.design_tail.dtype

            def value_and_gradient(v, d=d):
                return (
                    jax.value_and_grad(lambda q: _potential(q, d, bounds, 0.0))(z)
                    if v is None
                    else (
                        jax.value_and_grad(
                            lambda q: _potential(q, v.dataset, bounds, 0.0, v.groups)
                        )(z)
                    )
                )

            v0, g0 = value_and_gradient(None)
            v1, g1 = value_and_gradient(view)
            assert abs(float(v1) - float(v0)) <= 1e-6 * abs(float(v0))
            for name in g0:
                np.testing.assert_allclose(g1[name], g0[name], rtol=1e-4, atol=1e-6)


def _fewer(block: obs.Observables, n_uv: int, n_rows: int) -> obs.Observables:
    """``block`` without its last ``n_uv`` uv points and its first ``n_rows`` amplitude
    observables (another target's silent knots and dropped DISCOs)."""
    uv = np.arange(block.n_uv - n_uv)
    rows = np.arange(n_rows, block.n_obs)
    head, tail = np.asarray(block.design_head), np.asarray(block.design_tail)
    return dataclasses.replace(
        block,
        uv_m=block.uv_m[uv],
        wavelengths_m=block.wavelengths_m[uv],
        weights=block.weights[uv],
        design_head=head[n_rows:][:, uv],
        design_tail=tail[:, np.concatenate([uv, block.n_uv + uv])],
        exp_rows=block.exp_rows[rows],
        wrap_rows=block.wrap_rows[rows],
        data_raw=block.data_raw[rows],
        errors=block.errors[rows],
        kinds=tuple(np.asarray(block.kinds)[rows].tolist()),
        source="another_calvis.fits",
        target="ANOTHER",
    )


def test_another_targets_files_share_the_nuts_program(tmp_path):
    """Two targets whose calvis files differ in their uv points, DISCO count and names
    but fall in the same buckets give the NUTS program the same key: the second target
    reads the first one's program from disk instead of compiling its own."""
    from amigo.companions import posterior

    with jax.enable_x64(True):
        first = _dataset(tmp_path).blocks[1]
        second = _fewer(first, 3, 2)
        assert obs.uv_bucket(first.n_uv) == obs.uv_bucket(second.n_uv)

        def key(block, padded=True):
            dataset = obs.Dataset.from_blocks([block]).single_precision()
            z, bounds = _point(dataset)
            if padded:
                view = obs.program_view(dataset)
                data = (view.dataset, view.groups)
            else:
                groups = (jnp.asarray(dataset.group_index(0)),)
                data = (dataset, groups)
            args = ((z, jax.random.PRNGKey(0)), *data, bounds, 0.0, None, 10, 20)
            leaves, treedef = jax.tree_util.tree_flatten((args, {}))
            return posterior._nuts_draws._key(treedef, leaves)

        assert key(first) == key(second)
        # and in memory too (equinox's and JAX's caches compare the static fields)
        views = [obs.program_view(obs.Dataset.from_blocks([b])) for b in (first, second)]
        structures = [jax.tree_util.tree_structure(v.dataset) for v in views]
        assert structures[0] == structures[1]
        # the files as read would not
        assert key(first, padded=False) != key(second, padded=False)


def test_a_datasets_view_is_made_once_and_stays_on_the_device(tmp_path):
    """Every candidate fit asks for the view of the same dataset: made once, and for a
    dataset on the device, on the device (each compiled call would otherwise copy it)."""
    with jax.enable_x64(True):
        dataset = jax.device_put(_dataset(tmp_path))
        view = obs.program_view(dataset)
        assert obs.program_view(dataset) is view
        assert all(isinstance(leaf, jax.Array) for leaf in jax.tree.leaves(view.dataset))
        assert all(isinstance(g, jax.Array) for g in view.groups)
        # another dataset object (the same blocks) gets its own view; a dead dataset's
        # view goes with it
        other = obs.Dataset.from_blocks(dataset.blocks)
        assert obs.program_view(other) is not view
        kept = len(obs._VIEWS)
        del other
        gc.collect()
        assert len(obs._VIEWS) == kept - 1
        assert all(v is not None for v in obs._VIEWS.values())


def test_a_section_without_observables_stays_empty(tmp_path):
    """A phase-only block (``amigo detect --observables phase``) has no amplitude rows:
    its view pads none either (32 zero rows would cost a product each call)."""
    with jax.enable_x64(True):
        phases = obs.select_kinds(_dataset(tmp_path).blocks[0], ["phase"])
        view = obs.program_view(obs.Dataset.from_blocks([phases]))
        padded = view.dataset.blocks[0]
        assert padded.design_head.shape == (0, obs.uv_bucket(phases.n_uv))
        assert padded.n_obs == -(-phases.n_obs // obs.ROW_MULTIPLE) * obs.ROW_MULTIPLE
        with pytest.raises(ValueError, match="kinds"):
            view.dataset.group_index(0)


HOST_CHILD = """
import sys, tempfile
import jax
import numpy as np
from amigo import programs
from amigo.companions import posterior
import test_companions_posterior as t

assert len(jax.devices()) == 2, jax.devices()
other = jax.devices()[1]
with jax.enable_x64(True):
    dataset = t._dataset(__import__("pathlib").Path(tempfile.mkdtemp()))
    best, scales = t._best_fit(dataset)
    settings = dict(num_chains=2, seed=4, num_samples=250, ess_target=0)
    here = posterior.sample_posterior(dataset, best, scales, **settings)
    placed = []
    put = programs.on_device
    def spy(tree, device):
        moved = put(tree, device)
        placed.extend({d for leaf in jax.tree.leaves(moved) if isinstance(leaf, jax.Array)
                       for d in leaf.devices()})
        return moved
    programs.on_device = spy
    posterior.programs.latency_device = lambda: other  # a host device beside the default
    there = posterior.sample_posterior(dataset, best, scales, **settings)
assert placed and set(placed) == {other}, placed
for name in here.samples:
    np.testing.assert_array_equal(here.samples[name], there.samples[name])
print("the chains on the other device drew the same samples")
"""


def test_the_chains_run_on_the_latency_device_with_the_same_draws():
    """Where NUTS's chains are sent to another device (``programs.latency_device``: the
    host beside an accelerator), their inputs are committed to it, their programs made for
    it, and, the device being a CPU as here, the draws are the same bits. Two CPU devices
    stand in for host and accelerator (``--xla_force_host_platform_device_count=2`` in a
    child process, since JAX reads the flag when it starts)."""
    import subprocess
    import sys

    from conftest import two_device_env

    env = two_device_env()
    done = subprocess.run(
        [sys.executable, "-c", HOST_CHILD], capture_output=True, text=True, env=env, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "the same samples" in done.stdout


def test_the_sampler_device_setting_is_checked(monkeypatch):
    """``AMIGO_SAMPLER_DEVICE`` is ``host`` or ``default``; on a CPU backend either way
    the chains run where everything runs (no other device)."""
    from amigo import programs

    for choice in ("host", "default", ""):
        monkeypatch.setenv("AMIGO_SAMPLER_DEVICE", choice)
        assert programs.latency_device() is None
    monkeypatch.setenv("AMIGO_SAMPLER_DEVICE", "gpu")
    with pytest.raises(ValueError, match="expected 'default' or 'host'"):
        programs.latency_device()
