"""The physical bandpass (amigo.model.bandpass): filter x detector QE x stellar photon spectrum.

Validated against synphot (an independent implementation of the same photometric
definitions and of the Planck function) and against the metadata the SVO Filter Profile
Service wrote into the shipped VOTables.
"""

from __future__ import annotations

import numpy as np
import pytest

from amigo import niriss
from amigo.model import bandpass

MEDIUM_BANDS = ("F380M", "F430M", "F480M")
ANGSTROM = 1e-10


def _filter_only(name):
    return niriss.filter_curve(name)


# --------------------------------------------------------------------------------------
# (a) synphot
# --------------------------------------------------------------------------------------


def _synphot_bandpass(name, include_qe):
    synphot = pytest.importorskip("synphot")
    from synphot.models import Empirical1D

    wavelength, throughput = _filter_only(name)
    angstrom = wavelength / ANGSTROM
    band = synphot.SpectralElement(Empirical1D, points=angstrom, lookup_table=throughput)
    if include_qe:
        qe = bandpass.detector_qe(wavelength)
        band = band * synphot.SpectralElement(Empirical1D, points=angstrom, lookup_table=qe)
    return band, angstrom


@pytest.mark.parametrize("name", MEDIUM_BANDS)
def test_throughput_moments_match_synphot(name):
    band, angstrom = _synphot_bandpass(name, include_qe=False)
    wavelength, throughput = bandpass.effective_curve(name, include_qe=False)
    # synphot's avgwave / pivot / rmswidth of the bare throughput, in Angstrom.
    assert bandpass.effective_wavelength(wavelength, throughput) / ANGSTROM == pytest.approx(
        band.avgwave(angstrom).value, rel=1e-10
    )
    assert bandpass.pivot_wavelength(wavelength, throughput) / ANGSTROM == pytest.approx(
        band.pivot(angstrom).value, rel=1e-10
    )
    assert bandpass.rms_width(wavelength, throughput) / ANGSTROM == pytest.approx(
        band.rmswidth(angstrom).value, rel=1e-10
    )


@pytest.mark.parametrize("name", MEDIUM_BANDS)
@pytest.mark.parametrize("teff_k", [3000.0, 5000.0])
@pytest.mark.parametrize("include_qe", [False, True])
def test_blackbody_effective_wavelength_matches_synphot(name, teff_k, include_qe):
    import astropy.units as u
    from synphot import Observation, SourceSpectrum
    from synphot.models import BlackBody1D

    band, angstrom = _synphot_bandpass(name, include_qe)
    observation = Observation(SourceSpectrum(BlackBody1D, temperature=teff_k * u.K), band)
    # synphot: int P F_lambda lambda^2 / int P F_lambda lambda, i.e. the photon-weighted mean.
    expected = observation.effective_wavelength(binned=False, wavelengths=angstrom)
    wavelength, weight = bandpass.effective_curve(name, teff_k, include_qe=include_qe)
    ours = bandpass.effective_wavelength(wavelength, weight) / ANGSTROM
    # Same definition and grid: agreement is at rounding level (measured 0 to 1e-15).
    assert ours == pytest.approx(expected.to_value(u.AA), rel=1e-10)


def test_hot_blackbody_photon_spectrum_matches_synphot_planck():
    # synphot's BlackBody1D sampleset stops at 11x its peak, so a 10^4 K star is "disjoint"
    # from the band for Observation; compare the Planck functions directly instead.
    import astropy.units as u
    from synphot import units
    from synphot.models import BlackBody1D

    pytest.importorskip("synphot")
    wavelength, _ = _filter_only("F430M")
    for teff_k in (2500.0, 10_000.0, 40_000.0):
        theirs = BlackBody1D(temperature=teff_k * u.K)(wavelength / ANGSTROM)  # PHOTLAM / sr
        theirs = units.convert_flux(wavelength / ANGSTROM, theirs, units.PHOTLAM).value
        ours = bandpass.photon_blackbody(wavelength, teff_k)
        ratio = ours / theirs
        np.testing.assert_allclose(ratio / ratio.mean(), 1.0, rtol=1e-9)


# --------------------------------------------------------------------------------------
# (b) the SVO metadata of the shipped VOTables
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", MEDIUM_BANDS)
def test_svo_files_are_photon_counting_filter_only(name):
    params = bandpass.svo_parameters(name)
    assert params["WavelengthUnit"] == "Angstrom"
    assert params["DetectorType"] == "1"  # SVO: 1 = photon counter, 0 = energy counter
    assert params["Description"] == f"NIRISS {name} filter"
    _, throughput = _filter_only(name)
    # A telescope x instrument x QE system curve would peak near 0.3-0.5, not 0.75-0.92.
    assert 0.7 < throughput.max() < 0.95


@pytest.mark.parametrize("name", MEDIUM_BANDS)
def test_filter_only_numbers_match_svo_metadata(name):
    params = bandpass.svo_parameters(name)
    wavelength, throughput = _filter_only(name)
    # WavelengthMean = int x T dx / int T dx.
    assert bandpass.effective_wavelength(wavelength, throughput) / ANGSTROM == pytest.approx(
        params["WavelengthMean"], rel=1e-7
    )
    # WidthEff: the area over the peak (the file's description text says int x T dx, but the
    # number is the rectangle of equal area and peak height, as its second sentence says).
    area = bandpass._trapezoid(throughput, wavelength)
    assert area / throughput.max() / ANGSTROM == pytest.approx(params["WidthEff"], rel=1e-5)
    # WavelengthPivot: SVO's number is sqrt(int T / int T / x^2), the pivot of an
    # energy-counting T, i.e. the photon pivot of T / x. synphot's (photon) pivot, which
    # amigo follows, is 2.2e-4 (F430M) redder.
    assert bandpass.pivot_wavelength(wavelength, throughput / wavelength) / ANGSTROM == (
        pytest.approx(params["WavelengthPivot"], rel=1e-7)
    )
    # WavelengthMin/Max: first/last wavelength at >= 1 % of the peak, which SVO interpolates
    # and amigo takes on the 10 A grid: they agree to one sample.
    bins = bandpass.effective_bins(name, 9, include_qe=False)
    assert bins.edges_m[0] / ANGSTROM == pytest.approx(params["WavelengthMin"], abs=10.0)
    assert bins.edges_m[-1] / ANGSTROM == pytest.approx(params["WavelengthMax"], abs=10.0)


@pytest.mark.parametrize("name", MEDIUM_BANDS)
def test_vega_like_blackbody_close_to_svo_vega_wavelengths(name):
    # SVO's WavelengthPhot / WavelengthEff weight T by its Vega spectrum (photons / energy).
    # A 9550 K blackbody is only an approximation of Vega (hydrogen lines, model
    # atmosphere), so expect agreement to ~1e-4, not to rounding: measured offsets are
    # -3.6, +3.1, -4.7 A (F380M, F430M, F480M) against shifts of 25-50 A from the mean.
    params = bandpass.svo_parameters(name)
    wavelength, weight = bandpass.effective_curve(name, 9550.0, include_qe=False)
    photon_mean = bandpass.effective_wavelength(wavelength, weight) / ANGSTROM
    energy_mean = bandpass.effective_wavelength(wavelength, weight / wavelength) / ANGSTROM
    assert photon_mean == pytest.approx(params["WavelengthPhot"], abs=6.0)
    assert energy_mean == pytest.approx(params["WavelengthEff"], abs=6.0)


# --------------------------------------------------------------------------------------
# Binning: the throughput-only limit is niriss.filter_bins
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", MEDIUM_BANDS)
@pytest.mark.parametrize("n", [1, 9, 15])
def test_throughput_only_bins_reproduce_filter_bins(name, n):
    ours = bandpass.effective_bins(name, n, teff_k=None, width_scale=1.0, include_qe=False)
    reference = niriss.filter_bins(name, n)
    assert ours.name == reference.name
    np.testing.assert_allclose(ours.edges_m, reference.edges_m, rtol=1e-14)
    np.testing.assert_allclose(ours.wavelengths_m, reference.wavelengths_m, rtol=1e-13)
    np.testing.assert_allclose(ours.weights, reference.weights, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("name", MEDIUM_BANDS)
def test_bins_preserve_the_effective_wavelength(name):
    wavelength, weight = bandpass.effective_curve(name, 5000.0)
    bins = bandpass.effective_bins(name, 9, 5000.0)
    assert bins.weights.sum() == pytest.approx(1.0, rel=1e-12)
    assert np.all(np.diff(bins.wavelengths_m) > 0)
    # Like filter_bins, the bins cover only the support above 1 % of the peak: the wings
    # cut there move the mean by 0.4e-5 (F380M), 0.3e-5 (F430M) and 2.4e-5 (F480M).
    assert bins.central_wavelength_m == pytest.approx(
        bandpass.effective_wavelength(wavelength, weight), rel=3e-5
    )


def test_bad_arguments_are_rejected():
    with pytest.raises(ValueError):
        bandpass.effective_bins("F430M", 0)
    with pytest.raises(ValueError):
        bandpass.effective_curve("F430M", width_scale=0.0)
    with pytest.raises(ValueError):
        bandpass.effective_curve("F430M", teff_k=-10.0)
    with pytest.raises(ValueError):
        bandpass.effective_curve("F200W")


# --------------------------------------------------------------------------------------
# (c) the width correction
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", MEDIUM_BANDS)
@pytest.mark.parametrize("scale", [0.8, 0.93, 1.25])
def test_width_scale_conserves_mean_and_scales_rms_exactly(name, scale):
    base = bandpass.effective_curve(name, 5000.0)
    stretched = bandpass.effective_curve(name, 5000.0, width_scale=scale)
    assert bandpass.effective_wavelength(*stretched) == pytest.approx(
        bandpass.effective_wavelength(*base), rel=1e-13
    )
    assert bandpass.rms_width(*stretched) == pytest.approx(
        scale * bandpass.rms_width(*base), rel=1e-11
    )
    # The bins are the unstretched bins mapped by the same affine stretch about the mean.
    mean = bandpass.effective_wavelength(*base)
    bins = bandpass.effective_bins(name, 9, 5000.0, width_scale=scale)
    bins_1 = bandpass.effective_bins(name, 9, 5000.0)
    np.testing.assert_allclose(bins.weights, bins_1.weights, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(
        bins.wavelengths_m, mean + scale * (bins_1.wavelengths_m - mean), rtol=1e-12
    )
    span = bins.edges_m[-1] - bins.edges_m[0]
    assert span == pytest.approx(scale * (bins_1.edges_m[-1] - bins_1.edges_m[0]), rel=1e-12)


# --------------------------------------------------------------------------------------
# (d) the stellar spectrum
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", MEDIUM_BANDS)
def test_hotter_star_is_bluer(name):
    temperatures = [None, 2500.0, 3500.0, 5000.0, 10_000.0, 40_000.0]
    means = [
        bandpass.effective_wavelength(*bandpass.effective_curve(name, t)) for t in temperatures
    ]
    # None (flat photon spectrum) is reddest; then monotonically bluer with temperature.
    assert np.all(np.diff(means) < 0)
    # The Rayleigh-Jeans limit is a lambda^-3 photon spectrum.
    wavelength, weight = bandpass.effective_curve(name, None)
    rayleigh_jeans = bandpass.effective_wavelength(wavelength, weight * wavelength**-3.0)
    very_hot = bandpass.effective_wavelength(*bandpass.effective_curve(name, 1e7))
    assert very_hot == pytest.approx(rayleigh_jeans, rel=1e-7)


def test_photon_blackbody_is_planck_over_photon_energy():
    h, c, k = bandpass.PLANCK_J_S, bandpass.SPEED_OF_LIGHT_M_S, bandpass.BOLTZMANN_J_K
    wavelength = np.linspace(0.5e-6, 10e-6, 200)
    teff = 5772.0
    planck = 2 * h * c**2 / wavelength**5 / (np.exp(h * c / (wavelength * k * teff)) - 1)
    np.testing.assert_allclose(
        bandpass.photon_blackbody(wavelength, teff), planck / (h * c / wavelength), rtol=1e-12
    )
    # Wien's law for photons per unit wavelength: lambda_max T = hc / (3.920690 k).
    fine = np.linspace(0.3e-6, 1.5e-6, 120_001)
    peak = fine[np.argmax(bandpass.photon_blackbody(fine, teff))]
    assert peak * teff == pytest.approx(h * c / (3.920690395 * k), rel=1e-5)


# --------------------------------------------------------------------------------------
# The detector QE model
# --------------------------------------------------------------------------------------


def test_qe_model_passes_through_its_published_anchors():
    for wavelength, qe in bandpass.QE_ANCHORS:
        assert bandpass.detector_qe(wavelength) == pytest.approx(qe, abs=1e-12)
    fine = np.linspace(3.0e-6, 5.6e-6, 26_001)
    qe = bandpass.detector_qe(fine)
    assert qe.max() == pytest.approx(0.9125)
    # Half of the peak at 5.26 um: consistent with NIRISS's stated 5.2 um cutoff.
    half = fine[np.argmin(np.abs(qe - 0.5 * qe.max()))]
    assert half == pytest.approx(bandpass.NIRISS_CUTOFF_M, abs=0.1e-6)
    assert bandpass.detector_qe(2.5e-6) == pytest.approx(0.80)
    assert np.all(bandpass.detector_qe(np.array([6e-6, 8e-6])) >= 0.0)


# --------------------------------------------------------------------------------------
# (e) F430M widths (reported in docs/optics.md, "Bandpass")
# --------------------------------------------------------------------------------------


def test_f430m_widths():
    um = 1e-6
    filter_only = bandpass.effective_curve("F430M", include_qe=False)
    physical = bandpass.effective_curve("F430M", 5000.0)
    # Continuous curves (trapezoid): 0.06417 um filter-only, 0.06397 um x QE x 5000 K.
    assert bandpass.rms_width(*filter_only) / um == pytest.approx(0.06417, abs=2e-5)
    assert bandpass.rms_width(*physical) / um == pytest.approx(0.06397, abs=2e-5)
    assert bandpass.effective_wavelength(*filter_only) / um == pytest.approx(4.28599, abs=2e-5)
    assert bandpass.effective_wavelength(*physical) / um == pytest.approx(4.28244, abs=2e-5)

    # The 9 bins lose the within-bin variance (bin width^2 / 12): 0.0633 um.
    def binned_rms(bins):
        mean = bins.central_wavelength_m
        return float(np.sqrt(np.sum(bins.weights * (bins.wavelengths_m - mean) ** 2)))

    assert binned_rms(bandpass.effective_bins("F430M", 9, include_qe=False)) / um == (
        pytest.approx(0.06332, abs=2e-5)
    )
    assert binned_rms(bandpass.effective_bins("F430M", 9, 5000.0)) / um == pytest.approx(
        0.06313, abs=3e-5
    )
