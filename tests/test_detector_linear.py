"""Linear detector geometry against analytic images and the sky orientation chain."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amigo import niriss
from amigo.model.detector import (
    LinearDetector,
    bin_pixels,
    cubic_resample,
    displacement_reach,
    fourier_gaussian_blur,
    geometry_matrix,
    sky_to_optical_matrix,
)
from amigo.orientation import Orientation


@pytest.fixture(autouse=True)
def x64():
    with jax.enable_x64(True):
        yield


def gaussian_image(n: int, centre: np.ndarray, sigma: float, matrix=None) -> np.ndarray:
    """Unit-sum Gaussian density sampled on an n x n grid (offsets from the array centre),
    seen through ``d = matrix p`` (so its value at d is the density at matrix^-1 d)."""
    d = np.arange(n) - (n - 1) / 2
    dy, dx = np.meshgrid(d, d, indexing="ij")
    inv = np.eye(2) if matrix is None else np.linalg.inv(matrix)
    px = inv[0, 0] * dx + inv[0, 1] * dy - centre[0]
    py = inv[1, 0] * dx + inv[1, 1] * dy - centre[1]
    return np.exp(-0.5 * (px**2 + py**2) / sigma**2) / (2 * np.pi * sigma**2)


def test_geometry_matrix_is_rotation_times_area_preserving_scale():
    g = np.asarray(geometry_matrix(0.561, 1.00765))
    assert abs(np.linalg.det(g) - 1) < 1e-12
    # The image x axis turns counter-clockwise by phi; the y/x pixel scale ratio is a:
    # a unit optical step along detector-y direction spans 1/sqrt(a) pixels.
    phi = np.deg2rad(0.561)
    np.testing.assert_allclose(
        g @ [1, 0], [np.sqrt(1.00765) * np.cos(phi), np.sin(phi) / np.sqrt(1.00765)]
    )
    rot_back = np.array([[np.cos(phi), np.sin(phi)], [-np.sin(phi), np.cos(phi)]])
    np.testing.assert_allclose(
        g @ rot_back, np.diag([np.sqrt(1.00765), 1 / np.sqrt(1.00765)]), atol=1e-15
    )


def test_skew_and_scale_and_their_inverse():
    """The images of the optical axes are 90 + skew apart, at mean angle 90/2 + rotation
    (before the axis stretch); det G = scale^2 cos(skew); geometry_parameters inverts
    geometry_matrix for any of the four numbers."""
    rotation, skew, scale = -0.44, -0.26, 1.002
    g = np.asarray(geometry_matrix(rotation, 1.0, skew, scale))
    ax, ay = g @ [1, 0], g @ [0, 1]
    angle_x = np.rad2deg(np.arctan2(ax[1], ax[0]))
    angle_y = np.rad2deg(np.arctan2(ay[1], ay[0]))
    assert abs(angle_y - angle_x - (90 + skew)) < 1e-10
    assert abs(0.5 * (angle_x + angle_y - 90) - rotation) < 1e-10
    assert abs(np.linalg.det(g) - scale**2 * np.cos(np.deg2rad(skew))) < 1e-12
    for numbers in [
        (0.561, 1.00765, 0.0, 1.0),
        (-0.444, 1.006, -0.259, 1.00001),
        (3, 0.97, 2, 1.1),
    ]:
        back = niriss.geometry_parameters(np.asarray(geometry_matrix(*numbers)))
        got = (back.rotation_deg, back.anisotropy, back.skew_deg, back.scale)
        np.testing.assert_allclose(got, numbers, atol=1e-12)


def test_detector_defaults_to_the_siaf_geometry_turning_clockwise():
    detector = LinearDetector.create()
    np.testing.assert_allclose(detector.matrix(), niriss.nominal_geometry_matrix(), atol=1e-12)
    assert float(detector.rotation_deg) < 0  # clockwise, as the SIAF and real data say


def test_resampling_beyond_its_reach_is_nan_and_compiles_without_host_callbacks():
    image = jnp.ones((60, 60))
    assert np.all(np.isnan(cubic_resample(image, geometry_matrix(10.0, 1.0), reach=3)))
    assert np.all(np.isfinite(cubic_resample(image, geometry_matrix(0.5, 1.0), reach=3)))
    # The whole detector is one program without a host callback: JAX keeps such programs
    # out of its persistent compilation cache (an eqx.error_if here once did that to
    # every program of the fit).
    detector = LinearDetector.create()
    lowered = jax.jit(lambda d, x: d(x, 1.0)).lower(detector, jnp.ones((240, 240)))
    assert "callback" not in lowered.as_text()


def test_identity_resampling_is_exact():
    image = np.random.default_rng(0).normal(size=(30, 30))
    out = cubic_resample(jnp.asarray(image), jnp.eye(2))
    np.testing.assert_allclose(out, image, atol=1e-13)


def test_resampling_moves_an_analytic_image_by_the_matrix():
    n, sigma, centre = 96, 3.0, np.array([7.3, -4.1])
    g = np.asarray(geometry_matrix(0.561, 1.00765))
    # Exaggerate the geometry (10x the rotation and anisotropy) to make errors visible.
    g_big = np.asarray(geometry_matrix(5.61, 1.0765))
    for matrix in (g, g_big):
        image = gaussian_image(n, centre, sigma)
        reach = displacement_reach(matrix, image.shape)
        out = np.asarray(cubic_resample(jnp.asarray(image), jnp.asarray(matrix), reach))
        expected = gaussian_image(n, centre, sigma, matrix)
        err = np.abs(out - expected).max() / expected.max()
        assert err < 2e-3, err
        # Flux is conserved (det = 1; cubic interpolation is exactly conservative only
        # for pure shifts) and the centroid lands at matrix @ centre.
        print(
            f"\nresampling a sigma={sigma} Gaussian: max error {err:.1e} of peak, "
            f"flux change {out.sum() - 1:.1e}"
        )
        assert abs(out.sum() - 1) < 1e-4
        d = np.arange(n) - (n - 1) / 2
        cx = (out.sum(0) * d).sum() / out.sum()
        cy = (out.sum(1) * d).sum() / out.sum()
        np.testing.assert_allclose([cx, cy], matrix @ centre, atol=1e-3)  # sub-pixels


def test_jitter_adds_its_variance_and_conserves_flux():
    n, sigma0 = 64, 2.0
    image = gaussian_image(n, np.zeros(2), sigma0)
    d = np.arange(n) - (n - 1) / 2
    var_in = (image.sum(0) * d**2).sum() / image.sum()
    for jitter in (0.0, 0.2, 1.3):  # any sigma >= 0, sub-sample ones included
        out = np.asarray(fourier_gaussian_blur(jnp.asarray(image), jitter, pad=8))
        assert np.all(np.isfinite(out))
        assert abs(out.sum() - image.sum()) < 1e-12
        var_out = (out.sum(0) * d**2).sum() / out.sum()
        assert abs(var_out - var_in - jitter**2) < 1e-6
        # And the blur of a Gaussian is the analytic wider Gaussian.
        wider = gaussian_image(n, np.zeros(2), np.hypot(sigma0, jitter))
        assert np.abs(out - wider).max() < 1e-6 * wider.max()


def test_the_jitter_matrix_on_both_axes_is_the_two_dimensional_blur():
    # M X M^T against the 2-D padded transforms, and against the analytic wider Gaussian.
    rng = np.random.default_rng(5)
    image = rng.normal(size=(48, 48))
    for jitter_arcsec in (0.0, 0.021, 0.08):
        detector = LinearDetector.create(jitter_arcsec=jitter_arcsec)
        m = np.asarray(detector.jitter_matrix(48, jnp.float64))
        blurred = np.asarray(detector.jitter(jnp.asarray(image)))
        np.testing.assert_allclose(m @ image @ m.T, blurred, rtol=0, atol=1e-13)
    sigma = 0.08 * 3 / niriss.PIXEL_SCALE_ARCSEC  # samples of the 3x grid
    point = np.zeros(48)
    point[24] = 1.0
    d = np.arange(48) - 24
    analytic = np.exp(-0.5 * d**2 / sigma**2) / np.sqrt(2 * np.pi * sigma**2)
    # Sampled Gaussian of a band-limited point: equal where sigma >> 1 sample (here 3.7).
    assert np.abs(m @ point - analytic).max() < 1e-6


def test_zero_jitter_is_finite_with_a_finite_gradient():
    """A detector with jitter 0 returns the unblurred image (the old spatial blur divided
    by sigma and returned NaN), and its derivative in the jitter is finite (0 there)."""
    from amigo.model.optics import NRMOptics, OpticsConfig, PointSource

    optics = NRMOptics.create(OpticsConfig(pupil_npix=64))
    source = PointSource.create("F430M", flux=1.0, n_wavelengths=1)
    illum = optics.illuminance(source.spectrum, source.position_arcsec)
    detector = LinearDetector.create(jitter_arcsec=0.0)
    image = np.asarray(detector(illum, 1.0))
    assert np.all(np.isfinite(image))
    np.testing.assert_allclose(
        np.asarray(detector.jitter(illum)), np.asarray(illum), atol=1e-12 * float(illum.max())
    )

    def peak(jitter):
        return detector.with_jitter(jitter).jitter(illum).max()

    grad = jax.grad(peak)(0.0)
    assert np.isfinite(grad)


def test_bin_pixels():
    image = np.arange(36.0).reshape(6, 6)
    out = np.asarray(bin_pixels(jnp.asarray(image), 3))
    assert out.shape == (2, 2)
    assert out[0, 1] == image[:3, 3:].sum()


def test_detector_conserves_flux_of_a_psf():
    from amigo.model.optics import NRMOptics, OpticsConfig, PointSource

    optics = NRMOptics.create(OpticsConfig(pupil_npix=128))
    source = PointSource.create("F430M", flux=1e6, n_wavelengths=3)
    illum = optics.illuminance(source.spectrum, source.position_arcsec)
    detector = LinearDetector.create()
    image = np.asarray(detector(illum, source.flux))
    assert image.shape == (80, 80)
    jittered = detector.jitter(illum)
    resampled = detector.resample(jittered)
    jit_loss = float(jittered.sum() / illum.sum()) - 1
    res_loss = float(resampled.sum() / jittered.sum()) - 1
    # On a field padded so that no light leaves it, jitter conserves flux exactly and
    # resampling to the cubic-interpolation level; on the 80x80 field, the light blurred
    # or rotated out of the field (and none in) is what is lost.
    padded = jnp.pad(illum, 30)
    jit_padded = float(detector.jitter(padded).sum() / padded.sum()) - 1
    res_padded = float(detector.resample(detector.jitter(padded)).sum() / padded.sum()) - 1
    print(
        f"\nflux change on the 80x80 field: jitter {jit_loss:.1e}, resampling {res_loss:.1e}; "
        f"padded field: jitter {jit_padded:.1e}, resampling {res_padded:.1e}"
    )
    # (The Fourier-space blur conserves the sum to the rounding of the image's dtype.)
    assert abs(jit_padded) < 1e-8 and abs(res_padded) < 2e-5
    assert abs(jit_loss) < 5e-4 and abs(res_loss) < 5e-4
    # IPC moves charge between pixels and conserves it, up to the sliver that couples
    # across the subarray's edges (where the PSF is faint).
    np.testing.assert_allclose(image.sum(), 1e6 * float(resampled.sum()), rtol=5e-5)  # 1.1e-5
    no_ipc = LinearDetector.create(ipc=False)
    plain = np.asarray(no_ipc(illum, source.flux))
    np.testing.assert_allclose(plain.sum(), 1e6 * float(resampled.sum()), rtol=1e-12)
    from amigo.model.detector.read import convolve_ipc, default_ipc_kernel

    np.testing.assert_allclose(
        image, np.asarray(convolve_ipc(jnp.asarray(plain), jnp.asarray(default_ipc_kernel())))
    )


def test_offsets_round_trip_and_sky_chain():
    detector = LinearDetector.create()
    p = jnp.array([[0.31, -0.12], [-1.0, 0.5]])
    np.testing.assert_allclose(
        detector.detector_to_optical(detector.optical_to_detector(p)), p, atol=1e-12
    )
    # Arcsec along detector axes use the SIAF per-axis scales.
    pix = jnp.array([2.0, -3.0])
    arcsec = pix * jnp.array([niriss.PIXEL_SCALE_X_ARCSEC, niriss.PIXEL_SCALE_Y_ARCSEC])
    np.testing.assert_allclose(
        detector.detector_arcsec_to_optical(arcsec), detector.detector_to_optical(pix), atol=1e-12
    )
    np.testing.assert_allclose(
        detector.optical_to_detector_arcsec(detector.detector_arcsec_to_optical(arcsec)),
        arcsec,
        atol=1e-12,
    )
    # Sky -> optical matrix equals the chain sky -> detector (WCS) -> optical.
    orientation = Orientation(pa_aper_deg=172.3)
    sky = np.array([-323.4, 59.9])  # mas
    dx, dy = orientation.sky_to_detector(*sky)
    chained = np.asarray(detector.detector_to_optical(jnp.array([dx, dy]))) * 1000
    np.testing.assert_allclose(
        sky_to_optical_matrix(orientation, detector) @ sky, chained, rtol=1e-12
    )


def test_companion_lands_where_the_matrix_says():
    # A source at the optical offset p = G^-1 d appears moved by exactly d pixels on the
    # detector: with d whole pixels, its image is the on-axis image rolled by d.
    from amigo.model.optics import NRMOptics, OpticsConfig, PointSource

    optics = NRMOptics.create(OpticsConfig(pupil_npix=128))
    detector = LinearDetector.create(rotation_deg=5.0, anisotropy=1.05)  # exaggerated
    source = PointSource.create("F480M", n_wavelengths=1)
    shift = np.array([5, -3])  # detector pixels (x, y)
    offset = detector.detector_to_optical(jnp.asarray(shift, float))

    def image(position):
        return np.asarray(detector(optics.illuminance(source.spectrum, position), 1.0))

    on_axis, moved = image(jnp.zeros(2)), image(offset)
    rolled = np.roll(on_axis, (shift[1], shift[0]), axis=(0, 1))
    inner = (slice(10, -10), slice(10, -10))
    err = np.abs(moved - rolled)[inner].max() / on_axis.max()
    # The same with the sign of the rotation flipped misplaces the image by ~0.5 pixel.
    wrong = LinearDetector.create(rotation_deg=-5.0, anisotropy=1.05)
    wrong_offset = wrong.detector_to_optical(jnp.asarray(shift, float))
    wrong_err = np.abs(image(wrong_offset) - rolled)[inner].max() / on_axis.max()
    print(
        f"\nsource moved by G p: max |diff| / peak {err:.1e} (wrong rotation sign {wrong_err:.1e})"
    )
    assert err < 5e-3 and wrong_err > 20 * err
