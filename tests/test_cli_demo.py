"""`amigo demo` end to end: simulated raw ramps of a binary -> process -> fit -> detect.

The demo's binary is AB Dor-like (329 mas, PA 280.5 deg east of north, delta-mag 4.38 in
F480M); the companion must be found where it was simulated, within the errors amigo
reports (with a little room for the model's systematics, which the reported sigma_scale
absorbs). The fit goes through the shipped base model's detector with the physical account
of the charge migration in its network's place (the default for raw ramps).
"""

from __future__ import annotations

import json

import pytest

from amigo.cli import main
from amigo.companions.limits import photon_limit_dmag
from amigo.io.calvis import read_calvis


@pytest.mark.slow
def test_demo_finds_the_simulated_companion(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("AMIGO_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "demo"
    try:
        main(["demo", "--out", str(out), "--no-hmc"])
    except SystemExit as exit_:
        assert exit_.code in (0, None)
    printed = capsys.readouterr().out
    assert "simulated" in printed and "found" in printed
    for name in ("fit_summary.json", "AB-DOR_F480M_calvis.fits", "AB-DOR_F480M.oifits"):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "raw").glob("*_uncal.fits")) == [
        "jw01093012001_03102_00001_nis_uncal.fits",
        "jw01093015001_03102_00001_nis_uncal.fits",
    ]
    summary = json.loads((out / "fit_summary.json").read_text())
    assert [e["role"] for e in summary["exposures"]] == ["science", "calibrator"]
    assert "SIMULATED" in summary["model"]
    assert summary["detector"] == "boundary"
    assert summary["filters"]["F480M"]["detector"]["converged"]
    # The detector geometry and jitter are fitted and reported per exposure, with errors;
    # the simulator turns the image clockwise, as the SIAF does (docs/geometry.md).
    for exposure in summary["exposures"]:
        for key in ("rotation_deg", "anisotropy", "skew_deg", "scale", "jitter_mas"):
            assert exposure[key] is not None and f"{key}_err" in exposure, key
        assert exposure["rotation_deg"] < 0
        assert abs(exposure["rotation_deg"] + 0.444) < 0.1
    # Photons used, counted by hand from the simulation's truth: the science star's
    # photon rate in the subarray over the time the slopes span, (NGROUPS - 1) group
    # times per integration (not EFFEXPTM's NGROUPS). The fitted flux includes the PSF's
    # wings beyond the subarray, a few per cent more.
    truth = next(
        json.loads(p.read_text())
        for p in (out / "raw").glob("*_truth.json")
        if json.loads(p.read_text())["exposure"]["role"] == "science"
    )
    exposure = truth["exposure"]
    slope_s = exposure["nints"] * (exposure["ngroups"] - 1) * exposure["group_time_s"]
    by_hand = truth["illumination"]["photons_per_s_in_subarray"] * slope_s
    n_photons = read_calvis(out / "AB-DOR_F480M_calvis.fits").n_photons
    assert 1.0 <= n_photons / by_hand < 1.1, (n_photons, by_hand)
    doc = json.loads((out / "companions.json").read_text())
    assert doc["photon_limit_dmag"]["F480M"] == pytest.approx(
        photon_limit_dmag(n_photons), abs=1e-3
    )
    companions = doc["companions"]
    assert len(companions) >= 1
    c = companions[0]
    print(c)
    assert abs(c["sep_mas"] - 329.0) < 3 * c["sep_err_mas"] + 5.0
    assert abs((c["pa_deg"] - 280.5 + 180) % 360 - 180) < 3 * c["pa_err_deg"] + 1.0
    assert abs(c["dmag"]["F480M"] - 4.38) < 3 * c["dmag_err"]["F480M"] + 0.1
