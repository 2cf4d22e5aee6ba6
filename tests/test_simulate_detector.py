"""Physics of the simulator's detector, each piece against an independent calculation."""

from __future__ import annotations

import numpy as np
import pytest

from amigo import niriss
from amigo.simulation.detector import (
    DetectorConfig,
    EdgeStrips,
    RampSimulator,
    adc_transfer,
    bfe_coefficients,
    boundary_shifts,
    collect,
    convolve_ipc,
    draw_detector,
    intra_pixel_response,
    ipc_kernel,
    one_over_f_columns,
)
from amigo.simulation.illumination import AnalyticNRM
from amigo.simulation.scene import DetectorScene, DetectorSource
from amigo.simulation.state import InstrumentState

TG = niriss.GROUP_TIME_S
GAIN = niriss.GAIN_E_PER_DN


def _realisation(shape=(80, 80), seed=0):
    return draw_detector(np.random.default_rng(seed), DetectorConfig(), shape)


# ---------------------------------------------------------------------- BFE geometry


@pytest.mark.parametrize("k", [2, 3, 4, 5])
def test_bfe_collection_conserves_charge(k):
    rng = np.random.default_rng(k)
    rate = rng.gamma(2.0, 50.0, (12 * k, 10 * k))
    strips = EdgeStrips.from_rate(rate, k)
    shift_x = rng.uniform(-0.9, 0.9, (12, 9))
    shift_y = rng.uniform(-0.9, 0.9, (11, 10))
    collected = collect(strips, shift_x, shift_y)
    assert collected.sum() == pytest.approx(rate.sum(), rel=1e-13)
    # Undisplaced boundaries collect exactly the pixel sums.
    np.testing.assert_array_equal(
        collect(strips, 0 * shift_x, 0 * shift_y), rate.reshape(12, k, 10, k).sum(axis=(1, 3))
    )


def test_bfe_swept_charge_matches_brute_force_geometry():
    """A displaced boundary hands over exactly the light between its old and new place.

    Reference: the sub-pixel rates spread uniformly over 1000 samples per pixel along x,
    and the samples between the old and new boundary counted directly.
    """
    k = 4
    rng = np.random.default_rng(3)
    rate = rng.uniform(1.0, 10.0, (1 * k, 3 * k))  # one row of three pixels
    strips = EdgeStrips.from_rate(rate, k)
    column_rate = rate.sum(axis=0)  # (3k,) rate per sub-column
    fine = 1000
    density = np.repeat(column_rate / (fine // k), fine // k)  # per fine sample
    position = (np.arange(3 * fine) + 0.5) / fine  # pixel units, pixel j spans [j, j+1]
    for shift in (-0.61, -0.13, 0.07, 0.4):
        collected = collect(strips, np.array([[shift, 0.0]]), np.zeros((0, 3)))
        boundary = 1.0 + shift
        expected_first = density[position < boundary].sum()
        expected_second = density[(position >= boundary) & (position < 2.0)].sum()
        assert collected[0, 0] == pytest.approx(expected_first, rel=1e-9)
        assert collected[0, 1] == pytest.approx(expected_second, rel=1e-9)


def test_charged_pixel_shrinks_and_coefficients_follow_the_dipole_law():
    a = bfe_coefficients(1e-6, 2)
    assert a[2, 0] == pytest.approx(1e-6)
    # Normal field of a charge at (m + 1/2, n) from the boundary midpoint.
    assert a[2, 1] / a[2, 0] == pytest.approx((1.5 / 1.5**3) / (0.5 / 0.5**3))
    assert a[3, 0] / a[2, 0] == pytest.approx((0.5 / 1.25**1.5) / (0.5 / 0.5**3))
    charge = np.zeros((7, 7))
    charge[3, 3] = 1e4
    sx, sy = boundary_shifts(charge, a, a)
    # Its right boundary moves left (-x), its left boundary right (+x): the pixel shrinks.
    assert sx[3, 3] == pytest.approx(-1e-2)
    assert sx[3, 2] == pytest.approx(+1e-2)
    assert sy[3, 3] == pytest.approx(-1e-2)
    assert sy[2, 3] == pytest.approx(+1e-2)
    # A boundary one row away feels the n = 1 coefficient.
    assert sx[4, 3] == pytest.approx(-1e4 * a[3, 0])
    # Uniform illumination: the charged pixel collects less, its neighbours more.
    strips = EdgeStrips.from_rate(np.ones((7 * 3, 7 * 3)), 3)
    collected = collect(strips, sx, sy)
    assert collected[3, 3] < 9.0 < collected[3, 4]
    assert collected.sum() == pytest.approx(9.0 * 49)


# ---------------------------------------------------------------------- whole ramps


def test_ideal_detector_group_differences_equal_flux_times_group_time():
    rng = np.random.default_rng(1)
    k = 3
    rate = rng.uniform(0.0, 2e4, (80 * k, 80 * k))
    flux = rate.reshape(80, k, 80, k).sum(axis=(1, 3))  # photons / s / pixel
    sim = RampSimulator(rate, k, _realisation(), DetectorConfig.ideal(), ngroups=6)
    ramp, truth = sim.integration(np.random.default_rng(0))
    np.testing.assert_allclose(
        np.diff(ramp, axis=0), np.broadcast_to(flux * TG / GAIN, (5, 80, 80)), rtol=1e-12
    )
    np.testing.assert_allclose(ramp[0], flux * TG / GAIN, rtol=1e-12)
    assert truth.photons == pytest.approx(flux.sum() * 6 * TG, rel=1e-12)
    # Reference pixels (bottom 4 rows) collect nothing when modelled.
    config = DetectorConfig.ideal(reference_pixels=True)
    ramp, truth = RampSimulator(rate, k, _realisation(), config, ngroups=2).integration(
        np.random.default_rng(0)
    )
    assert np.all(ramp[:, :4] == 0.0) and np.all(ramp[:, 4:] > 0.0)
    assert truth.photons == pytest.approx(flux[4:].sum() * 2 * TG, rel=1e-12)


def test_poisson_arrivals_have_poisson_variance():
    k = 2
    rate = np.full((80 * k, 80 * k), 2000.0)  # 8000 photons/s per pixel
    sim = RampSimulator(rate, k, _realisation(), DetectorConfig.ideal(poisson=True), ngroups=3)
    ramp, _ = sim.integration(np.random.default_rng(5))
    electrons = np.diff(ramp, axis=0) * GAIN
    mean = 8000.0 * TG
    assert electrons.mean() == pytest.approx(mean, rel=0.01)
    assert electrons.var() / mean == pytest.approx(1.0, abs=0.05)


def _width(image):
    """Core width (pixels): Gaussian fitted to the log of the 3x3 pixels around the peak."""
    y0, x0 = np.unravel_index(np.argmax(image), image.shape)
    patch = np.log(image[y0 - 1 : y0 + 2, x0 - 1 : x0 + 2])
    yy, xx = np.mgrid[-1:2, -1:2]
    design = np.stack(
        [np.ones(9), xx.ravel(), yy.ravel(), xx.ravel() ** 2, yy.ravel() ** 2, (xx * yy).ravel()], 1
    )
    coeffs = np.linalg.lstsq(design, patch.ravel(), rcond=None)[0]
    return (-1.0 / (2 * coeffs[3]) * -1.0 / (2 * coeffs[4])) ** 0.25


@pytest.fixture(scope="module")
def psf_rate():
    """A jittered F430M NRM image (3 wavelengths, 4x) with unit total rate."""
    state = InstrumentState(**{**InstrumentState.perfect().__dict__, "jitter_mas": 21.4})
    scene = DetectorScene((DetectorSource(45.2, 40.3, 1.0),))
    return AnalyticNRM(n_wavelengths=3).render(scene, "F430M", state, 4)


def test_bfe_broadens_the_core_by_a_few_percent_at_30k_dn_and_grows_with_signal(psf_rate):
    k, ngroups = 4, 20
    peak_rate = psf_rate.reshape(80, k, 80, k).sum(axis=(1, 3)).max()
    broadening = {}
    for peak_dn in (10000.0, 30000.0):
        rate = psf_rate * peak_dn * GAIN / (peak_rate * ngroups * TG)
        images = {}
        for bfe in (False, True):
            sim = RampSimulator(rate, k, _realisation(), DetectorConfig.ideal(bfe=bfe), ngroups)
            images[bfe] = sim.integration(np.random.default_rng(0))[0][-1]
        assert images[True].sum() == pytest.approx(images[False].sum(), rel=1e-12)
        broadening[peak_dn] = _width(images[True]) / _width(images[False]) - 1.0
    assert 0.02 < broadening[30000.0] < 0.05  # "a few percent" (3.0 % by default)
    # Grows with signal, close to linearly (the shifts are linear in the charge).
    assert broadening[30000.0] / broadening[10000.0] == pytest.approx(3.0, rel=0.2)


def test_adc_residual_folded_modulo_1024_shows_the_sinusoid():
    k = 2
    # A gradient of rates so that the reads cover many ADC periods.
    rate = np.repeat(np.repeat(np.linspace(2e3, 1.7e5, 80 * 80).reshape(80, 80), k, 0), k, 1) / k**2
    config = DetectorConfig.ideal(adc_inl=True, quantize=True, bias=True)
    realisation = _realisation()
    sim = RampSimulator(rate, k, realisation, config, ngroups=5)
    raw, _ = sim.integration(np.random.default_rng(0))
    flux = rate.reshape(80, k, 80, k).sum(axis=(1, 3))
    ideal = realisation.bias_dn + flux * TG * np.arange(1, 6)[:, None, None] / GAIN
    ideal = np.broadcast_to(ideal, raw.shape)
    residual = raw.astype(float) - ideal
    phase = 2 * np.pi * (ideal % 1024.0) / 1024.0
    design = np.stack([np.sin(phase).ravel(), np.cos(phase).ravel(), np.ones(phase.size)], 1)
    sin_amp, cos_amp, offset = np.linalg.lstsq(design, residual.ravel(), rcond=None)[0]
    assert sin_amp == pytest.approx(2.0, abs=0.03)
    assert abs(cos_amp) < 0.03 and abs(offset) < 0.03
    # Folded and binned, the residual traces 2 sin(2 pi v / 1024) within rounding noise.
    bins = np.clip((ideal % 1024.0 / 64).astype(int), 0, 15).ravel()
    binned = np.bincount(bins, residual.ravel(), 16) / np.bincount(bins, minlength=16)
    centres = 2 * np.pi * (np.arange(16) + 0.5) / 16
    expected = 2.0 * np.sin(centres) * np.sinc(1 / 16)  # mean of a sine over each bin
    np.testing.assert_allclose(binned, expected, atol=0.05)
    assert adc_transfer(np.array([256.0]), 2.0, 1024.0)[0] == pytest.approx(258.0)


def test_ipc_kernel_normalised_and_oriented():
    kernel = ipc_kernel()
    assert kernel.sum() == pytest.approx(1.0, abs=1e-15)
    charge = np.zeros((9, 9))
    charge[4, 4] = 1.0
    out = convolve_ipc(charge, kernel)
    norm = 1.0000028
    assert out[5, 4] == pytest.approx(3.980e-3 / norm)  # up: +y, next row
    assert out[3, 4] == pytest.approx(5.028e-3 / norm)  # down
    assert out[4, 3] == pytest.approx(4.710e-3 / norm) == out[4, 5]
    assert out[6, 6] == pytest.approx(-6.5e-6 / norm)
    assert out.sum() == pytest.approx(1.0)


def test_nonlinearity_saturation_and_intra_pixel_response():
    response = intra_pixel_response(4, 0.05)
    assert response.mean() == pytest.approx(1.0)
    # Edge-middle over centre of the bowl: 1 - 0.05 (sampled finely with an odd k).
    fine = intra_pixel_response(201, 0.05)
    assert fine[100, 200] / fine[100, 100] == pytest.approx(0.95, abs=1e-3)
    realisation = _realisation((4, 4))
    k = 2
    rate = np.full((4 * k, 4 * k), 2e7)  # 8e7 e-/s per pixel: saturates in ~1 ms
    config = DetectorConfig.ideal(nonlinearity=True, saturation=True)
    ramp, truth = RampSimulator(rate, k, realisation, config, ngroups=2).integration(
        np.random.default_rng(0)
    )
    q = config.full_well_e
    np.testing.assert_allclose(ramp[-1], q * (1 + realisation.nonlinearity_c2_per_e * q) / GAIN)
    assert truth.saturated_pixels == 16


def test_one_over_f_noise_has_the_configured_rms_and_a_red_spectrum():
    rng = np.random.default_rng(2)
    samples = np.stack([one_over_f_columns(rng, 20, 80, 80, 1.5) for _ in range(40)])
    assert samples.std() == pytest.approx(1.5, rel=0.15)
    # Adjacent columns are correlated (red noise), unlike white noise.
    flat = samples.reshape(40, -1)
    correlation = np.mean(flat[:, 1:] * flat[:, :-1]) / np.mean(flat**2)
    assert correlation > 0.3


def test_cosmic_rays_arrive_at_the_configured_rate():
    k = 2
    config = DetectorConfig.ideal(cosmic_rays=True, cosmic_ray_rate_per_cm2_s=2000.0)
    sim = RampSimulator(np.zeros((80 * k, 80 * k)), k, _realisation(), config, ngroups=10)
    counts = [len(sim.integration(np.random.default_rng(i))[1].cosmic_rays) for i in range(30)]
    expected = 2000.0 * (80 * 18e-4) ** 2 * 10 * TG
    assert np.mean(counts) == pytest.approx(expected, rel=0.2)
    ramp, truth = sim.integration(np.random.default_rng(99))
    for hit in truth.cosmic_rays:  # the jump appears in the group the hit falls in
        y, x, g = hit["y"], hit["x"], hit["group"]
        before = ramp[g - 1, y, x] if g > 0 else 0.0
        assert ramp[g, y, x] - before >= 0.69 * hit["electrons"] / GAIN


def test_config_from_mapping_rejects_unknown_keys_and_bad_types():
    config = DetectorConfig.from_mapping({"bfe": False, "read_noise_dn": 3})
    assert config.bfe is False and config.read_noise_dn == 3.0
    with pytest.raises(ValueError, match="unknown"):
        DetectorConfig.from_mapping({"bfee": True})
    with pytest.raises(ValueError, match="true or false"):
        DetectorConfig.from_mapping({"bfe": 1})
