"""The latent bases' pieces (amigo.model.basis) against independent calculations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amigo.model import basis as B
from amigo.model.image import (
    FilterSetup,
    Instrument,
    OpticsParams,
    filter_psfs,
    illuminance_from_psfs,
)
from amigo.model.visibility import UVGrid


@pytest.fixture(scope="module")
def small():
    """F480M through the nominal instrument (3 wavelengths) on the tests' 27 x 0.5 m grid."""
    instrument = Instrument.nominal(n_wavelengths=3)
    setup = FilterSetup.create("F480M", instrument, grid=UVGrid(27, 0.5))
    psfs = filter_psfs(instrument, setup, OpticsParams.from_instrument(instrument))
    return instrument, setup, psfs, B._touched_knots(setup, psfs)


def test_knot_jacobian_is_the_ffts_derivative(small):
    """The knot Jacobian through the fit's band products equals forward-mode
    differentiation of the plain path (the visibilities injected into every wavelength's
    PSF and inverse-transformed by FFTs, :func:`illuminance_from_psfs`, then the jitter's
    Fourier blur and the detector) for amplitude and phase knots across the grid, to
    float32 rounding."""
    instrument, setup, psfs, knots = small
    jac = np.asarray(B.knot_jacobian(instrument, setup, psfs, jnp.asarray(knots)))
    k, n_half = len(knots), setup.grid.n_half
    zero = jnp.zeros(n_half, jnp.float32)
    detector = instrument.detector

    def plain(a_half, p_half):
        log_amp, phase = setup.grid.to_full(a_half, p_half)
        illuminance = illuminance_from_psfs(
            instrument, setup, psfs, jnp.zeros(()), jnp.zeros(2), log_amp, phase
        )
        return detector.after_jitter(detector.jitter(illuminance), 1.0)

    scale = np.abs(jac).max()
    for i in np.linspace(0, k - 1, 5).astype(int):
        unit = jax.nn.one_hot(knots[i], n_half, dtype=jnp.float32)
        for block, tangents in ((0, (unit, zero)), (1, (zero, unit))):
            reference = jax.jvp(plain, (zero, zero), tangents)[1]
            np.testing.assert_allclose(jac[block * k + i], reference, atol=2e-6 * scale)


def test_knot_mtf_is_the_direct_fourier_sum(small):
    """The band-averaged MTF by a matrix product equals the triple sum it stands for."""
    instrument, setup, psfs, knots = small
    psfs = np.asarray(psfs, float)
    weights = np.asarray(setup.spectrum(jnp.zeros(())).weights(), float)
    uv = setup.grid.half_knots_m()[knots[::7]]
    n = psfs.shape[-1]
    theta = (np.arange(n) - (n - 1) / 2) * instrument.psf_pixel_rad
    direct = np.zeros(len(uv))
    for psf, w, wl in zip(psfs, weights, np.asarray(setup.wavelengths_m), strict=True):
        ex = np.exp(-2j * np.pi * np.outer(uv[:, 0] / wl, theta))
        ey = np.exp(-2j * np.pi * np.outer(uv[:, 1] / wl, theta))
        direct += w * np.abs(np.einsum("ky,yx,kx->k", ey, psf, ex)) / psf.sum()
    mtf = B.knot_mtf(psfs, weights, setup.wavelengths_m, instrument.psf_pixel_rad, uv)
    np.testing.assert_allclose(mtf, direct, rtol=1e-10, atol=1e-12)


def test_a_built_basis_is_orthonormal_and_sorted(small):
    """Each basis is the leading eigenvectors of its Hessian: orthonormal columns over the
    used knots, eigenvalues in decreasing order, fewer modes than knots."""
    instrument, setup, _, knots = small
    basis, info = B.build_basis(instrument, "F480M", setup.grid)
    for modes, evals in ((basis.amp, info.amp_eigenvalues), (basis.phase, info.phase_eigenvalues)):
        m = np.asarray(modes, float)
        assert 0 < m.shape[1] < len(knots) == m.shape[0]
        np.testing.assert_allclose(m.T @ m, np.eye(m.shape[1]), atol=1e-5)
        assert np.all(np.diff(evals) <= 1e-9 * evals[0])
