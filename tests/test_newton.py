"""The Levenberg-Marquardt pieces of amigo.fitting.newton against direct linear algebra."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from amigo.fitting.newton import Layout
from amigo.fitting.params import FitParams
from amigo.model.image import ExposureParams, OpticsParams, SourceParams
from amigo.solvers.levenberg_marquardt import FisherSolve, marginal_errors


def _params(rng, n_exposures=3, n_targets=2, n_amp=4, n_phase=5):
    return FitParams(
        exposures=ExposureParams(
            jnp.asarray(rng.normal(size=(n_exposures, 2)), jnp.float32),
            jnp.asarray(rng.normal(size=n_exposures), jnp.float32),
            jnp.asarray(20 + rng.normal(size=n_exposures), jnp.float32),
        ),
        sources=SourceParams(
            jnp.asarray(rng.normal(size=(n_targets, n_amp)), jnp.float32),
            jnp.asarray(rng.normal(size=(n_targets, n_phase)), jnp.float32),
            jnp.asarray(rng.normal(size=n_targets), jnp.float32),
        ),
        optics=OpticsParams(
            jnp.asarray(rng.normal(size=(7, 10)), jnp.float32),
            jnp.asarray(1.5, jnp.float32),
            jnp.asarray([-0.44, 1.006, -0.26, 1.0], jnp.float32),
            jnp.asarray(3.0, jnp.float32),
        ),
    )


def test_layout_round_trip_and_local_indices():
    rng = np.random.default_rng(0)
    params = _params(rng)
    layout = Layout.of(params)
    vector = layout.pack(params)
    assert vector.shape == (layout.size,) == (3 * 4 + 2 + 76 + 2 * 9,)
    back = layout.pack(layout.unpack(params, vector + 1.0))
    np.testing.assert_allclose(back, vector + 1.0, rtol=1e-6)
    # Exposure 2 of target 1: its position, flux, its target's slope, its jitter, latents.
    local = layout.local(2, 1)
    p = layout.unpack(params, vector)
    np.testing.assert_allclose(vector[local[:2]], np.asarray(p.exposures.position_arcsec[2]))
    assert vector[local[2]] == pytest.approx(float(p.exposures.log_flux[2]))
    assert vector[local[3]] == pytest.approx(float(p.sources.slope_per_um[1]))
    assert vector[local[4]] == pytest.approx(float(p.exposures.jitter_mas[2]))
    latent = np.concatenate([p.sources.amp[1], p.sources.phase[1]])
    np.testing.assert_allclose(vector[local[5:]], latent)
    np.testing.assert_allclose(vector[layout.wavefront[:-1]], np.ravel(p.optics.zernikes_nm))
    np.testing.assert_allclose(vector[layout.geometry], np.asarray(p.optics.geometry))
    assert vector[layout.band[0]] == pytest.approx(3.0)


def test_undamped_step_is_the_newton_step_and_degeneracies_get_none():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(30, 6)) * np.array([1e3, 1, 1e-2, 5, 1, 1])  # mixed units
    fisher, grad = a.T @ a, rng.normal(size=6)
    np.testing.assert_allclose(
        FisherSolve(fisher)(grad, 0.0), np.linalg.solve(fisher, grad), rtol=1e-8
    )
    # Two exactly degenerate parameters (one column duplicated): no step along the
    # degenerate direction, and the step solves the system on the rest.
    b = np.column_stack([a, a[:, 1]])
    fisher = b.T @ b
    grad = b.T @ rng.normal(size=30)
    d = FisherSolve(fisher)(grad, 0.0)
    np.testing.assert_allclose(fisher @ d, grad, rtol=1e-6, atol=1e-8 * np.abs(grad).max())
    assert d[1] * np.sqrt(fisher[1, 1]) == pytest.approx(d[6] * np.sqrt(fisher[6, 6]), rel=1e-6)
    # Damping shortens the step.
    assert np.linalg.norm(FisherSolve(fisher)(grad, 10.0)) < np.linalg.norm(d)


def test_marginal_errors_of_blocks_are_those_of_the_whole_matrix(monkeypatch):
    rng = np.random.default_rng(2)

    def block(n, scale):
        a = rng.normal(size=(3 * n, n)) * scale
        return a.T @ a

    # Two groups that never meet, a parameter without information, and a degeneracy
    # (a duplicated column) in the first block: the blocks are decomposed apart, under
    # the whole matrix's floor.
    a = rng.normal(size=(40, 8)) * np.array([1e3, 1, 1e-2, 5, 1, 1, 1, 1])
    a = np.column_stack([a, a[:, 3]])
    first, second = a.T @ a, block(6, 1e-3)
    fisher = np.zeros((16, 16))
    fisher[:9, :9], fisher[10:, 10:] = first, second
    solver = FisherSolve(fisher)
    expected = []
    for i in range(16):
        unit = np.zeros(16)
        unit[i] = 1.0
        variance = solver(unit)[i]
        expected.append(np.sqrt(variance) if variance > 0 else np.nan)
    errors = marginal_errors(fisher, np.arange(16))
    np.testing.assert_allclose(errors, expected, rtol=1e-9)
    assert np.isnan(errors[9]) and np.isfinite(errors[:9]).all() and np.isfinite(errors[10:]).all()
    # Without the duplicate the first block is regular: its errors are sqrt(diag(F^-1)).
    regular = np.zeros((14, 14))
    regular[:8, :8], regular[8:, 8:] = first[:8, :8], second
    np.testing.assert_allclose(
        marginal_errors(regular, np.arange(14)), np.sqrt(np.diag(np.linalg.inv(regular))), rtol=1e-8
    )
    assert np.isnan(marginal_errors(None, np.arange(3))).all()
    # The solver's own decompositions of the two parts (a fit's two stages) give the
    # same errors without decomposing again, the parameter without information NaN.
    parts = []
    for rows in (slice(0, 9), slice(10, 16)):
        part = np.zeros_like(fisher)
        part[rows, rows] = fisher[rows, rows]
        parts.append(FisherSolve(part))
    with monkeypatch.context() as patch:  # read, not decomposed again
        patch.setattr(np.linalg, "eigh", None)
        from_solves = marginal_errors(fisher, np.arange(16), tuple(parts))
    np.testing.assert_allclose(from_solves, expected, rtol=1e-9)
    assert np.isnan(from_solves[9])
    with pytest.raises(ValueError, match="another Fisher matrix"):
        marginal_errors(2.0 * fisher, np.arange(16), tuple(parts))


def _small_fit(rng: np.random.Generator, w0: np.ndarray):
    """A FilterFit of one noisy nominal image as a calibrator and a science exposure,
    with wavefront ``w0`` (7, 10) nm. The small configuration the fitting tests share (3
    wavelengths, 27 x 27 knots at 0.5 m, F480M): the same compiled programs, which the
    suite's persistent compilation cache then serves to whichever test runs later."""
    import equinox as eqx

    from amigo.fitting.filter_fit import FilterFit, FitExposure
    from amigo.likelihood.pixels import ImageData
    from amigo.model.basis import load_basis
    from amigo.model.image import FilterSetup, Instrument
    from amigo.model.visibility import UVGrid

    instrument = Instrument.nominal(n_wavelengths=3)
    instrument = eqx.tree_at(
        lambda i: i.optics.zernikes_nm, instrument, jnp.asarray(w0, jnp.float32)
    )
    basis, _ = load_basis(instrument, "F480M", UVGrid(27, 0.5))
    setup = FilterSetup.create("F480M", instrument, basis)
    image = np.asarray(instrument.detector(instrument.optics.illuminance(
        setup.spectrum(jnp.zeros(())), jnp.zeros(2)), 1e6))  # fmt: skip
    sigma = np.sqrt(image + 100.0)
    data = ImageData(
        image + sigma * rng.normal(size=image.shape), sigma, np.ones(image.shape, bool)
    )
    return FilterFit(instrument, setup, [FitExposure("c", "calibrator", "C", data),
                                         FitExposure("s", "science", "S", data)])  # fmt: skip


@pytest.mark.slow
def test_the_solver_sees_the_stripes_covariance():
    """With 1/f stripes set (a Gaussian process along each column, amigo.likelihood.stripes),
    the solver's loss is the fit's chi2 with them (not without), its gradient is minus a
    central difference of that loss, and the normal equations' gradient is the same: the
    whitened residuals whitened once more are C^-1 r only for a symmetric whitener."""
    from amigo.fitting.newton import N_LOCAL_SCALARS, _Problem

    rng = np.random.default_rng(5)
    fit = _small_fit(rng, rng.normal(0, 10.0, (7, 10)))
    params = fit.initial_params()
    layout = Layout.of(params)
    vector = layout.pack(params)
    plain = np.asarray(fit.chi2(params), float)
    fit.stripe_sigma[:] = [3.0, 5.0]  # DN/s, over pixel errors of 10-1000 DN/s
    fit.stripe_length[:] = [10.0, np.inf]  # the process; one offset per column
    chi2 = np.asarray(fit.chi2(params), float)
    assert np.all(np.abs(chi2 - plain) > 1e-3 * plain)  # the stripes enter
    vector[layout.wavefront] += rng.normal(0, 3.0, layout.wavefront.size)
    for e in (0, 1):
        problem = _Problem(fit, params, np.array([e]))
        problem.float64 = True
        assert problem.loss(layout.pack(params)) == pytest.approx(0.5 * chi2[e], rel=1e-4)
        gradient = problem.gradient(vector)
        # The calibrator along the wavefront, the science exposure along its latent
        # visibilities (a science stage does not move the instrument).
        direction = np.zeros(layout.size)
        along = layout.wavefront if e == 0 else problem.locals[e][N_LOCAL_SCALARS:]
        direction[along] = rng.normal(size=np.size(along))
        h = 1e-3  # the latents' third derivatives show at 1e-2 (0.7 % of a larger slope)
        slope = (problem.loss(vector + h * direction) - problem.loss(vector - h * direction)) / (
            2 * h
        )
        assert -slope == pytest.approx(float(gradient @ direction), rel=2e-2)
        _, normal = problem.normal_equations(vector, "test")
        scale = np.abs(gradient).max()
        np.testing.assert_allclose(normal, gradient, rtol=1e-4, atol=1e-6 * scale)
        if e == 1:  # a science stage's gradient leaves the instrument block alone
            assert not np.any(gradient[layout.optics])
        # The other exposure's image is not computed: its residuals are zero.
        assert not np.any(problem._residuals_at(vector)[1 - e])
    # One reverse pass serves a stage only if its exposures are of one kind.
    with pytest.raises(ValueError, match="calibrators only or science only"):
        _Problem(fit, params, np.array([0, 1])).gradient(vector)


@pytest.mark.slow
def test_wavefront_prior_adds_exactly_its_gaussian_term():
    """The prior of ``NewtonConfig.wavefront_prior_nm`` adds ``|w - w0|^2 / (2 s^2)`` to
    the calibrators' loss (``w0``: the instrument's own wavefront), ``-(w - w0) / s^2`` to
    their gradient (checked against a finite difference of the loss) and ``1 / s^2`` to
    the diagonal of the wavefront's Fisher block, and nothing to a science-only stage."""
    from amigo.fitting.newton import _Problem

    rng = np.random.default_rng(3)
    w0 = rng.normal(0, 10.0, (7, 10))
    fit = _small_fit(rng, w0)
    params = fit.initial_params()
    layout = Layout.of(params)
    vector = layout.pack(params)
    # The fit's model images (FilterFit.models: all exposures in one compiled program)
    # against the engine's own per-exposure model, for the calibrator and the science
    # exposure (no prior is active at the starting point).
    chi2 = np.asarray(fit.chi2(params), float)
    for e in (0, 1):
        alone = _Problem(fit, params, np.array([e]))
        alone.float64 = True
        assert alone.loss(vector) == pytest.approx(0.5 * chi2[e], rel=1e-4)
    vector[layout.wavefront] += rng.normal(0, 3.0, layout.wavefront.size)  # away from w0
    vector[layout.geometry] += [0.05, 2e-3, -0.05, 1e-3]  # and from the SIAF geometry
    offset = vector[layout.wavefront] - np.append(w0.ravel(), 0.0)
    s = 2.0
    free, tied = _Problem(fit, params, np.array([0])), _Problem(fit, params, np.array([0]), s)
    free.float64 = tied.float64 = True  # so that the data terms cancel to rounding
    assert tied.loss(vector) - free.loss(vector) == pytest.approx(
        0.5 * np.sum(offset**2) / s**2, rel=1e-6
    )
    g_free, g_tied = free.gradient(vector), tied.gradient(vector)
    expected = np.zeros(layout.size)
    expected[layout.wavefront] = -offset / s**2
    rounding = 1e-8 * np.abs(g_free).max()  # of the data term, which cancels
    np.testing.assert_allclose(g_tied - g_free, expected, rtol=1e-5, atol=rounding)
    # g = -dL/dv: a central difference of the loss along a wavefront direction, and along
    # the detector geometry (data term and its always-on prior).
    direction = np.zeros(layout.size)
    direction[layout.wavefront] = rng.normal(size=layout.wavefront.size)
    h = 1e-2
    slope = (tied.loss(vector + h * direction) - tied.loss(vector - h * direction)) / (2 * h)
    assert -slope == pytest.approx(float(g_tied @ direction), rel=2e-2)
    direction = np.zeros(layout.size)
    direction[layout.geometry] = [0.01, 1e-4, 0.01, 1e-4]
    direction[layout.band] = 0.5
    h = 0.5
    slope = (tied.loss(vector + h * direction) - tied.loss(vector - h * direction)) / (2 * h)
    assert -slope == pytest.approx(float(g_tied @ direction), rel=2e-2)
    f_free, n_free = free.normal_equations(vector, "test")
    f_tied, n_tied = tied.normal_equations(vector, "test")
    added = np.zeros((layout.size, layout.size))
    added[layout.wavefront, layout.wavefront] = 1 / s**2
    np.testing.assert_allclose(f_tied - f_free, added, atol=1e-6 * np.abs(f_free).max())
    np.testing.assert_allclose(n_tied - n_free, expected, rtol=1e-5, atol=rounding)
    science = _Problem(fit, params, np.array([1]), s)
    assert not np.any(science.prior_precision)
    assert science.loss(vector) == pytest.approx(_Problem(fit, params, np.array([1])).loss(vector))


class _Curve:
    """``y = a exp(-b x) + c`` fitted to noisy samples: a small nonlinear least-squares
    :class:`~amigo.solvers.levenberg_marquardt.Problem` that counts its Jacobians."""

    def __init__(self) -> None:
        rng = np.random.default_rng(4)
        self.x = np.linspace(0.0, 4.0, 40)
        self.y = 2.0 * np.exp(-1.3 * self.x) + 0.5 + 0.01 * rng.normal(size=self.x.size)
        self.n_values, self.n_groups, self.float64 = float(self.x.size), 1, False
        self.jacobians: list[bool] = []  # the precision of each

    def residuals(self, v):
        return (self.y - (v[0] * np.exp(-v[1] * self.x) + v[2])) / 0.01

    def jacobian(self, v):
        e = np.exp(-v[1] * self.x)
        return -np.column_stack([e, -v[0] * self.x * e, np.ones_like(e)]) / 0.01

    def loss(self, v):
        return 0.5 * float(np.sum(self.residuals(v) ** 2))

    def gradient(self, v):
        return -self.jacobian(v).T @ self.residuals(v)

    def refresh(self, v):
        return False  # no noise model to measure

    def normal_equations(self, v, label):
        self.jacobians.append(self.float64)
        j = self.jacobian(v)
        return j.T @ j, -j.T @ self.residuals(v)


class _Settings:
    max_iterations, tolerance, damping, chord_steps, float64_check = 12, 1e-6, 1e-3, 20, True


class _Measured(_Curve):
    """A :class:`_Curve` with a noise model measured by ``refresh``: the first
    measurement scales the errors by 1.1 (a new likelihood) when ``changes``; it records
    how many Jacobians had been taken at each measurement."""

    def __init__(self, changes: bool) -> None:
        super().__init__()
        self.changes, self.scale, self.measured_after = changes, 1.0, []

    def residuals(self, v):
        return super().residuals(v) / self.scale

    def jacobian(self, v):
        return super().jacobian(v) / self.scale

    def refresh(self, v):
        self.measured_after.append(len(self.jacobians))
        if self.changes and self.scale == 1.0:
            self.scale = 1.1
            return True
        return False


def test_the_noise_model_is_measured_after_the_cold_start():
    """Not before the first Jacobians (the start's residuals are the model's errors);
    before the confirmation where the first Jacobians' chord steps converge (then new
    Jacobians where it changed the likelihood, none where it did not), and before the
    second Jacobians from farther away; the optimum is the plain fit's."""
    from amigo.solvers.levenberg_marquardt import minimise

    reference = minimise(_Curve(), np.array([1.0, 1.0, 0.0]), _Settings(), "reference")
    assert reference.fisher is not None
    direction = np.array([1.0, -2.0, 0.5])
    near = reference.vector + direction * np.sqrt(
        2.5e-6 / (direction @ reference.fisher @ direction)
    )
    quiet = _Measured(changes=False)
    found = minimise(quiet, near, _Settings(), "quiet")
    assert found.converged and quiet.jacobians == [False] and quiet.measured_after == [1]
    noisy = _Measured(changes=True)
    found = minimise(noisy, near, _Settings(), "noisy")
    assert found.converged and noisy.jacobians == [False, True]
    assert noisy.measured_after == [1]  # not again at the same point
    far = _Measured(changes=True)
    found = minimise(far, np.array([1.0, 1.0, 0.0]), _Settings(), "far")
    assert found.converged and far.measured_after[0] == 1 and len(far.jacobians) >= 2
    np.testing.assert_allclose(found.vector, reference.vector, rtol=1e-6)

    # A fit that stops first (one iteration) measures it before it returns, and a matrix
    # of the likelihood before the measurement is not returned as the solution's.
    class _OneIteration(_Settings):
        max_iterations = 1

    short = _Measured(changes=True)
    stopped = minimise(short, np.array([1.0, 1.0, 0.0]), _OneIteration(), "short")
    assert short.measured_after == [1] and not stopped.converged and stopped.solve is None

    # Without the float64 check, a cold start can converge at its first Jacobians: not
    # before the noise model is measured (then new Jacobians for the new likelihood).
    class _Float32(_Settings):
        float64_check = False

    plain = _Measured(changes=True)
    done = minimise(plain, reference.vector, _Float32(), "float32")
    assert done.converged and plain.measured_after == [1] and len(plain.jacobians) == 2


def test_a_given_fisher_matrix_saves_jacobians_and_changes_no_optimum():
    """From the exact matrix at the optimum: converged with no new Jacobians. From an
    approximate one (another point): chord steps, then new Jacobians confirm, and the
    optimum is the one found without it."""
    from amigo.solvers.levenberg_marquardt import minimise

    start = np.array([1.0, 1.0, 0.0])
    plain = _Curve()
    reference = minimise(plain, start, _Settings(), "plain")
    assert reference.converged and reference.fisher is not None

    exact = _Curve()
    again = minimise(exact, reference.vector, _Settings(), "exact", reference.fisher)
    assert again.converged and exact.jacobians == []
    np.testing.assert_array_equal(again.fisher, reference.fisher)
    # With the matrix comes the solver's decomposition of it (marginal errors read it).
    assert reference.solve is not None
    grad = np.array([0.3, -1.0, 2.0])
    np.testing.assert_allclose(reference.solve(grad), FisherSolve(reference.fisher)(grad))

    stale = _Curve()
    near = reference.vector * np.array([1.05, 0.95, 1.1])
    approximate = stale.normal_equations(near, "")[0]
    stale.jacobians.clear()
    found = minimise(stale, start, _Settings(), "approximate", approximate, exact=False)
    assert found.converged and found.fisher is not None
    assert stale.jacobians and stale.jacobians[-1]  # confirmed by float64 normal equations
    np.testing.assert_allclose(found.vector, reference.vector, rtol=1e-5)


def test_a_float64_gradient_confirms_convergence_with_the_last_matrix(monkeypatch):
    """Chord steps that end near their Jacobians (``dx^T F dx`` about 2.3 tolerances over
    three parameters, within STALE_FISHER_REACH of one tolerance per parameter): the
    float64 gradient weighed by the last matrix confirms convergence, with no float64
    Jacobians; the optimum is the one float64 normal equations confirm (a reach of 0 asks
    for them, and so does a start beyond the reach)."""
    from amigo.solvers import levenberg_marquardt as lm

    reference = lm.minimise(_Curve(), np.array([1.0, 1.0, 0.0]), _Settings(), "reference")
    assert reference.fisher is not None
    direction = np.array([1.0, -2.0, 0.5])
    # _Settings' tolerance is 1e-6 (times chi2 / n = 1.1 here).
    start = reference.vector + direction * np.sqrt(
        2.5e-6 / (direction @ reference.fisher @ direction)
    )
    quick = _Curve()
    found = lm.minimise(quick, start, _Settings(), "quick")
    assert found.converged and found.fisher is not None and quick.float64
    assert quick.jacobians == [False]  # one float32 evaluation, at the start
    monkeypatch.setattr(lm, "STALE_FISHER_REACH", 0.0)
    strict = _Curve()
    confirmed = lm.minimise(strict, start, _Settings(), "strict")
    assert confirmed.converged and confirmed.fisher is not None and strict.jacobians[-1]
    np.testing.assert_allclose(found.vector, confirmed.vector, rtol=1e-7)
    np.testing.assert_allclose(found.vector, reference.vector, rtol=1e-7)
    monkeypatch.setattr(lm, "STALE_FISHER_REACH", 1.0)
    # Twice as far: 9 tolerances over three parameters, beyond the reach.
    far = _Curve()
    beyond = lm.minimise(
        far, reference.vector + 2.0 * (start - reference.vector), _Settings(), "far"
    )
    assert beyond.converged and far.jacobians[-1] and len(far.jacobians) == 2
    np.testing.assert_allclose(beyond.vector, reference.vector, rtol=1e-7)


def test_jacobian_batch_is_the_default_unless_the_environment_sets_it(monkeypatch):
    from amigo.model import columns

    monkeypatch.delenv(columns.JVP_BATCH_ENV, raising=False)
    assert columns.jvp_batch() == columns.JVP_BATCH
    monkeypatch.setenv(columns.JVP_BATCH_ENV, "48")
    assert columns.jvp_batch() == 48
    for bad in ("0", "-3", "many"):
        monkeypatch.setenv(columns.JVP_BATCH_ENV, bad)
        with pytest.raises(ValueError, match=columns.JVP_BATCH_ENV):
            columns.jvp_batch()


@pytest.mark.parametrize("batch", ["3", "64"])
def test_jacobian_columns_do_not_depend_on_the_batch(monkeypatch, batch):
    """A batch larger than a block, or one that does not divide it: the same columns as
    ``jax.jacfwd`` (the blocks' batches are shared evenly and padded with zero tangents)."""
    import jax

    from amigo.model import columns

    monkeypatch.setenv(columns.JVP_BATCH_ENV, batch)
    x = jnp.linspace(-1.0, 1.0, 11)
    weights = jnp.arange(33.0).reshape(3, 11) / 10.0

    def function(v):
        return jnp.sin(weights @ v) * jnp.sum(v**2)

    columns = columns.columns_of(function, x, (4,))
    np.testing.assert_allclose(columns, jax.jacfwd(function)(x).T, rtol=1e-5, atol=1e-6)


def test_hole_window_wavefront_columns_are_the_whole_models_derivatives():
    """The instrument block's Zernike columns through each hole's pupil window against
    forward-mode differentiation of the whole model in float64, along a random wavefront
    direction and along unequal pistons (agreement measured: 3e-7 to 7e-7 of the
    largest pixel; float32 columns)."""
    import equinox as eqx
    import jax

    from amigo.fitting import newton
    from amigo.model.basis import load_basis
    from amigo.model.image import FilterSetup, Instrument, filter_psfs, float64
    from amigo.model.visibility import UVGrid

    rng = np.random.default_rng(11)
    instrument = Instrument.nominal(n_wavelengths=3)  # the fitting tests' configuration
    instrument = eqx.tree_at(
        lambda i: i.optics.zernikes_nm,
        instrument,
        jnp.asarray(rng.normal(0, 20.0, (7, 10)), jnp.float32),
    )
    basis, _ = load_basis(instrument, "F480M", UVGrid(27, 0.5))
    setup = FilterSetup.create("F480M", instrument, basis)
    windows = newton._windows(instrument)
    assert windows is not None and windows.size < 0.3 * min(instrument.optics.grid.shape)
    block = jnp.asarray(
        np.concatenate([rng.normal(0, 20.0, 70), [15.0], [-0.44, 1.006, -0.26, 1.0], [2.0]]),
        jnp.float32,
    )
    n = basis.n_amp + basis.n_phase
    theta = jnp.asarray(
        np.concatenate([[0.3, -0.2, np.log(1e6), 0.1, 20.0], rng.normal(0, 0.05, n)]),
        jnp.float32,
    )
    anchor = jnp.asarray([0.01, -0.02], jnp.float32)
    columns = np.asarray(newton.optics_jacobian(block, theta, instrument, setup, anchor))
    directions = np.zeros((2, block.size))
    directions[0, :70] = rng.normal(size=70)
    directions[1, 0:70:10] = np.arange(1.0, 8.0)  # unequal pistons: the fringes move
    shape = (7, 10)

    def image_of(vector, theta, instrument, setup, anchor):
        optics = newton._split_block(vector, shape)
        psfs = filter_psfs(instrument, setup, optics, anchor)
        return newton._local_image(theta, *newton._at(instrument, setup, optics), psfs, anchor)

    with jax.enable_x64(True):
        args = float64((block, theta, instrument, setup, anchor))

        @jax.jit
        def derivatives(args, directions):
            def along(d):
                return jax.jvp(lambda v: image_of(v, *args[1:]), (args[0],), (d,))[1]

            return jax.vmap(along)(directions)

        expected = np.asarray(derivatives(args, jnp.asarray(directions)))
    got = np.tensordot(directions, columns.astype(np.float64), 1)
    for g, e in zip(got, expected, strict=True):
        assert np.max(np.abs(g - e)) < 2e-5 * np.max(np.abs(e))


@pytest.mark.slow
def test_signature_amplitudes_see_what_the_parameters_absorbed():
    """``signature_amplitudes`` measures a detector-like term ``B`` (here a response
    non-linear in the pixel's signal, 6 % at the peak) at ~1 in data that have it and at
    ~0 in data that do not, although the fitted parameters (flux, visibilities,
    wavefront) absorb much of it: projected at fixed parameters, the "absent" case reads
    ~0.5. This is the check by which ``amigo fit`` leaves out the base model's detector
    on level-2 images that do not show it (``RampDetector.check_detector``)."""
    import dataclasses

    from amigo.fitting.filter_fit import FitConfig
    from amigo.fitting.newton import NewtonConfig, _Problem, signature_amplitudes

    rng = np.random.default_rng(11)
    fit = _small_fit(rng, rng.normal(0, 10.0, (7, 10)))
    y = fit.exposures[0].image.data
    # Of a noiseless image (a detector model's correction does not know the noise; one
    # made from the data would correlate with it).
    image = np.asarray(fit.models(fit.initial_params())[0], np.float64)
    signature = 0.06 * image**2 / image.max()

    def on(data):
        return fit.with_exposures(
            [
                dataclasses.replace(e, image=dataclasses.replace(e.image, data=data))
                for e in fit.exposures
            ]
        )

    config = FitConfig(newton=NewtonConfig(max_iterations=12))
    for truth, observed in ((0.0, y), (1.0, y + signature)):
        # The model's detector adds B: the fit sees the data less B; without it, as read.
        with_it, without = on(observed - signature), on(observed)
        params = with_it.fit(config).params
        amplitudes = signature_amplitudes(with_it, without, params, "test")
        for a, sigma in amplitudes:
            assert 0 < sigma < 0.15
            assert abs(a - truth) < 3 * sigma + 0.05, (truth, amplitudes)
        if truth == 0.0:
            # What a projection at the fitted parameters would say: far from 0.
            layout = Layout.of(params)
            vector = layout.pack(params)
            r1 = _Problem(with_it, params, np.array([0]))._residuals_at(vector)[0]
            r0 = _Problem(without, params, np.array([0]))._residuals_at(vector)[0]
            b = r0 - r1
            assert 1.0 + float(b @ r1) / float(b @ b) > 0.3
    # The fit's priors are part of its likelihood: a wavefront held by a tight prior
    # absorbs less of B, so the same data measure it more precisely (strictly: the prior
    # adds to the Fisher matrix what the parameters could take of the signature).
    held = FitConfig(newton=NewtonConfig(max_iterations=12, wavefront_prior_nm=0.5))
    params = with_it.fit(held).params
    free = signature_amplitudes(with_it, without, params, "test")
    tight = signature_amplitudes(with_it, without, params, "test", held.newton)
    assert tight[0][1] < free[0][1]
    assert abs(tight[0][0] - 1.0) < 3 * tight[0][1] + 0.05


class _Flat32(_Curve):
    """A :class:`_Curve` whose float32 loss cannot fall (a constant): the solver's damped
    search fails there and it goes on in float64, where the loss is the curve's."""

    def loss(self, v):
        return super().loss(v) if self.float64 else 1e12


def test_a_failed_damped_search_leaves_the_damping_as_it_was():
    """After twelve rejected dampings (each 4 times the last) the solver goes on in
    float64; its first step there is taken with the damping it had before the search, a
    nearly Gauss-Newton step that takes most of the way to the optimum, not one damped
    4^12 times more that barely moves."""
    from amigo.solvers.levenberg_marquardt import minimise

    problem = _Flat32()
    found = minimise(problem, np.array([1.0, 1.0, 0.0]), _Settings(), "flat32")
    assert found.converged and problem.float64
    start = found.history.index(1e12) + 1  # the loss re-evaluated in float64
    first_fall = found.history[start] - found.history[start + 1]
    assert first_fall > 0.5 * (found.history[start] - found.history[-1])


def test_a_target_in_both_roles_is_refused():
    """One target with a calibrator and a science exposure would share its latent
    visibilities between the solver's two stages and leave no calibrator to calibrate
    against: refused by name (the pipeline keys such targets apart by role and visit)."""
    from amigo.fitting.filter_fit import FilterFit

    fit = _small_fit(np.random.default_rng(0), np.zeros((7, 10)))
    same = [dataclasses.replace(e, target="STAR") for e in fit.exposures]
    with pytest.raises(ValueError, match="STAR"):
        FilterFit(fit.instrument, fit.setup, same)
