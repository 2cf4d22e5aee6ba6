"""NIRISS AMI facts: mask geometry, filters and their binning."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from astropy.io import fits

from amigo import niriss


def test_mask_has_21_nonredundant_baselines():
    b = niriss.baselines_m()
    assert b.shape == (21, 2)
    lengths = np.hypot(*b.T)
    assert lengths.min() == pytest.approx(1.32, abs=0.01)
    assert lengths.max() == pytest.approx(5.28, abs=0.01)
    # Non-redundant: no two baselines (or a baseline and the negative of another) coincide.
    for p, q in itertools.combinations(range(21), 2):
        assert np.linalg.norm(b[p] - b[q]) > 0.5
        assert np.linalg.norm(b[p] + b[q]) > 0.5


def test_holes_fit_inside_pupil():
    radius = np.hypot(*niriss.HOLE_CENTRES_M.T)
    hole_circumradius = niriss.HOLE_FLAT_TO_FLAT_M / np.sqrt(3)
    assert np.all(radius + hole_circumradius < niriss.PUPIL_DIAMETER_M / 2)


def test_pixel_scales_and_anisotropy_consistent():
    mean = 0.5 * (niriss.PIXEL_SCALE_X_ARCSEC + niriss.PIXEL_SCALE_Y_ARCSEC)
    assert mean == pytest.approx(niriss.PIXEL_SCALE_ARCSEC, rel=1e-4)
    m = niriss.SCI_TO_IDEAL_ARCSEC_PER_PIX
    assert np.hypot(*m[:, 0]) == pytest.approx(niriss.PIXEL_SCALE_X_ARCSEC, rel=1e-4)
    assert np.hypot(*m[:, 1]) == pytest.approx(niriss.PIXEL_SCALE_Y_ARCSEC, rel=1e-4)


def test_reference_rows_are_the_bottom_four():
    mask = niriss.reference_row_mask()
    assert mask.shape == (80, 80)
    assert mask[:4].all() and not mask[4:].any()


@pytest.mark.parametrize("name", niriss.CALIBRATED_FILTERS)
@pytest.mark.parametrize("n", [1, 5, 9, 21])
def test_filter_bins_weights_normalised_and_inside_band(name, n):
    bins = niriss.filter_bins(name, n)
    assert bins.wavelengths_m.shape == bins.weights.shape == (n,)
    assert bins.weights.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.all(bins.weights > 0)
    assert np.all(np.diff(bins.wavelengths_m) > 0)
    assert np.all(
        (bins.wavelengths_m > bins.edges_m[:-1]) & (bins.wavelengths_m < bins.edges_m[1:])
    )


@pytest.mark.parametrize("name", niriss.CALIBRATED_FILTERS)
def test_binned_mean_wavelength_equals_curve_mean(name):
    # Independent: the throughput-weighted mean of the raw tabulated curve (trapezoid rule).
    wavelength, throughput = niriss.filter_curve(name)
    inside = throughput >= niriss.FILTER_SUPPORT_FRACTION * throughput.max()
    w, t = wavelength[inside], throughput[inside]
    mean = np.trapezoid(w * t, w) / np.trapezoid(t, w)
    bins = niriss.filter_bins(name, 9)
    assert bins.central_wavelength_m == pytest.approx(mean, rel=2e-4)
    assert bins.central_wavelength_m == pytest.approx(niriss.CENTRAL_WAVELENGTH_M[name], rel=0.01)


def test_f430m_half_power_limits_match_published_values():
    blue, red = niriss.half_power_limits("F430M")
    assert abs(blue - 4.182e-6) < 5e-9
    assert abs(red - 4.395e-6) < 5e-9


def test_f277w_works_but_warns():
    with pytest.warns(niriss.UncalibratedFilterWarning, match="F277W"):
        bins = niriss.filter_bins("f277w", 9)
    assert bins.weights.sum() == pytest.approx(1.0)


def test_unknown_filter_is_rejected():
    with pytest.raises(ValueError, match="not an AMI filter"):
        niriss.filter_bins("F150W")
    with pytest.raises(ValueError):
        niriss.filter_bins("F430M", 0)


def test_hole_axes_match_real_power_spectrum(com1093_dir):
    """The 21 splodges of a real calibrator image sit where the mask frame predicts.

    Independent check of the frame's axes: the power of the real image at the 21
    predicted baseline frequencies is far above its power at the frequencies predicted by
    the transposed mask (the other plausible convention).
    """
    image = fits.getdata(com1093_dir / "jw01093015001_03102_00001_nis_cal.fits", "SCI")
    image = np.nan_to_num(image.astype(float))
    image[: niriss.N_REFERENCE_ROWS] = 0
    power = np.abs(np.fft.fft2(image)) ** 2
    wavelength = niriss.CENTRAL_WAVELENGTH_M["F480M"]
    rad_per_pix = np.array([niriss.PIXEL_SCALE_X_ARCSEC, niriss.PIXEL_SCALE_Y_ARCSEC])
    rad_per_pix = rad_per_pix / 206264.806

    def log_power(baselines):
        k = np.rint(baselines / wavelength * rad_per_pix * 80).astype(int) % 80
        return np.log(power[k[:, 1], k[:, 0]]).sum()

    b = niriss.baselines_m()
    assert log_power(b) > log_power(b[:, ::-1]) + 30
