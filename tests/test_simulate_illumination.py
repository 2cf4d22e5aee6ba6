"""The simulator's analytic NRM illumination against closed-form and brute-force values."""

from __future__ import annotations

import numpy as np
import pytest

from amigo import niriss
from amigo.simulation.illumination import (
    AnalyticNRM,
    UniformIllumination,
    hexagon_vertices_m,
    hole_phases_and_tilts,
    integrate_subpixels,
    nrm_intensity,
    polygon_fourier_transform,
)
from amigo.simulation.scene import DetectorScene, DetectorSource
from amigo.simulation.state import InstrumentState

HEX_AREA = 1.5 * np.sqrt(3.0) * (0.80 / np.sqrt(3.0)) ** 2


def test_hexagon_fourier_transform_matches_brute_force_integral():
    radius = 0.80 / np.sqrt(3.0)
    x = np.linspace(-0.5, 0.5, 2001)
    xx, yy = np.meshgrid(x, x)
    # Flat-topped hexagon with vertices on +-x (independent point-in-hexagon test).
    inside = (np.abs(yy) <= np.sqrt(3) / 2 * radius) & (
        np.sqrt(3) * np.abs(xx) + np.abs(yy) <= np.sqrt(3) * radius
    )
    d_area = (x[1] - x[0]) ** 2
    for qx, qy in [(0.0, 0.0), (0.3, 0.2), (1.1, -0.5), (-0.7, 1.3), (2.0, 0.0)]:
        brute = np.sum(inside * np.exp(-2j * np.pi * (qx * xx + qy * yy))) * d_area
        closed = polygon_fourier_transform(np.array(qx), np.array(qy), hexagon_vertices_m())
        assert closed == pytest.approx(brute, abs=2e-3 * HEX_AREA)
    assert polygon_fourier_transform(np.array(0.0), np.array(0.0), hexagon_vertices_m()) == (
        pytest.approx(HEX_AREA)
    )


def test_on_axis_intensity_and_piston_phases():
    """Peak = N A / lambda^2 for unit flux; a half-wave piston on one hole gives (N-2)^2."""
    centres = np.asarray(niriss.HOLE_CENTRES_M)
    wavelength = 4.3e-6
    zero = np.zeros(7)
    peak = nrm_intensity(np.array(0.0), np.array(0.0), wavelength, centres, zero, np.zeros((7, 2)))
    assert peak == pytest.approx(7 * HEX_AREA / wavelength**2, rel=1e-12)
    piston = zero.copy()
    piston[3] = wavelength / 2
    flipped = nrm_intensity(
        np.array(0.0), np.array(0.0), wavelength, centres, piston, np.zeros((7, 2))
    )
    assert flipped / peak == pytest.approx(25 / 49, rel=1e-12)
    # Fringes: between two holes only, the pattern is cos^2 with period lambda / baseline.
    two = centres[[1, 2]]
    baseline = two[1] - two[0]
    theta = np.linspace(0, 3, 7) * wavelength / np.dot(baseline, baseline) * baseline[0]
    thetay = np.linspace(0, 3, 7) * wavelength / np.dot(baseline, baseline) * baseline[1]
    values = nrm_intensity(theta, thetay, wavelength, two, np.zeros(2), np.zeros((2, 2)))
    envelope = (
        np.abs(
            polygon_fourier_transform(theta / wavelength, thetay / wavelength, hexagon_vertices_m())
        )
        ** 2
        * 4
        / (wavelength**2 * 2 * HEX_AREA)
    )
    fringe = np.cos(np.pi * np.linspace(0, 3, 7)) ** 2
    np.testing.assert_allclose(values, envelope * fringe, atol=1e-9 * values.max())


def test_defocus_maps_to_hole_piston_and_tilt():
    state = InstrumentState.perfect()
    state = InstrumentState(state.zernike_nm, {"F430M": 50.0})
    piston, gradient = hole_phases_and_tilts(state, "F430M")
    radius = niriss.PUPIL_DIAMETER_M / 2
    c = np.asarray(niriss.HOLE_CENTRES_M)
    # Independent: finite differences of sqrt(3) d (2 r^2 / R^2 - 1) at the hole centres.
    opd = lambda xy: np.sqrt(3) * 50e-9 * (2 * np.sum(xy**2, -1) / radius**2 - 1)  # noqa: E731
    np.testing.assert_allclose(piston, opd(c), rtol=1e-12)
    h = 1e-4
    dx, dy = np.array([h, 0.0]), np.array([0.0, h])
    fd = np.stack(
        [
            (opd(c + dx) - opd(c - dx)) / (2 * h),
            (opd(c + dy) - opd(c - dy)) / (2 * h),
        ],
        -1,
    )
    np.testing.assert_allclose(gradient, fd, rtol=1e-6)


def test_subpixel_integration_is_exact_for_the_band_limited_image():
    state = InstrumentState.perfect()
    scene = DetectorScene((DetectorSource(40.3, 38.7, 1.0),))
    model = AnalyticNRM(n_wavelengths=1)
    coarse = model.render(scene, "F380M", state, 2).reshape(80, 2, 80, 2).sum(axis=(1, 3))
    fine = model.render(scene, "F380M", state, 6).reshape(80, 6, 80, 6).sum(axis=(1, 3))
    assert np.abs(coarse - fine).max() < 1e-7 * fine.max()
    # Most of the light of a centred star falls on SUB80.
    assert 0.85 < fine.sum() < 1.0


def test_jitter_and_integration_conserve_flux_and_uniform_fills_evenly():
    rng = np.random.default_rng(0)
    samples = rng.uniform(size=(64, 64))
    assert integrate_subpixels(samples, 3.0).sum() == pytest.approx(samples.sum(), rel=1e-12)
    flat = UniformIllumination().render(
        DetectorScene((DetectorSource(1, 2, 6400.0),)), "F480M", InstrumentState.perfect(), 3
    )
    assert flat.shape == (240, 240)
    np.testing.assert_allclose(flat.reshape(80, 3, 80, 3).sum(axis=(1, 3)), 1.0)


@pytest.mark.slow
def test_project_optics_and_analytic_model_agree_for_piston_tilt_and_hole_positions():
    """Two independent implementations (sampled pupil + MFT + resampling in JAX, and the
    closed form here) of the same instrument state: Noll 1-3 per hole, distorted and
    shifted holes, jitter, two sources. The closed form is exact for this state."""
    from amigo.simulation.optics_illumination import OpticalModelIllumination

    rng = np.random.default_rng(4)
    zernike = np.zeros((7, 10))
    zernike[:, :3] = rng.normal(0.0, 20.0, (7, 3))
    state = InstrumentState(
        zernike_nm=zernike,
        defocus_nm={"F480M": 0.0},
        pupil_distortion=rng.normal(0.0, 2e-3, (2, 2)),
        hole_shift_m=rng.normal(0.0, 3e-3, (7, 2)),
        jitter_mas=20.0,
    )
    scene = DetectorScene((DetectorSource(44.3, 41.6, 1.0), DetectorSource(49.1, 37.2, 0.3)))
    optics = OpticalModelIllumination(n_wavelengths=3, pupil_npix=256).render(
        scene, "F480M", state, 4
    )
    analytic = AnalyticNRM(n_wavelengths=3).render(scene, "F480M", state, 4)
    a = analytic.reshape(80, 4, 80, 4).sum(axis=(1, 3))
    o = optics.reshape(80, 4, 80, 4).sum(axis=(1, 3))
    assert np.abs(a - o).max() < 5e-3 * a.max()
    assert np.sqrt(np.mean((a - o) ** 2)) < 2e-4 * a.max()
    assert o.sum() == pytest.approx(a.sum(), rel=5e-3)
