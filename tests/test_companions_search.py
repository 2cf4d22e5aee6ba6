"""Injection and recovery: companions put into simulated observables are found again.

The simulations (tests/detect_helpers.py) are independent NumPy code; recovery is judged
against the reported 1-sigma errors (posterior or Laplace), within 2 sigma.
"""

from __future__ import annotations

import numpy as np
import pytest

from amigo.companions import observables as obs
from amigo.companions.search import SearchSettings, detect
from amigo.orientation import separation_pa
from detect_helpers import write_sim_calvis, write_sim_oifits

# At most 400 draws, in chunks of 200 (the sampler stops at its effective-sample target):
# the errors of one chain of 200 are Monte Carlo estimates noisy enough to decide a
# 2-sigma check (the faint companion's dDec error came out 5.4 mas in one such chain,
# 7.4-8.2 in others).
FAST_HMC = dict(num_warmup=150, num_samples=400, num_chains=1)


def _check(estimate, truth, filters):
    """Position and delta-mag within 2 sigma of the truth ``(dRA, dDec, {filter: c})``."""
    dra, ddec, flux = truth
    assert abs(estimate.dra_mas - dra) < 2 * estimate.dra_err_mas
    assert abs(estimate.ddec_mas - ddec) < 2 * estimate.ddec_err_mas
    sep, pa = separation_pa(dra, ddec)
    assert abs(estimate.sep_mas - sep) < 2 * estimate.sep_err_mas + 1e-9
    assert abs((estimate.pa_deg - pa + 180) % 360 - 180) < 2 * estimate.pa_err_deg
    for f in filters:
        assert abs(estimate.dmag[f] + 2.5 * np.log10(flux[f])) < 2 * estimate.dmag_err[f]


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::amigo.companions.posterior.PosteriorWarning")
def test_one_companion_in_two_filters_with_hmc(tmp_path):
    rng = np.random.default_rng(0)
    truth = (-323.4, 59.9, {"F380M": 0.0188, "F480M": 0.0176})  # AB Dor C-like
    blocks = [
        obs.load(
            write_sim_calvis(
                tmp_path / f"S_{f}_calvis.fits", f, [(truth[0], truth[1], truth[2][f])], rng
            )
        )
        for f in ("F380M", "F480M")
    ]
    result = detect(obs.Dataset.from_blocks(blocks), SearchSettings(rmax_mas=600.0, **FAST_HMC))
    assert len(result.companions) == 1
    companion = result.companions[0]
    assert companion.method == "hmc"
    assert companion.detection_sigma > 20
    _check(companion.estimate, truth, ("F380M", "F480M"))
    for f in ("F380M", "F480M"):  # the per-filter posteriors agree too
        _check(companion.per_filter[f], (truth[0], truth[1], truth[2]), (f,))
    for scale in result.sigma_scale.values():
        assert 0.6 < scale < 1.5
    assert result.posterior.r_hat_max < 1.1


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::amigo.companions.posterior.PosteriorWarning")
def test_two_companions_one_near_the_noise(tmp_path):
    """A bright companion and one detected at ~10 sigma, in one filter (DISCO-like).

    Each splodge is sampled at 7 uv points, as the forward model does: with the 21 baseline
    centres alone, the lattice of the NIRISS mask makes near-exact aliases of a companion
    (three positions ~700 mas apart fit equally well), and a faint second companion can
    then be traded for an alias of the first.
    """
    rng = np.random.default_rng(1)
    bright = (210.0, -380.0, 0.02)
    faint = (-150.0, 420.0, 0.0008)
    path = write_sim_calvis(
        tmp_path / "S_F430M_calvis.fits",
        "F430M",
        [bright, faint],
        rng,
        error=1e-3,
        splodge_radius_m=0.35,
    )
    result = detect(
        obs.Dataset.from_blocks([obs.load(path)]), SearchSettings(rmax_mas=600.0, **FAST_HMC)
    )
    assert len(result.companions) == 2
    first, second = result.companions
    assert 5 < second.detection_sigma < 20 < first.detection_sigma
    _check(first.estimate, (bright[0], bright[1], {"F430M": bright[2]}), ("F430M",))
    _check(second.estimate, (faint[0], faint[1], {"F430M": faint[2]}), ("F430M",))


@pytest.mark.slow
def test_oifits_companion_near_the_noise_without_hmc(tmp_path):
    """V2 + closure phases with correlated noise; Laplace errors from the joint fit."""
    rng = np.random.default_rng(2)
    truth = (180.0, 240.0, 0.003)
    path = write_sim_oifits(tmp_path / "sim.oifits", rng, truth, cp_error_rad=4e-3, v2_error=3e-3)
    # 21 point baselines on the mask's lattice: aliases ~700 mas from the truth fit almost
    # as well at this signal-to-noise; the field is kept inside the nearest alias.
    result = detect(
        obs.Dataset.from_blocks([obs.load(path)]), SearchSettings(rmax_mas=400.0, hmc=False)
    )
    assert len(result.companions) == 1
    companion = result.companions[0]
    assert companion.method == "fit"
    assert 5 < companion.detection_sigma < 20
    _check(companion.estimate, (truth[0], truth[1], {"F480M": truth[2]}), ("F480M",))


@pytest.mark.slow
def test_null_data_give_no_detection(tmp_path):
    rng = np.random.default_rng(3)
    blocks = [
        obs.load(write_sim_calvis(tmp_path / "N_F380M_calvis.fits", "F380M", [], rng)),
        obs.load(write_sim_calvis(tmp_path / "N_F480M_calvis.fits", "F480M", [], rng)),
    ]
    calvis = detect(obs.Dataset.from_blocks(blocks), SearchSettings(hmc=False))
    oifits = detect(
        obs.Dataset.from_blocks([obs.load(write_sim_oifits(tmp_path / "null.oifits", rng, None))]),
        SearchSettings(hmc=False),
    )
    for result in (calvis, oifits):
        assert result.companions == ()
        assert np.max(result.detection_maps[0].joint_significance) < 5.0
        # Limits exist everywhere outside the inner working angle and deepen outwards.
        for curve in result.limits:
            assert np.all(np.isfinite(curve.ruffio_dmag)) and curve.sep_mas.size > 5
            assert curve.ruffio_dmag[-1] > curve.ruffio_dmag[0] - 0.5


def test_a_companion_beyond_the_search_radius_is_not_reported(tmp_path):
    """A companion just outside ``rmax`` pulls the edge of the grid; the joint fit then
    follows it outside the searched field: not a detection, but a note. Searched with a
    radius that includes it, it is found where it is."""
    rng = np.random.default_rng(4)
    truth = (-560.0, 280.0, {"F480M": 0.02})  # 626 mas
    block = obs.load(
        write_sim_calvis(tmp_path / "S_F480M_calvis.fits", "F480M", [(*truth[:2], 0.02)], rng)
    )
    dataset = obs.Dataset.from_blocks([block])
    result = detect(dataset, SearchSettings(rmax_mas=560.0, hmc=False))
    assert all(c.estimate.sep_mas <= 560.0 for c in result.companions)
    assert any("beyond the search radius" in w for w in result.warnings)
    wide = detect(dataset, SearchSettings(rmax_mas=700.0, hmc=False))
    assert len(wide.companions) == 1
    _check(wide.companions[0].estimate, truth, ("F480M",))
