"""Visibility injection and the Hermitian knot grid, against independent calculations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

from amigo import niriss
from amigo.model.visibility import Injector, UVGrid, binary_log_visibility, keys_kernel

MAS = np.pi / 180 / 3600 / 1000
PIXEL_RAD = niriss.PIXEL_SCALE_ARCSEC * 1000 / 3 * MAS


def analytic_nrm_psf(n: int, wavelength_m: float, offset_rad=(0.0, 0.0), d_m: float = 0.8):
    """Point-sampled PSF of 7 circular holes (Airy envelope x fringes), written from the
    closed-form Fourier transform of a disc; independent of amigo's optics."""
    axis = (np.arange(n) - (n - 1) / 2) * PIXEL_RAD
    y, x = np.meshgrid(axis - offset_rad[1], axis - offset_rad[0], indexing="ij")
    arg = np.pi * d_m * np.hypot(x, y) / wavelength_m
    safe = np.maximum(arg, 1e-12)
    envelope = np.where(arg > 1e-12, 2 * scipy.special.j1(safe) / safe, 1.0)
    field = sum(
        np.exp(-2j * np.pi * (hx * x + hy * y) / wavelength_m) for hx, hy in niriss.HOLE_CENTRES_M
    )
    return envelope**2 * np.abs(field) ** 2


def test_keys_kernel_interpolates_and_sums_to_one():
    assert keys_kernel(np.array([0.0]))[0] == 1.0
    np.testing.assert_allclose(keys_kernel(np.array([1.0, 2.0, -1.0])), 0.0, atol=1e-15)
    t = np.linspace(0, 1, 7)
    total = sum(keys_kernel(t - k) for k in range(-2, 4))
    np.testing.assert_allclose(total, 1.0, atol=1e-12)


def test_hermitian_grid_round_trip():
    grid = UVGrid(7, 0.5)
    rng = np.random.default_rng(0)
    a, p = rng.normal(size=grid.n_half), rng.normal(size=grid.n_half)
    amp, pha = grid.to_full(a, p)
    # Point symmetry: log|V|(-b) = log|V|(b), arg V(-b) = -arg V(b); zero at b = 0.
    np.testing.assert_array_equal(amp, amp[::-1, ::-1])
    np.testing.assert_array_equal(pha, -pha[::-1, ::-1])
    assert amp[3, 3] == 0 and pha[3, 3] == 0
    s_amp, s_pha = grid.fold_matrix()
    np.testing.assert_array_equal(s_amp @ a, amp.ravel())
    np.testing.assert_array_equal(s_pha @ p, pha.ravel())
    # Knot coordinates: the free knots are the half plane v > 0 or (v = 0, u > 0).
    uv = grid.half_knots_m()
    assert np.all((uv[:, 1] > 0) | ((uv[:, 1] == 0) & (uv[:, 0] > 0)))


def test_unit_visibility_is_identity():
    psf = analytic_nrm_psf(96, 4.3e-6)[None]
    injector = Injector.build(UVGrid(), [4.3e-6], PIXEL_RAD, 96)
    zero = jnp.zeros((51, 51))
    out = np.asarray(injector(jnp.asarray(psf, jnp.float32), zero, zero))
    np.testing.assert_allclose(out, psf, atol=2e-6 * psf.max())


@pytest.mark.parametrize("wavelength_m", [3.8e-6, 4.8e-6])
def test_binary_injection_matches_shifted_psfs(wavelength_m):
    """A binary's log-visibility injected into a PSF equals (PSF + c PSF(. - theta)) / (1 + c)
    computed directly at the shifted position."""
    n = 160
    theta = np.array([150.0, -40.0]) * MAS
    contrast = 1e-2
    psf = analytic_nrm_psf(n, wavelength_m)
    truth = (psf + contrast * analytic_nrm_psf(n, wavelength_m, theta)) / (1 + contrast)
    grid = UVGrid()
    log_amp, phase = binary_log_visibility(grid.knots_m(), [wavelength_m], [1.0], theta, contrast)
    injector = Injector.build(grid, [wavelength_m], PIXEL_RAD, n)
    image = injector(
        jnp.asarray(psf[None], jnp.float32),
        jnp.asarray(log_amp.reshape(51, 51), jnp.float32),
        jnp.asarray(phase.reshape(51, 51), jnp.float32),
    )
    # Away from the field edges, where the shifted truth receives light from outside the
    # computed field (the injection cannot know about it).
    inner = slice(12, -12)
    error = np.abs(np.asarray(image)[0] - truth)[inner, inner]
    signal = np.abs(truth - psf).max()
    # Measured 1.6e-5 of the peak (0.2 % of the companion's signal) at 4.8 um.
    assert error.max() < 5e-5 * truth.max()
    assert error.max() < 0.01 * signal


def test_fourier_shift_matches_analytic_shift_inside_the_field():
    n = 160
    wavelength_m = 4.3e-6
    shift_pix = np.array([2.3, -1.6])
    psf = analytic_nrm_psf(n, wavelength_m)
    truth = analytic_nrm_psf(n, wavelength_m, shift_pix * PIXEL_RAD)
    injector = Injector.build(UVGrid(), [wavelength_m], PIXEL_RAD, n)
    out = np.asarray(
        injector(jnp.asarray(psf[None], jnp.float32), shift_pix=jnp.asarray(shift_pix))
    )[0]
    # The truncated field is not periodic: its edge step rings through the Fourier shift
    # (measured: 5.6e-3 of the peak at the very edge, 9e-5 10 px in, 4.6e-5 20 px in).
    # amigo's model computes the optics on a field 4 detector pixels wider than SUB80
    # for this reason (tests/test_model.py).
    inner = slice(20, -20)
    np.testing.assert_allclose(out[inner, inner], truth[inner, inner], atol=1e-4 * truth.max())


def test_broadband_injection_equals_the_weighted_monochromatic_images():
    # One inverse FFT of the weighted spectra against one per wavelength, then weighted.
    n = 96
    wavelengths = np.array([3.9e-6, 4.3e-6, 4.7e-6])
    weights = np.array([0.2, 0.5, 0.3])
    psfs = np.stack([analytic_nrm_psf(n, wl) for wl in wavelengths])
    grid = UVGrid()
    log_amp, phase = binary_log_visibility(
        grid.knots_m(), wavelengths, weights, np.array([120.0, 60.0]) * MAS, 0.05
    )
    injector = Injector.build(grid, wavelengths, PIXEL_RAD, n)
    args = (
        jnp.asarray(log_amp.reshape(51, 51), jnp.float32),
        jnp.asarray(phase.reshape(51, 51), jnp.float32),
        jnp.asarray([0.7, -1.2], jnp.float32),
    )
    per_wavelength = np.asarray(injector(jnp.asarray(psfs, jnp.float32), *args))
    expected = np.tensordot(weights, per_wavelength, 1)
    got = np.asarray(
        injector.broadband(jnp.asarray(psfs, jnp.float32), jnp.asarray(weights), *args)
    )
    np.testing.assert_allclose(got, expected, atol=1e-6 * expected.max())


def test_the_band_image_is_numpys_inverse_transform_of_the_shifted_band():
    # The pruned transform (columns outside the band and rows outside the kept corner
    # skipped) against NumPy's full irfft2 of the zero-padded band, in float64.
    n = 96
    with jax.enable_x64(True):
        injector = Injector.build(UVGrid(), np.array([4.3e-6]), PIXEL_RAD, n, dtype=np.float64)
    rows, nx_band, size = np.asarray(injector.rows), injector.nx_band, injector.fft_size
    rng = np.random.default_rng(3)
    band = rng.normal(size=(len(rows), nx_band)) + 1j * rng.normal(size=(len(rows), nx_band))
    shift = np.array([0.7, -1.2])  # (dx, dy) in samples
    full = np.zeros((size, size // 2 + 1), complex)
    full[rows, :nx_band] = band
    ramp_y = np.exp(-2j * np.pi * np.fft.fftfreq(size) * shift[1])
    ramp_x = np.exp(-2j * np.pi * np.fft.rfftfreq(size) * shift[0])
    expected = np.fft.irfft2(full * ramp_y[:, None] * ramp_x[None, :], s=(size, size))[:n, :n]
    with jax.enable_x64(True):
        got = np.asarray(injector._band_image(jnp.asarray(band), jnp.asarray(shift)))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-14 * np.abs(expected).max())


def test_the_band_axes_are_the_inverse_transform_of_the_band_as_two_products():
    # Re(E_y band E_x^T) against NumPy's irfft2 of the shifted, zero-padded band, on a
    # window (start, size) of the image, in float64.
    n, start, size = 96, 7, 80
    with jax.enable_x64(True):
        injector = Injector.build(UVGrid(), np.array([4.3e-6]), PIXEL_RAD, n, dtype=np.float64)
        e_y, e_x = injector.band_axes(jnp.asarray([0.7, -1.2]), start, size, jnp.float64)
    rows, nx_band, fft = np.asarray(injector.rows), injector.nx_band, injector.fft_size
    rng = np.random.default_rng(4)
    band = rng.normal(size=(len(rows), nx_band)) + 1j * rng.normal(size=(len(rows), nx_band))
    full = np.zeros((fft, fft // 2 + 1), complex)
    full[rows, :nx_band] = band
    ramp_y = np.exp(-2j * np.pi * np.fft.fftfreq(fft) * -1.2)
    ramp_x = np.exp(-2j * np.pi * np.fft.rfftfreq(fft) * 0.7)
    expected = np.fft.irfft2(full * ramp_y[:, None] * ramp_x[None, :], s=(fft, fft))
    expected = expected[start : start + size, start : start + size]
    got = np.real(np.asarray(e_y) @ band @ np.asarray(e_x).T)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-14 * np.abs(expected).max())


def test_the_jittered_illuminance_is_the_detectors_blur_of_the_illuminance():
    # The fit's path (point source by FFTs, visibilities by the composed per-axis
    # matrices) against the plain one (broadband image, crop, sub-pixel integration,
    # the detector's 2-D jitter), float64, with visibilities, a shift and a jitter.
    from amigo.model.image import (
        FilterSetup,
        Instrument,
        OpticsParams,
        filter_psfs,
        float64,
        illuminance_from_psfs,
        jittered_illuminance,
    )

    with jax.enable_x64(True):
        instrument = Instrument.nominal(n_wavelengths=3)
        setup = FilterSetup.create("F430M", instrument)
        instrument, setup = float64((instrument, setup))
        psfs = filter_psfs(instrument, setup, OpticsParams.from_instrument(instrument))
        rng = np.random.default_rng(6)
        k = setup.injector.w_y.shape[-1]
        log_amp, phase = (jnp.asarray(0.1 * rng.normal(size=(k, k))) for _ in range(2))
        args = (instrument, setup, psfs, jnp.asarray(0.3), jnp.asarray([0.02, -0.013]))
        jitter = jnp.asarray(0.024)
        got = np.asarray(jittered_illuminance(*args, log_amp, phase, None, jitter))
        plain = illuminance_from_psfs(*args, log_amp, phase)
        expected = np.asarray(instrument.detector.with_jitter(jitter).jitter(plain))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-13 * expected.max())
