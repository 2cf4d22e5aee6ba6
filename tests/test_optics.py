"""The optical model against independent calculations (analytic, brute force, finite
differences). All in float64. Figures reached are printed (run with ``-s``) and quoted
in docs/optics.md."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amigo import niriss
from amigo.model.optics import (
    ARCSEC_TO_RAD,
    Aperture,
    LinearSpectrum,
    NRMOptics,
    OpticsConfig,
    SEDSpectrum,
    box_fir_taps,
    cubic_upsample_taps,
    integrate_pixels,
    mft,
    mft_symmetric,
    pixel_transfer,
)
from amigo.model.optics.aperture import zernike_basis


@pytest.fixture(autouse=True)
def x64():
    with jax.enable_x64(True):
        yield


# ------------------------------------------------------------------------------------
# Independent reference: the analytic Fourier transform of a polygon
# ------------------------------------------------------------------------------------


def hexagon_vertices(flat_to_flat: float) -> np.ndarray:
    """Counter-clockwise vertices of a flat-top hexagon (vertices on the x axis)."""
    angles = np.deg2rad(np.arange(6) * 60.0)
    return flat_to_flat / np.sqrt(3) * np.stack([np.cos(angles), np.sin(angles)], 1)


def polygon_ft(vertices: np.ndarray, qx: np.ndarray, qy: np.ndarray) -> np.ndarray:
    """``int_P exp(-i q.x) d^2x`` over a convex polygon, by the divergence theorem.

    ``exp(-i q.x) = (i / q^2) div(q exp(-i q.x))``, so the area integral is a sum over
    edges of ``(q.n) L exp(-i q.m) sinc(q.t L / 2)`` (n outward normal, m midpoint).
    """
    total = np.zeros(np.broadcast(qx, qy).shape, complex)
    for a, b in zip(vertices, np.roll(vertices, -1, axis=0), strict=True):
        t = b - a
        length = np.hypot(*t)
        normal = np.array([t[1], -t[0]]) / length
        mid = 0.5 * (a + b)
        half_phase = 0.5 * (qx * t[0] + qy * t[1])
        total += (
            (qx * normal[0] + qy * normal[1])
            * length
            * np.exp(-1j * (qx * mid[0] + qy * mid[1]))
            * np.sinc(half_phase / np.pi)
        )
    return 1j * total / (qx**2 + qy**2)


def analytic_psf(theta_x: np.ndarray, theta_y: np.ndarray, wavelength: float) -> np.ndarray:
    """Intensity density (per rad^2, unit total power) of the ideal 7-hole mask."""
    qx, qy = 2 * np.pi * theta_x / wavelength, 2 * np.pi * theta_y / wavelength
    verts = hexagon_vertices(niriss.HOLE_FLAT_TO_FLAT_M)
    field = sum(
        polygon_ft(verts, qx, qy) * np.exp(-1j * (qx * cx + qy * cy))
        for cx, cy in niriss.HOLE_CENTRES_M
    )
    area = 7 * np.sqrt(3) / 2 * niriss.HOLE_FLAT_TO_FLAT_M**2
    return np.abs(field) ** 2 / (wavelength**2 * area)


def test_polygon_ft_reference_is_right():
    # The reference itself: q -> 0 gives the area; a square's transform is a sinc product.
    verts = hexagon_vertices(0.8)
    area = np.sqrt(3) / 2 * 0.8**2
    assert abs(polygon_ft(verts, np.array(1e-4), np.array(2e-4)) - area) < 1e-9
    square = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    qx, qy = np.array([1.3, -4.0]), np.array([2.1, 0.7])
    expected = np.sinc(qx / (2 * np.pi)) * np.sinc(qy / (2 * np.pi))
    np.testing.assert_allclose(polygon_ft(square, qx, qy), expected, atol=1e-12)


def test_symmetric_mft_equals_a_direct_fourier_sum():
    # Random complex field on an asymmetric pupil grid; the symmetric real-arithmetic
    # transform against the plain sum exp(-2 pi i (x tx + y ty) / lambda) written here.
    rng = np.random.default_rng(3)
    ny, nx, m = 9, 12, 10
    x = (np.arange(nx) - 3.7) * 0.05
    y = (np.arange(ny) - 6.2) * 0.05
    theta = (np.arange(m) - 0.5 * (m - 1)) * 1e-7
    field = rng.normal(size=(ny, nx)) + 1j * rng.normal(size=(ny, nx))
    wavelength = 4.3e-6
    k = 2 * np.pi / wavelength
    direct = np.einsum(
        "yx,ay,bx->ab",
        field,
        np.exp(-1j * k * np.outer(theta, y)),
        np.exp(-1j * k * np.outer(theta, x)),
    )
    half = theta[m // 2 :]
    re, im = mft_symmetric(
        jnp.asarray(field.real), jnp.asarray(field.imag), x, y, wavelength, half, half
    )
    np.testing.assert_allclose(np.asarray(re) + 1j * np.asarray(im), direct, atol=1e-12)
    general = mft(jnp.asarray(field), x, y, wavelength, theta, theta)
    np.testing.assert_allclose(np.asarray(general), direct, atol=1e-12)


def test_odd_focal_grid_uses_the_general_transform():
    # An odd number of focal samples (a zero angle) cannot use the symmetric transform;
    # the PSF must still be centred and agree with the even grid's where both sample.
    config = OpticsConfig(npix_detector=9, oversample=3, fresnel=False)  # 27 samples
    optics = NRMOptics.create(config)
    psf = np.asarray(optics.psfs(jnp.array([WAVELENGTH]), jnp.zeros(2))[0])
    assert psf.shape == (27, 27)
    np.testing.assert_allclose(psf, psf[::-1, ::-1], rtol=1e-9, atol=1e-12 * psf.max())
    assert np.unravel_index(psf.argmax(), psf.shape) == (13, 13)


# ------------------------------------------------------------------------------------
# The PSF against the closed form
# ------------------------------------------------------------------------------------

WAVELENGTH = 4.3e-6


def gauss_legendre_box(centres: np.ndarray, pitch: float, n: int = 3):
    """Nodes and weights of an n-point Gauss-Legendre rule over each sample's box."""
    x, w = np.polynomial.legendre.leggauss(n)
    nodes = (centres[:, None] + 0.5 * pitch * x[None, :]).ravel()
    return nodes, np.tile(0.5 * w, len(centres))


@pytest.fixture(scope="module")
def ideal_mono():
    """Model and analytic PSFs (point sampled and pixel integrated) at one wavelength."""
    with jax.enable_x64(True):
        optics = NRMOptics.create(OpticsConfig(fresnel=False))
        point = np.asarray(optics.psfs(jnp.array([WAVELENGTH]), jnp.zeros(2))[0])
        integrated = np.asarray(optics.integrate_pixels(point))
        theta = np.asarray(optics.focal_grid_rad())
    pitch = optics.config.psf_pixel_rad
    ref_point = analytic_psf(theta[None, :], theta[:, None], WAVELENGTH) * pitch**2
    # Box integral of the analytic intensity over every sub-pixel (3x3 Gauss-Legendre).
    nodes, weights = gauss_legendre_box(theta, pitch)
    dense = analytic_psf(nodes[None, :], nodes[:, None], WAVELENGTH) * pitch**2
    m = len(theta)
    ww = weights[:, None] * weights[None, :]
    ref_integrated = (dense * ww).reshape(m, 3, m, 3).sum(axis=(1, 3))
    return point, integrated, ref_point, ref_integrated


def test_psf_matches_closed_form_point_sampled(ideal_mono):
    point, _, ref, _ = ideal_mono
    err = np.abs(point - ref).max() / ref.max()
    print(f"\npoint-sampled PSF vs analytic hexagons: max |diff| / peak = {err:.2e}")
    assert err < 1e-3


def test_psf_matches_closed_form_pixel_integrated(ideal_mono):
    _, integrated, _, ref = ideal_mono
    err = np.abs(integrated - ref).max() / ref.max()
    rms = np.sqrt(np.mean((integrated - ref) ** 2)) / ref.max()
    print(f"\npixel-integrated PSF vs analytic: max |diff| / peak = {err:.2e}, rms {rms:.2e}")
    assert err < 1e-3


def test_psf_normalisation_and_centring(ideal_mono):
    point, _, ref, _ = ideal_mono
    # Unit power over the plane: the field of view holds most of it, as the analytic one.
    assert abs(point.sum() - ref.sum()) < 5e-3
    # Point symmetric mask intensity: the on-axis PSF is centred on the array centre.
    m = point.shape[0]
    c = (m - 1) / 2
    yy, xx = np.mgrid[:m, :m]
    core = (np.hypot(xx - c, yy - c) < 20) * point
    assert abs((core * xx).sum() / core.sum() - c) < 0.05
    assert abs((core * yy).sum() / core.sum() - c) < 0.05


def test_power_spectrum_has_21_splodges_at_the_baselines(ideal_mono):
    point = ideal_mono[0]
    m = point.shape[0]
    pad = 4
    big = np.zeros((pad * m, pad * m))
    big[:m, :m] = point
    otf = np.abs(np.fft.fftshift(np.fft.fft2(big)))
    otf /= otf.max()
    pitch = OpticsConfig().psf_pixel_rad
    u = (np.arange(pad * m) - pad * m // 2) * WAVELENGTH / (pad * m * pitch)  # metres
    uu, vv = np.meshgrid(u, u)
    baselines = niriss.baselines_m()
    assert baselines.shape == (21, 2)
    splodges = np.concatenate([baselines, -baselines, [[0.0, 0.0]]])
    near_any = np.zeros_like(otf, bool)
    for b in splodges:
        dist = np.hypot(uu - b[0], vv - b[1])
        near_any |= dist < 0.95  # the hexagon autocorrelation reaches 2 x 0.462 m
        if not b.any():
            continue
        local = np.where(dist < 0.4, otf, 0)
        # The splodge peaks at the baseline (within a fraction of the 0.8 m hole)...
        iy, ix = np.unravel_index(local.argmax(), local.shape)
        assert np.hypot(u[ix] - b[0], u[iy] - b[1]) < 0.08, b
        # ... with the non-redundant height 1/7 of the zero frequency.
        assert 0.12 < local.max() < 0.16, (b, local.max())
    # And there is no power anywhere else in the uv plane.
    print(f"\npower outside the 43 splodges: {otf[~near_any].max():.1e} of the peak")
    assert otf[~near_any].max() < 2e-3


# ------------------------------------------------------------------------------------
# Pixel integration against a 30x oversampled reference
# ------------------------------------------------------------------------------------


def test_pixel_integration_beats_12x_point_sampling():
    npix, wavelength = 24, 3.8e-6  # a small field; the bluest calibrated band is hardest
    with jax.enable_x64(True):

        def point_psf(oversample):
            config = OpticsConfig(npix_detector=npix, oversample=oversample, fresnel=False)
            optics = NRMOptics.create(config)
            return optics.psfs(jnp.array([wavelength]), jnp.array([0.013, -0.021]))[0]

        def to_pixels(image, factor):
            return np.asarray(image).reshape(npix, factor, npix, factor).sum(axis=(1, 3))

        psf30 = point_psf(30)
        ref = to_pixels(psf30, 30)
        # The 30x reference is itself a midpoint rule (error ~ h^2): Richardson
        # extrapolation with a 15x one removes that term, for an exact-to-1e-7 reference.
        exact = (4 * ref - to_pixels(point_psf(15), 15)) / 3
        plain12 = to_pixels(point_psf(12), 12)
        psf3 = point_psf(3)
        models = {
            "3x fir": to_pixels(integrate_pixels(psf3, "fir"), 3),
            "3x cubic (paper)": to_pixels(integrate_pixels(psf3, "cubic"), 3),
            "3x none": to_pixels(psf3, 3),
            "12x point": plain12,
            "30x point": ref,
        }
    vs30 = {k: np.abs(v - ref).max() / ref.max() for k, v in models.items() if k != "30x point"}
    # Filters see zeros beyond the field: away from its edge (here 1% of the peak, on
    # SUB80 1e-4) they are exact; compare the interior too.
    inner = (slice(1, -1), slice(1, -1))
    vs_exact = {k: np.abs(v - exact)[inner].max() / ref.max() for k, v in models.items()}
    print("\npixel integration, max |diff| / peak over 24x24 pixels at 3.8 um")
    print("  vs 30x:   ", {k: f"{v:.1e}" for k, v in vs30.items()})
    print("  vs exact (inner 22x22): ", {k: f"{v:.1e}" for k, v in vs_exact.items()})
    assert vs30["3x fir"] <= vs30["12x point"]  # the paper's benchmark
    assert vs_exact["3x fir"] < 0.1 * vs_exact["12x point"]  # and far better in truth
    assert vs_exact["3x cubic (paper)"] < vs_exact["3x none"]


def test_fir_taps_and_transfer():
    taps = box_fir_taps()
    assert abs(taps.sum() - 1) < 1e-14 and np.allclose(taps, taps[::-1])
    f = np.linspace(0, 0.27, 50)
    np.testing.assert_allclose(pixel_transfer(jnp.asarray(f)), np.sinc(f), atol=3e-5)
    # The paper's scheme is exactly cubic upsampling by 3 and block averaging.
    rng = np.random.default_rng(1)
    image = rng.normal(size=(30, 30))
    up = jax.image.resize(jnp.asarray(image), (90, 90), "cubic")
    block_mean = np.asarray(up).reshape(30, 3, 30, 3).mean(axis=(1, 3))
    filtered = np.asarray(integrate_pixels(jnp.asarray(image), "cubic"))
    np.testing.assert_allclose(filtered[3:-3, 3:-3], block_mean[3:-3, 3:-3], atol=1e-10)
    assert cubic_upsample_taps().shape == (5,)


@pytest.mark.parametrize("method", ["fir", "cubic", "none"])
def test_the_integration_matrix_on_both_axes_is_the_separable_filter(method):
    from amigo.model.optics.propagation import integration_matrix

    image = np.random.default_rng(2).normal(size=(30, 30))
    f = integration_matrix(30, method)
    with jax.enable_x64(True):
        filtered = np.asarray(integrate_pixels(jnp.asarray(image), method))
    np.testing.assert_allclose(f @ image @ f.T, filtered, rtol=0, atol=1e-14)


# ------------------------------------------------------------------------------------
# Sign conventions: tilt, Zernikes, position, defocus
# ------------------------------------------------------------------------------------

SMALL = OpticsConfig(npix_detector=32, pupil_npix=160, fresnel=False)


def _psf(optics, position=(0.0, 0.0), wavelength=WAVELENGTH):
    return np.asarray(optics.psfs(jnp.array([wavelength]), jnp.asarray(position))[0])


def test_zernike_basis_is_orthonormal_on_its_disc():
    # Independent check on a fine grid (numerical integration over the disc).
    from amigo.model.optics.aperture import PupilGrid

    n = 400
    axis = (np.arange(n) - (n - 1) / 2) * (2.0 / n)
    grid = PupilGrid(x_m=jnp.asarray(axis), y_m=jnp.asarray(axis), pixel_m=2.0 / n)
    basis = np.asarray(zernike_basis(grid, jnp.zeros((1, 2)), 1.0, 10))[0]
    disc = np.hypot(*np.meshgrid(axis, axis)) <= 1.0
    gram = np.einsum("iyx,jyx->ij", basis * disc, basis * disc) / disc.sum()
    np.testing.assert_allclose(gram, np.eye(10), atol=2e-2)
    # Noll 2 is x tilt: 2 rho cos(theta) = 2 x / r; Noll 3 is y tilt.
    x, y = np.meshgrid(axis, axis)
    np.testing.assert_allclose(basis[1][disc], 2 * x[disc], atol=1e-12)
    np.testing.assert_allclose(basis[2][disc], 2 * y[disc], atol=1e-12)


def test_tilt_zernikes_move_the_image_like_the_source_position():
    # OPD = t . x moves the image to +t. Over hole h, t . x is the Noll-2/3 tilts
    # t r_z / 2 (Noll 2 = 2 (x - c_x) / r_z, r_z the Zernike disc radius) plus the piston
    # t . c_h: the same image as a source at +t.
    optics = NRMOptics.create(SMALL)
    r_z = SMALL.zernike_radius_factor * niriss.HOLE_FLAT_TO_FLAT_M / np.sqrt(3)
    c_nm = 40.0
    tilt_arcsec = 2 * c_nm * 1e-9 / r_z / ARCSEC_TO_RAD
    slope = np.array([1.0, -0.5]) * 2 * c_nm / r_z  # nm per metre
    z = jnp.zeros((7, 10)).at[:, 1].set(c_nm).at[:, 2].set(-0.5 * c_nm)
    z = z.at[:, 0].set(jnp.asarray(niriss.HOLE_CENTRES_M @ slope))
    tilted = _psf(eqx.tree_at(lambda o: o.zernikes_nm, optics, z))
    moved = _psf(optics, (tilt_arcsec, -0.5 * tilt_arcsec))
    np.testing.assert_allclose(tilted, moved, atol=1e-9 * moved.max())
    # And the position convention: a source one pixel towards +x (+y) gives the same
    # image moved by 3 sub-pixels along the columns (rows), sample for sample.
    base = _psf(optics)
    scale = SMALL.pixel_scale_arcsec
    np.testing.assert_allclose(_psf(optics, (scale, 0.0))[:, 3:], base[:, :-3], atol=1e-12)
    np.testing.assert_allclose(_psf(optics, (0.0, scale))[3:, :], base[:-3, :], atol=1e-12)


def test_global_piston_is_removed():
    optics = NRMOptics.create(SMALL)
    z = jnp.asarray(np.random.default_rng(2).normal(0, 30, (7, 10)))
    a = _psf(eqx.tree_at(lambda o: o.zernikes_nm, optics, z))
    b = _psf(eqx.tree_at(lambda o: o.zernikes_nm, optics, z.at[:, 0].add(77.0)))
    np.testing.assert_allclose(a, b, atol=1e-12)
    grad = jax.grad(
        lambda z: jnp.sum(
            optics.psfs(jnp.array([WAVELENGTH]), jnp.zeros(2)) ** 2 * 0
            + eqx.tree_at(lambda o: o.zernikes_nm, optics, z).psfs(
                jnp.array([WAVELENGTH]), jnp.zeros(2)
            )[0, 40, 50]
        )
    )(z)
    assert abs(float(grad[:, 0].sum())) < 1e-9 * float(jnp.abs(grad).max())


DEFOCUS_NM = 60.0


def direct_defocused_psf(optics, defocus_nm, wavelength):
    """Fraunhofer sum of the pupil with the quadratic OPD written here (NumPy, float64).

    The discrete Fourier sum is evaluated directly at the output angles (as two
    matrix products, since it is separable); no FFT and no focal-plane transfer.
    """
    amplitude, _ = (np.asarray(a) for a in optics.pupil())
    x, y = np.asarray(optics.grid.x_m), np.asarray(optics.grid.y_m)
    radius = 0.5 * optics.config.pupil_diameter_m
    opd = 2 * np.sqrt(3) * defocus_nm * 1e-9 * (x[None, :] ** 2 + y[:, None] ** 2) / radius**2
    field = amplitude * np.exp(2j * np.pi * opd / wavelength)
    theta = np.asarray(optics.focal_grid_rad())
    kernel_x = np.exp(-2j * np.pi / wavelength * np.outer(theta, x))
    kernel_y = np.exp(-2j * np.pi / wavelength * np.outer(theta, y))
    e = kernel_y @ field @ kernel_x.T
    norm = optics.grid.pixel_m * optics.config.psf_pixel_rad / wavelength
    return np.abs(e * norm) ** 2 / float(optics.pupil_power())


def test_fresnel_defocus_matches_quadratic_pupil_phase():
    config = dataclasses.replace(
        SMALL, npix_detector=80, fresnel=True, defocus_method="angular_spectrum"
    )
    optics = NRMOptics.create(config, defocus_nm=DEFOCUS_NM)
    model = _psf(optics)
    direct = direct_defocused_psf(optics, DEFOCUS_NM, WAVELENGTH)
    wrong_sign = direct_defocused_psf(optics, -DEFOCUS_NM, WAVELENGTH)
    focused = direct_defocused_psf(optics, 0.0, WAVELENGTH)
    peak = direct.max()
    m = model.shape[0]
    inner = slice(m // 4, 3 * m // 4)  # the finite field loses light near its edges
    err = np.abs(model - direct)[inner, inner].max() / peak
    err_all = np.abs(model - direct).max() / peak
    effect = np.abs(focused - direct)[inner, inner].max() / peak
    sign_err = np.abs(model - wrong_sign)[inner, inner].max() / peak
    print(
        f"\ndefocus {DEFOCUS_NM} nm: angular spectrum vs quadratic pupil phase, "
        f"max |diff|/peak {err:.1e} (inner half), {err_all:.1e} (whole field); "
        f"defocus effect {effect:.1e}; opposite sign {sign_err:.1e}"
    )
    assert err < 2e-3 and err < 0.05 * effect and sign_err > 10 * err
    # The "pupil" method is the same OPD applied in the pupil: no edge loss at all.
    pupil_config = dataclasses.replace(config, defocus_method="pupil")
    pupil_way = _psf(NRMOptics.create(pupil_config, defocus_nm=DEFOCUS_NM))
    np.testing.assert_allclose(pupil_way, direct, atol=1e-9 * peak)


def test_defocus_equals_per_hole_zernikes():
    # A quadratic OPD k r^2 over hole h (centre c, Zernike radius r) is piston, tilts
    # Noll 2/3 = k r c_x, k r c_y and Noll 4 = k r^2 / (2 sqrt 3): a test that ties the
    # defocus parameter's sign and scale to the Zernike convention.
    config = dataclasses.replace(SMALL, fresnel=True, defocus_method="pupil")
    optics = NRMOptics.create(config)
    k = 2 * np.sqrt(3) * DEFOCUS_NM / (0.5 * config.pupil_diameter_m) ** 2  # nm / m^2
    r = config.zernike_radius_factor * niriss.HOLE_FLAT_TO_FLAT_M / np.sqrt(3)
    c = niriss.HOLE_CENTRES_M
    z = np.zeros((7, 10))
    z[:, 0] = k * ((c**2).sum(1) + r**2 / 2)
    z[:, 1], z[:, 2] = k * r * c[:, 0], k * r * c[:, 1]
    z[:, 3] = k * r**2 / (2 * np.sqrt(3))
    via_defocus = _psf(eqx.tree_at(lambda o: o.defocus_nm, optics, jnp.asarray(DEFOCUS_NM)))
    via_zernikes = _psf(eqx.tree_at(lambda o: o.zernikes_nm, optics, jnp.asarray(z)))
    np.testing.assert_allclose(via_defocus, via_zernikes, atol=1e-7 * via_defocus.max())


# ------------------------------------------------------------------------------------
# Static and dynamic apertures; distortions; spectra
# ------------------------------------------------------------------------------------


def test_static_and_dynamic_paths_agree():
    dynamic = NRMOptics.create(SMALL, static=False)
    z = jnp.asarray(np.random.default_rng(3).normal(0, 20, (7, 10)))
    dynamic = eqx.tree_at(lambda o: o.zernikes_nm, dynamic, z)
    np.testing.assert_allclose(_psf(dynamic), _psf(dynamic.frozen()), atol=1e-14)


def test_global_distortion_moves_holes_without_shift_freedom():
    aperture = Aperture.nominal()
    # Linear global term x -> x + a x: holes drawn where x (1 + a) = c_x, i.e. at c_x / (1 + a).
    a = 0.01
    coeff = aperture.global_distortion.at[0, 0].set(a)  # first term is x
    distorted = eqx.tree_at(lambda ap: ap.global_distortion, aperture, coeff)
    optics = NRMOptics.create(SMALL, aperture=distorted, static=False)
    amp, _ = optics.pupil()
    x = np.asarray(optics.grid.x_m)
    amp = np.asarray(amp)
    for h, (cx, _cy) in enumerate(niriss.HOLE_CENTRES_M):
        hole = np.asarray(optics.aperture.hole_transmissions(optics.grid))[h]
        centroid_x = (hole.sum(0) * x).sum() / hole.sum()
        assert abs(centroid_x - cx / (1 + a)) < 2e-3, h
    holes = np.asarray(optics.aperture.hole_transmissions(optics.grid))
    assert holes.max() <= 1.0 and holes.min() >= 0.0
    assert abs(amp.sum() - holes.sum()) < 1e-9 * holes.sum()  # sharpening keeps the area
    # No constant term: the zero polynomial leaves the mask exactly in place.
    assert aperture.global_distortion.shape == (2, 9)
    assert aperture.hole_distortion.shape == (7, 2, 5)


def test_spectrum_weights_and_slope():
    spec = LinearSpectrum.from_filter("F430M", 9, slope_per_um=2.0)
    w = np.asarray(spec.weights())
    assert w.shape == (9,) and abs(w.sum() - 1) < 1e-12 and (w > 0).all()
    flat = np.asarray(LinearSpectrum.from_filter("F430M", 9).weights())
    # A positive slope moves weight to the red end.
    lam = np.asarray(spec.wavelengths_m)
    assert (w * lam).sum() > (flat * lam).sum()
    # A user SED equal to the linear one gives the same weights.
    lam_c = float(spec.central_wavelength_m)
    custom = SEDSpectrum.from_filter("F430M", lambda l: 1 + 2.0 * (l - lam_c) / 1e-6, 9)
    np.testing.assert_allclose(custom.weights(), w, rtol=1e-12)


# ------------------------------------------------------------------------------------
# Gradients against finite differences
# ------------------------------------------------------------------------------------

GRAD = OpticsConfig(npix_detector=16, pupil_npix=128, fresnel=True)


def _image_with(params):
    """Pipeline (dynamic mask, Fresnel, 3 wavelengths) as a function of a flat dict."""
    from amigo.model.detector import LinearDetector

    optics = NRMOptics.create(GRAD, static=False)
    aperture = optics.aperture
    aperture = eqx.tree_at(
        lambda a: (a.global_distortion, a.hole_distortion, a.flat_to_flat_m),
        aperture,
        (
            aperture.global_distortion.at[0, 1].set(params["global_xy"]),
            aperture.hole_distortion.at[3, 1, 0].set(params["hole_3_yx"]),
            params["flat_to_flat_m"],
        ),
    )
    z = jnp.zeros((7, 10)) + 10.0
    z = z.at[2, 4].set(params["z_2_5"]).at[5, 7].set(params["z_5_8"])
    optics = eqx.tree_at(
        lambda o: (o.aperture, o.zernikes_nm, o.defocus_nm),
        optics,
        (aperture, z, params["defocus_nm"]),
    )
    spectrum = LinearSpectrum.from_filter("F480M", 3)
    spectrum = eqx.tree_at(lambda s: s.slope_per_um, spectrum, params["slope"])
    position = jnp.stack([params["x_arcsec"], params["y_arcsec"]])
    detector = LinearDetector.create(jitter_arcsec=1.0, rotation_deg=1.0, anisotropy=1.0)
    detector = eqx.tree_at(
        lambda d: (d.jitter_arcsec, d.rotation_deg, d.anisotropy),
        detector,
        (params["jitter_arcsec"], params["rotation_deg"], params["anisotropy"]),
    )
    return detector(optics.illuminance(spectrum, position), params["flux"])


GRAD_POINT = {
    "z_2_5": 25.0,
    "z_5_8": -30.0,
    "defocus_nm": 40.0,
    "x_arcsec": 0.031,
    "y_arcsec": -0.017,
    "global_xy": 0.003,
    "hole_3_yx": 0.02,
    "flat_to_flat_m": 0.8,
    "slope": 1.5,
    "jitter_arcsec": 0.021,
    "rotation_deg": 0.56,
    "anisotropy": 1.0077,
    "flux": 1e4,
}
FD_STEP = {
    "z_2_5": 1e-3,
    "z_5_8": 1e-3,
    "defocus_nm": 1e-3,
    "x_arcsec": 1e-7,
    "y_arcsec": 1e-7,
    "global_xy": 1e-7,
    "hole_3_yx": 1e-6,
    "flat_to_flat_m": 1e-7,
    "slope": 1e-5,
    "jitter_arcsec": 1e-7,
    "rotation_deg": 1e-5,
    "anisotropy": 1e-7,
    "flux": 1.0,
}


def test_gradients_match_finite_differences():
    weights = jnp.asarray(np.random.default_rng(4).normal(size=(16, 16)))
    params = {k: jnp.asarray(v) for k, v in GRAD_POINT.items()}

    loss = jax.jit(lambda p: jnp.sum(weights * _image_with(p)))
    grads = jax.jit(jax.grad(lambda p: jnp.sum(weights * _image_with(p))))(params)
    worst = 0.0
    for name, step in FD_STEP.items():
        up = dict(params, **{name: params[name] + step})
        down = dict(params, **{name: params[name] - step})
        fd = (float(loss(up)) - float(loss(down))) / (2 * step)
        ad = float(grads[name])
        rel = abs(ad - fd) / max(abs(fd), 1e-300)
        worst = max(worst, rel)
        assert rel < 2e-4, (name, ad, fd)
        assert abs(fd) > 0, name
    print(f"\ngradients vs central differences: worst relative error {worst:.1e}")


def test_band_taper_narrows_the_band_and_keeps_it_normalised():
    """The band-shape correction of LinearSpectrum: tau > 0 narrows the rms width by the
    documented ~0.43 tau s^2, tau < 0 widens it, tau = 0 is the plain filter weights."""
    from amigo.model.optics import LinearSpectrum

    plain = LinearSpectrum.from_filter("F430M", 9)
    wl = np.asarray(plain.wavelengths_m) * 1e6

    def width(tau):
        s = LinearSpectrum(
            plain.wavelengths_m, plain.filter_weights, plain.central_wavelength_m,
            plain.slope_per_um, tau,
        )  # fmt: skip
        w = np.asarray(s.weights(), np.float64)
        assert abs(w.sum() - 1) < 1e-6
        mean = (w * wl).sum()
        return np.sqrt((w * (wl - mean) ** 2).sum())

    s0 = width(0.0)
    np.testing.assert_allclose(np.asarray(plain.weights()), np.asarray(plain.filter_weights) / float(plain.filter_weights.sum()), rtol=1e-6)  # fmt: skip
    narrow = 1 - width(20.0) / s0
    assert narrow == pytest.approx(0.43 * 20 * s0**2, rel=0.15)
    assert width(-20.0) > s0


def test_zernike_orders_and_radial_polynomials_against_independent_forms():
    """Noll's ordering agrees with his definition for j = 1..66 (Noll 1976: modes by radial
    order n, then by |m| upwards, each |m| > 0 twice; an even j carries the cosine (m > 0),
    an odd j the sine (m < 0)) and with his table for j = 1..22; the radial polynomials
    equal the Jacobi-polynomial form R_n^m(rho) = (-1)^s rho^|m| P_s^(|m|, 0)(1 - 2 rho^2),
    s = (n - |m|)/2, to 1e-12."""
    from scipy.special import eval_jacobi

    from amigo.model.optics.aperture import _zernike_factors, noll_indices

    # Noll (1976), Table 1: (n, m) of j = 1..22, m < 0 for the sine modes.
    table = [(0, 0), (1, 1), (1, -1), (2, 0), (2, -2), (2, 2), (3, -1), (3, 1), (3, -3),
             (3, 3), (4, 0), (4, 2), (4, -2), (4, 4), (4, -4), (5, 1), (5, -1), (5, 3),
             (5, -3), (5, 5), (5, -5), (6, 0)]  # fmt: skip
    assert [noll_indices(j) for j in range(1, 23)] == table

    def by_definition(j: int) -> tuple[int, int]:
        n = 0
        while (n + 1) * (n + 2) // 2 < j:
            n += 1
        first = n * (n + 1) // 2 + 1  # the first j of radial order n
        orders = sorted(a for a in range(n % 2, n + 1, 2) for _ in range(1 if a == 0 else 2))
        a = orders[j - first]
        return n, 0 if a == 0 else (a if j % 2 == 0 else -a)

    rho = np.linspace(0.0, 1.0, 21)
    for j in range(1, 67):
        assert noll_indices(j) == by_definition(j), j
        n, m, c, k = _zernike_factors(j)
        radial = np.sum(c * rho[:, None] ** (n - 2 * k), axis=1)
        s = (n - abs(m)) // 2
        jacobi = (-1) ** s * rho ** abs(m) * eval_jacobi(s, abs(m), 0, 1 - 2 * rho**2)
        np.testing.assert_allclose(radial, jacobi, atol=1e-12)
    assert [noll_indices(j) for j in range(1, 7)] == [
        (0, 0),
        (1, 1),
        (1, -1),
        (2, 0),
        (2, -2),
        (2, 2),
    ]
