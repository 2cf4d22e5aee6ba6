"""Detection significance: trials of the grid, the inner working angle, a stellar spectrum.

The trials formula is calibrated against Monte-Carlo null data sets by
benchmarks/false_alarm.py (40 null calvis pairs, F380M + F480M, 600 mas: the false-alarm
probabilities of the highest peaks are close to uniform, 55 % below 0.5 and 10 % below
0.1); here the formulas are checked against direct calculations and the search is run
on a scene whose "companion" has contrasts that no spectrum has.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from amigo.companions import observables as obs
from amigo.companions.grid import inner_working_angle_mas, sigma_from_chi2
from amigo.companions.search import SearchSettings, detect
from amigo.companions.significance import (
    MAX_BLUE_COLOUR_MAG_PER_UM,
    MAX_RED_COLOUR_MAG_PER_UM,
    effective_trials,
    inside_working_angle,
    log_chi2_sf,
    significance,
    spectrum_test,
)
from detect_helpers import write_sim_calvis

WAVELENGTHS_UM = np.array([3.83, 4.29, 4.82])  # F380M, F430M, F480M


def test_one_trial_is_the_local_significance():
    for dchi2, dof in [(30.0, 1), (40.0, 2), (60.0, 3)]:
        s = significance(dchi2, dof, 1.0)
        assert s.sigma == pytest.approx(s.local_sigma, rel=1e-9)
        assert s.local_sigma == pytest.approx(float(sigma_from_chi2(dchi2, dof)), rel=1e-9)
        assert s.false_alarm_probability == pytest.approx(stats.chi2.sf(dchi2, dof), rel=1e-9)


def test_false_alarm_probability_of_n_trials():
    """``1 - (1 - p)^N`` where that is computable; ``N p`` in the far tail, where the two
    branches meet continuously; the significance falls with the trials."""
    p = stats.chi2.sf(20.0, 2)
    s = significance(20.0, 2, 200.0)
    assert s.false_alarm_probability == pytest.approx(1 - (1 - p) ** 200, rel=1e-9)
    deep = significance(400.0, 2, 200.0)
    assert np.log(deep.false_alarm_probability) == pytest.approx(
        np.log(200.0) + float(log_chi2_sf(400.0, 2)), rel=1e-9
    )
    near = [significance(d, 2, 200.0).false_alarm_probability for d in (114.9, 115.1)]
    assert near[0] > near[1] and near[0] / near[1] < 1.2
    assert significance(60.0, 2, 200.0).sigma < significance(60.0, 2, 1.0).sigma
    # A 5-sigma local peak among 200 positions: FAP ~ 200 x 5.7e-7, 3.86 sigma.
    five = float(stats.chi2.isf(stats.norm.sf(5.0) * 2, 2))
    assert significance(five, 2, 200.0).local_sigma == pytest.approx(5.0, rel=1e-6)
    global_sigma = stats.norm.isf(200 * stats.norm.sf(5.0))
    assert significance(five, 2, 200.0).sigma == pytest.approx(global_sigma, rel=1e-3)
    assert global_sigma == pytest.approx(3.86, abs=0.01)


def test_trials_are_resolution_elements_in_the_annulus():
    assert effective_trials(1000.0, 70.0) == pytest.approx((1000**2 - 70**2) / 70**2)
    assert effective_trials(50.0, 70.0) == 1.0


def test_a_candidate_is_inside_the_working_angle_only_beyond_two_of_its_errors():
    """A candidate fitted at 90 +- 8 mas may be a companion at 103 mas (93-mas inner
    working angle): a detection; one at 56 +- 9 mas is not."""
    assert not inside_working_angle(90.0, 8.0, 93.0)
    assert not inside_working_angle(100.0, 0.0, 93.0)
    assert inside_working_angle(56.0, 9.0, 93.0)
    assert inside_working_angle(76.0, 8.0, 93.0)  # 2.1 sigma inside


def test_a_smooth_spectrum_passes_and_a_broken_one_fails():
    rng = np.random.default_rng(0)
    # A companion 1.5 mag per micron redder than its star, 2 % errors: consistent.
    truth = 0.02 * 10 ** (0.4 * 1.5 * (WAVELENGTHS_UM - 4.3))
    errors = 0.02 * truth
    p_values = np.array(
        [
            spectrum_test(truth + rng.normal(0, errors), errors, WAVELENGTHS_UM).p_value
            for _ in range(200)
        ]
    )
    # The truth lies inside the cone of admitted spectra: noisy contrasts around it need
    # no constraint (p = 1) unless the noise crosses a wall; never a false rejection.
    assert np.mean(p_values < 1e-3) == 0.0
    assert np.mean(p_values > 0.999) > 0.5
    fitted = spectrum_test(truth, errors, WAVELENGTHS_UM)
    assert fitted.chi2 == pytest.approx(0.0, abs=1e-9)
    assert fitted.colour_mag_per_um == pytest.approx(-1.5, abs=0.02)  # brighter in the red
    # The spurious candidate of the issue: dmag 25.1 / 0.24 / 3.8 (F380M / F430M / F480M).
    broken = 10 ** (-0.4 * np.array([25.1, 0.24, 3.8]))
    test = spectrum_test(broken, 0.05 * broken + 1e-3, WAVELENGTHS_UM)
    assert not test.consistent and test.p_value < 1e-10
    # Two filters: any pair fits, unless the colour exceeds the steepest one admitted,
    # towards the blue (the companion fainter in the red) or the red.
    gap = WAVELENGTHS_UM[2] - WAVELENGTHS_UM[0]
    for bound, sign in ((MAX_BLUE_COLOUR_MAG_PER_UM, -1.0), (MAX_RED_COLOUR_MAG_PER_UM, 1.0)):
        pair = np.array([0.01, 0.01 * 10 ** (sign * 0.4 * 0.8 * bound * gap)])
        assert spectrum_test(pair, 0.01 * pair, WAVELENGTHS_UM[[0, 2]]).consistent
        pair = np.array([0.01, 0.01 * 10 ** (sign * 0.4 * 1.2 * bound * gap)])
        assert not spectrum_test(pair, 0.01 * pair, WAVELENGTHS_UM[[0, 2]]).consistent


def test_a_cool_companion_peaking_in_f430m_is_a_spectrum_and_a_dip_is_not():
    """HD 206893 c's contrasts (9.14 / 8.32 / 8.07 mag) are no exponential in wavelength
    (the test before 2026-12-01 rejected them at these errors), nor is a T dwarf's peak
    between the methane and carbon monoxide bands; flux missing in the middle filter
    only is no spectrum."""
    c = 10 ** (-0.4 * np.array([9.14, 8.32, 8.07]))
    for relative in (0.15, 0.05, 0.02):
        assert spectrum_test(c, relative * c, WAVELENGTHS_UM).chi2 == pytest.approx(0, abs=1e-6)
    peak = 10 ** (-0.4 * np.array([10.0, 8.0, 8.6]))
    assert spectrum_test(peak, 0.05 * peak, WAVELENGTHS_UM).consistent
    # The simulated c found at 8.4 sigma, once rejected: 10.01 +- 0.52 / 8.28 +- 0.15 /
    # 8.60 +- 0.29 mag.
    dmag, dmag_err = np.array([10.01, 8.28, 8.60]), np.array([0.52, 0.15, 0.29])
    found = 10 ** (-0.4 * dmag)
    assert spectrum_test(found, found * 0.4 * np.log(10) * dmag_err, WAVELENGTHS_UM).consistent
    dip = np.array([1e-3, 0.0, 1e-3])
    assert spectrum_test(dip, np.full(3, 1e-4), WAVELENGTHS_UM).p_value < 1e-9
    # The order of the filters given does not matter.
    order = [2, 0, 1]
    assert spectrum_test(dip[order], np.full(3, 1e-4), WAVELENGTHS_UM[order]).p_value < 1e-9
    rising = spectrum_test(peak[order], 0.05 * peak[order], WAVELENGTHS_UM[order])
    assert rising.consistent


@pytest.mark.slow
def test_contrasts_no_spectrum_has_are_a_rejected_candidate_not_a_companion(tmp_path):
    """A point source bright in F380M and absent in F480M (residual structure that one
    filter sees): well above the threshold, but reported as a rejected candidate."""
    rng = np.random.default_rng(11)
    flux = {"F380M": 0.03, "F480M": 1e-6}
    blocks = [
        obs.load(write_sim_calvis(tmp_path / f"X_{f}_calvis.fits", f, [(250.0, -180.0, c)], rng))
        for f, c in flux.items()
    ]
    dataset = obs.Dataset.from_blocks(blocks)
    result = detect(dataset, SearchSettings(rmax_mas=500.0, hmc=False))
    assert result.companions == ()
    (rejected,) = result.rejected
    assert rejected.reason == "spectrum"
    assert rejected.significance.sigma > 5.0
    assert (
        abs(rejected.estimate.dra_mas - 250.0) < 10 and abs(rejected.estimate.ddec_mas + 180) < 10
    )
    iwa = inner_working_angle_mas(dataset.blocks)
    assert result.trials == pytest.approx(effective_trials(500.0, iwa))
