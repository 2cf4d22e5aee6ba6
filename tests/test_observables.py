"""Kernel projection, calibration and decorrelation (pure linear algebra, float64)."""

from __future__ import annotations

import numpy as np

from amigo.observables import kernel as obs


def _orthonormal(rng, n, m):
    q, _ = np.linalg.qr(rng.normal(size=(n, m)))
    return q


def _spd(rng, n, scale=1.0):
    a = rng.normal(size=(n, n))
    return scale * (a @ a.T / n + 0.5 * np.eye(n))


def test_kernel_projector_nulls_the_jacobian():
    rng = np.random.default_rng(1)
    jac = rng.normal(size=(40, 6)) @ rng.normal(size=(6, 9))  # rank 6 with 9 columns
    k = obs.kernel_projector(jac)
    assert k.shape == (34, 40)
    np.testing.assert_allclose(k @ k.T, np.eye(34), atol=1e-12)
    np.testing.assert_allclose(k @ jac, 0.0, atol=1e-10 * np.abs(jac).max())


def test_decorrelation_gives_independent_amplitudes_and_phases():
    rng = np.random.default_rng(2)
    cov = _spd(rng, 12)
    t, var = obs.decorrelation(cov, n_amp=5)
    out = t @ cov @ t.T
    np.testing.assert_allclose(out, np.diag(var), atol=1e-10)
    # Amplitude observables use amplitudes only.
    np.testing.assert_array_equal(t[:5, 5:], 0.0)


def test_discos_are_calibrated_and_chi2_distributed():
    """Simulate latent estimates = B^T v + G theta + noise for science and calibrator with
    different nuisance errors; the DISCO chi2 against D v must follow chi2(n)."""
    rng = np.random.default_rng(3)
    n_knots, m_a, m_p, n_nuis = 60, 20, 18, 5
    basis_a = _orthonormal(rng, n_knots, m_a)
    basis_p = _orthonormal(rng, n_knots, m_p)
    to_knots = np.zeros((m_a + m_p, 2 * n_knots))
    to_knots[:m_a, :n_knots] = basis_a.T
    to_knots[m_a:, n_knots:] = basis_p.T
    g = rng.normal(size=(m_a + m_p, n_nuis))
    kernel = obs.build_kernel(g, m_a)
    assert kernel.amp.shape == (m_a - n_nuis, m_a)
    c_sci, c_cal = _spd(rng, m_a + m_p, 1e-4), _spd(rng, m_a + m_p, 1e-4)
    v = rng.normal(size=2 * n_knots) * 0.05  # the sky's knot log-visibilities
    chi2 = []
    for _ in range(300):
        x_sci = (
            to_knots @ v
            + g @ rng.normal(size=n_nuis)
            + rng.multivariate_normal(np.zeros(m_a + m_p), c_sci)
        )
        x_cal = g @ rng.normal(size=n_nuis) + rng.multivariate_normal(np.zeros(m_a + m_p), c_cal)
        d = obs.discos(x_sci, c_sci, x_cal, c_cal, kernel, to_knots)
        chi2.append(d.chi2(v))
    n = len(d.values)
    assert n == (m_a - n_nuis) + (m_p - n_nuis)
    mean = np.mean(chi2)
    assert abs(mean - n) < 4 * np.sqrt(2 * n / len(chi2))
    # Without calibration the nuisance terms would dominate: the point model is rejected.
    assert np.mean([d.chi2(np.zeros_like(v))]) > 3 * n


def test_combine_is_inverse_variance_weighted():
    a, b = np.array([1.0, 2.0]), np.array([3.0, 2.0])
    ca, cb = np.diag([1.0, 4.0]), np.diag([1.0, 1.0])
    mean, cov = obs.combine([a, b], [ca, cb])
    np.testing.assert_allclose(mean, [2.0, 2.0])
    np.testing.assert_allclose(cov, np.diag([0.5, 0.8]))


def test_covariance_from_hessian_inverts():
    rng = np.random.default_rng(4)
    h = _spd(rng, 8)
    np.testing.assert_allclose(obs.covariance_from_hessian(h) @ h, np.eye(8), atol=1e-10)


def _hexagon(x, y, centre, width):
    """Flat-top hexagon (flats parallel to x) rasterised by its three edge normals."""
    inside = np.ones(x.shape, bool)
    for angle in np.radians([90.0, 30.0, 150.0]):
        normal = np.cos(angle) * (x - centre[0]) + np.sin(angle) * (y - centre[1])
        inside &= np.abs(normal) <= width / 2
    return inside.astype(float)


def test_envelope_knots_are_where_the_fringes_do_not_reach():
    """Against the mask's OTF computed independently: the autocorrelation of a rasterised
    pupil (2 cm pixels, FFT) less the seven holes' own autocorrelations is the fringes'
    part; at the envelope knots it is below 1 % of a splodge's peak, at every other knot
    within 1 m of the origin above 4 %."""
    from amigo import niriss as nis
    from amigo.model.visibility import UVGrid

    step, n = 0.02, 512
    axis = (np.arange(n) - n // 2) * step
    x, y = np.meshgrid(axis, axis)

    def autocorrelation(pupil):
        power = np.abs(np.fft.fft2(pupil, s=(2 * n, 2 * n))) ** 2
        return np.fft.fftshift(np.real(np.fft.ifft2(power)))

    width = nis.HOLE_FLAT_TO_FLAT_M
    mask = sum(_hexagon(x, y, c, width) for c in nis.HOLE_CENTRES_M)
    single = autocorrelation(_hexagon(x, y, (0.0, 0.0), width))
    fringes = (autocorrelation(mask) - nis.N_HOLES * single) / single.max()

    knots = UVGrid(51, 0.259).half_knots_m()
    envelope = obs.envelope_knots(knots, nis.baselines_m(), width)
    pixel = np.round(knots / step).astype(int) + n
    at_knots = fringes[pixel[:, 1], pixel[:, 0]]
    radius = np.hypot(*knots.T)
    assert envelope.sum() == 8 and radius[envelope].max() < 0.58
    assert np.abs(at_knots[envelope]).max() < 0.01
    near = (radius < 1.0) & ~envelope
    assert near.sum() >= 10 and at_knots[near].min() > 0.04


def test_knot_nuisance_makes_the_kernel_blind_to_those_knots():
    rng = np.random.default_rng(5)
    n_used, m = 40, 12
    amp = np.linalg.qr(rng.normal(size=(n_used, m)))[0]
    phase = np.linalg.qr(rng.normal(size=(n_used, m)))[0]
    to_latent = np.zeros((2 * m, 2 * n_used))
    to_latent[:m, :n_used], to_latent[m:, n_used:] = amp.T, phase.T
    chosen = np.zeros(n_used, bool)
    chosen[[0, 3, 7]] = True
    g = np.concatenate([rng.normal(size=(2 * m, 4)), obs.knot_nuisance(to_latent, chosen)], 1)
    kernel = obs.build_kernel(g, m)
    knots = np.flatnonzero(chosen)
    blind = kernel.matrix @ to_latent[:, np.concatenate([knots, n_used + knots])]
    assert np.abs(blind).max() < 1e-10
    assert kernel.amp.shape[0] == m - 4 - 3 and kernel.phase.shape[0] == m - 4 - 3


def test_discos_leave_out_directions_of_no_variance_and_fail_when_none_is_left():
    """A kernel covariance that is not positive definite (here: the science and the
    calibrator covariance cancel along chosen directions) gives no DISCO there, instead
    of a zero error that would weigh it infinitely; none left is a NumericalFailure."""
    import pytest

    from amigo.errors import NumericalFailure

    rng = np.random.default_rng(8)
    m_a, m_p = 6, 5
    m = m_a + m_p
    kernel = obs.build_kernel(np.zeros((m, 0)), m_a)  # no nuisance: the identity
    c_sci = _spd(rng, m)
    # the calibrator's covariance removes two amplitude directions and one phase one
    dead = np.zeros((m, 3))
    dead[[1, 4], [0, 1]] = 1.0
    dead[m_a + 2, 2] = 1.0
    c_cal = -dead @ dead.T @ c_sci @ dead @ dead.T
    # the rest stays positive: add it back off the dead directions
    keep = np.eye(m) - dead @ dead.T
    c_cal = c_cal + keep @ _spd(rng, m) @ keep
    to_knots = np.eye(m)
    d = obs.discos(np.zeros(m), c_sci, np.zeros(m), c_cal, kernel, to_knots)
    total = d.dropped + len(d.values)
    assert total == m and d.dropped >= 1
    assert np.all(d.errors > 0) and np.all(np.isfinite(d.errors))
    assert len(d.kinds) == len(d.values) == d.matrix.shape[0]
    with pytest.raises(NumericalFailure, match="no positive variance"):
        obs.discos(np.zeros(m), c_sci, np.zeros(m), -c_sci, kernel, to_knots)
    with pytest.raises(NumericalFailure, match="not finite"):
        obs.discos(np.full(m, np.nan), c_sci, np.zeros(m), c_cal, kernel, to_knots)


def test_numerical_errors_of_a_stage_become_its_failure_and_others_pass_through():
    """``amigo.errors.numerical(stage)``, around the fit, the latent Hessians, their
    covariances and the kernel (amigo.observables.extract): what NumPy raises for a
    matrix without a result becomes that stage's NumericalFailure (the filter's
    ``failed`` record); any other exception is a bug and is not hidden."""
    import pytest

    from amigo.errors import NumericalFailure, numerical

    for error in (np.linalg.LinAlgError("Singular matrix"), FloatingPointError("overflow")):
        with pytest.raises(NumericalFailure) as caught, numerical("latent Hessians"):
            raise error
        assert str(caught.value) == f"latent Hessians: {type(error).__name__}: {error}"
    with pytest.raises(NumericalFailure, match=r"^fit: LinAlgError"), numerical("fit"):
        np.linalg.inv(np.zeros((2, 2)))
    with pytest.raises(KeyError), numerical("fit"):
        raise KeyError("not numerical")


def test_disco_signs_follow_the_data_not_the_eigensolver(monkeypatch):
    """An eigenvector's sign is arbitrary: whatever signs the eigensolver returns, each
    DISCO row's largest entry is positive, so a rerun whose last bits differ (and whose
    solver flips a vector) writes the same values."""
    rng = np.random.default_rng(8)
    m_a, m_p, n_knots = 10, 9, 30
    to_knots = np.linalg.qr(rng.normal(size=(2 * n_knots, m_a + m_p)))[0].T
    kernel = obs.build_kernel(rng.normal(size=(m_a + m_p, 3)), m_a)
    x_sci, x_cal = rng.normal(size=m_a + m_p), rng.normal(size=m_a + m_p)
    c_sci, c_cal = _spd(rng, m_a + m_p, 1e-3), _spd(rng, m_a + m_p, 1e-3)
    first = obs.discos(x_sci, c_sci, x_cal, c_cal, kernel, to_knots)
    rows = first.matrix  # as DISCO_MATRIX stores it
    largest = rows[np.arange(len(rows)), np.argmax(np.abs(rows), axis=1)]
    assert np.all(largest > 0)

    eigh = np.linalg.eigh

    def flipped(matrix):
        values, vectors = eigh(matrix)
        return values, -vectors  # the other, equally valid, sign of every eigenvector

    monkeypatch.setattr(obs.np.linalg, "eigh", flipped)
    second = obs.discos(x_sci, c_sci, x_cal, c_cal, kernel, to_knots)
    np.testing.assert_allclose(second.values, first.values, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(second.latent_matrix, first.latent_matrix, atol=1e-14)
