"""``amigo detect`` through its public interface: files written, keys, exit codes, peer data."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np
import pytest

from amigo.cli import main
from conftest import SHARED_DATA
from detect_helpers import write_point_source_oifits, write_sim_calvis, write_sim_oifits

#: Keys of companions.json fixed by the project's interfaces (shared/design/interfaces.md).
TOP_KEYS = {
    "amigo_version",
    "inputs",
    "filters",
    "companions",
    "sigma_scale",
    "contrast_limits",
    "photon_limit_dmag",
}
COMPANION_KEYS = {
    "id",
    "sep_mas",
    "sep_err_mas",
    "pa_deg",
    "pa_err_deg",
    "dra_mas",
    "ddec_mas",
    "dmag",
    "dmag_err",
    "detection_sigma",
    "method",
}


def run(argv: list[str]) -> int:
    with pytest.raises(SystemExit) as exit_info:
        main(["detect", *argv])
    return exit_info.value.code


def within_2_sigma(companion: dict, dra: float, ddec: float, dmag: dict[str, float]) -> None:
    assert abs(companion["dra_mas"] - dra) < 2 * companion["dra_err_mas"]
    assert abs(companion["ddec_mas"] - ddec) < 2 * companion["ddec_err_mas"]
    for f, value in dmag.items():
        assert abs(companion["dmag"][f] - value) < 2 * companion["dmag_err"][f]


def check_contrast_maps(out: Path, rows: list[dict], companion: dict) -> None:
    """contrast_maps.fits: its sky axes put the detection map's peak on the companion,
    and its limit maps' annulus means are the CSV's curves."""
    from astropy.io import fits
    from astropy.wcs import WCS

    with fits.open(out / "contrast_maps.fits") as hdul:
        names = [h.name for h in hdul[1:]]
        assert names == ["SIGNIFICANCE"] + [
            f"{m}_{f}" for f in ("F380M", "F480M", "COMBINED") for m in ("ABSIL", "RUFFIO")
        ]
        significance = hdul["SIGNIFICANCE"].data
        wcs = WCS(hdul["SIGNIFICANCE"].header)
        peak = np.unravel_index(np.nanargmax(significance), significance.shape)
        dra, ddec = wcs.pixel_to_world_values(peak[1], peak[0])
        step = hdul[0].header["STEPMAS"]
        # The nearest grid point to the companion (the peak of a smooth map).
        assert abs(dra - companion["dra_mas"]) <= 0.5 * step + 1e-6
        assert abs(ddec - companion["ddec_mas"]) <= 0.5 * step + 1e-6
        for hdu in hdul[2:]:  # every map on the same sky axes
            assert hdu.data.shape == significance.shape
            for key in ("CTYPE1", "CTYPE2", "CRPIX1", "CRPIX2", "CDELT1", "CDELT2", "CUNIT1"):
                assert hdu.header[key] == hdul["SIGNIFICANCE"].header[key]
        n_y, n_x = significance.shape
        x, y = wcs.pixel_to_world_values(*np.meshgrid(np.arange(n_x), np.arange(n_y)))
        radius = np.hypot(x, y)
        for f in ("F480M", "combined"):
            absil = hdul[f"ABSIL_{f.upper()}"].data
            curve = [r for r in rows if r["filter"] == f]
            # The CSV's annuli are step wide; their centres are its sep_mas.
            for r in curve[:3]:
                ring = np.abs(radius - float(r["sep_mas"])) < step / 2
                ring &= np.isfinite(absil)
                assert np.mean(absil[ring]) == pytest.approx(float(r["absil_dmag"]), abs=1e-3)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::amigo.companions.posterior.PosteriorWarning")
def test_calvis_end_to_end(tmp_path, capsys):
    rng = np.random.default_rng(7)
    truth = (-323.4, 59.9)
    flux = {"F380M": 0.0188, "F480M": 0.0176}
    inputs = [
        str(write_sim_calvis(tmp_path / f"ABDOR-SIM_{f}_calvis.fits", f, [(*truth, flux[f])], rng))
        for f in flux
    ]
    out = tmp_path / "out"
    code = run(
        [
            *inputs,
            "--out",
            str(out),
            "--rmax-mas",
            "600",
            "--warmup",
            "60",
            "--samples",
            "60",
            "--chains",
            "1",
            "--no-per-filter",
        ]
    )
    assert code == 0
    assert "companion 1: sep" in capsys.readouterr().out
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "companions.json",
        "contrast_limits.csv",
        "contrast_limits.png",
        "contrast_maps.fits",
        "corner_1.png",
        "detection_maps.png",
        "posterior_predictive.png",
    ]
    doc = json.loads((out / "companions.json").read_text())
    assert TOP_KEYS <= set(doc)
    assert doc["filters"] == ["F380M", "F480M"]
    assert doc["inputs"] == [os.path.basename(p) for p in inputs]
    (companion,) = doc["companions"]
    assert COMPANION_KEYS <= set(companion)
    assert companion["method"] == "hmc" and companion["detection_sigma"] > 20
    # the sampler's settings as run: the warm-up asked for, Laplace's mass matrix kept
    assert (doc["hmc"]["num_warmup"], doc["hmc"]["mass_matrix"]) == (60, "laplace")
    # Loose check here (60 samples); the 2-sigma recovery is tested in test_companions_search.
    assert abs(companion["sep_mas"] - np.hypot(*truth)) < 5 * companion["sep_err_mas"] + 1
    assert set(doc["contrast_limits"]["F480M"]) >= {"sep_mas", "dmag_3sigma"}
    assert doc["photon_limit_dmag"]["F380M"] == pytest.approx(7.5)
    with open(out / "contrast_limits.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert {r["filter"] for r in rows} == {"F380M", "F480M", "combined"}
    assert set(doc["contrast_limits"]) == {"F380M", "F480M"}
    assert set(doc["combined"]["contrast_limits"]) >= {"sep_mas", "sep_lambda_d", "dmag_3sigma"}
    # Two filters of 1e8 photons each: the combined rule counts 2e8.
    rule = doc["combined"]["photon_limit_dmag"]
    assert rule == pytest.approx(7.5 + 1.25 * np.log10(2), abs=1e-3)
    for row in rows:  # lambda / D of the filter's mean wavelength, D = 6.603 m
        wave = {"F380M": 3.83e-6, "F480M": 4.82e-6, "combined": 4.33e-6}[row["filter"]]
        mas = float(row["sep_lambda_d"]) * wave / 6.603464 * 206264806.2
        assert mas == pytest.approx(float(row["sep_mas"]), rel=0.02)
    assert set(rows[0]) == {
        "filter",
        "sep_mas",
        "n_sigma",
        "ruffio_dmag",
        "ruffio_dmag_std",
        "absil_dmag",
        "absil_dmag_std",
        "photon_limit_dmag",
        "sep_lambda_d",
        "absil_all_dmag",
        "absil_dof",
        "n_obs",
    }
    # The Absil test counts the observables a companion can move: here (21 uv points,
    # 29 kernel observables a filter) all of them, and so the same limit as on all.
    for row in rows:
        assert (
            int(row["absil_dof"])
            == int(row["n_obs"])
            == 29 * (2 if row["filter"] == "combined" else 1)
        )
        assert float(row["absil_all_dmag"]) == pytest.approx(float(row["absil_dmag"]), abs=1e-3)
    check_contrast_maps(out, rows, companion)
    # The same search again keeps the products (companions.json, written last, records
    # the inputs and options); another option or input is another search.
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    argv = [*inputs, "--out", str(out), "--rmax-mas", "600", "--warmup", "60", "--samples",
            "60", "--chains", "1", "--no-per-filter"]  # fmt: skip
    assert run(argv) == 0
    assert "up to date (same inputs and options), kept" in capsys.readouterr().out
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    from amigo.pipeline._detect import _detect_key

    settings = {"rmax_mas": 600.0, "seed": 0}
    assert _detect_key(inputs, settings) != _detect_key(inputs, {**settings, "seed": 1})
    assert _detect_key(inputs, settings) != _detect_key(inputs[:1], settings)


@pytest.mark.parametrize("kind", ["missing", "text", "image"])
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, kind):
    path = tmp_path / "input.fits"
    if kind == "text":
        path.write_text("hello")
    elif kind == "image":
        from astropy.io import fits

        fits.HDUList([fits.PrimaryHDU(np.zeros((4, 4)))]).writeto(path)
    code = run([str(path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("amigo: error:") and str(path) in err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_bad_option_exits_2(tmp_path, capsys):
    code = run(["x.fits", "--out", str(tmp_path), "--rmax-mas", "-3"])
    assert code == 2


@pytest.mark.slow
def test_peer_implaneia_binary_gives_a_companion(oifits_dir, tmp_path):
    """The simulated binary's closure phases are fit by one companion (chi2_nu < 1).

    Its V2 disagree with its own closure phases (no binary fits both: chi2 ~ 7000 for 21
    V2), so closure phases alone are used, as a user would after seeing the V2 residuals.
    """
    out = tmp_path / "out"
    code = run(
        [
            str(oifits_dir / "implaneia_sim_binary_F430M.oifits"),
            "--out",
            str(out),
            "--observables",
            "phase",
            "--no-hmc",
        ]
    )
    assert code == 0
    doc = json.loads((out / "companions.json").read_text())
    assert len(doc["companions"]) == 1
    companion = doc["companions"][0]
    assert companion["detection_sigma"] > 50
    assert 0.5 < companion["dmag"]["F430M"] < 1.5  # a near-equal binary (flux ratio ~0.4)


@pytest.mark.slow
def test_peer_nuhor_null_and_injection(oifits_dir, tmp_path):
    nuhor = oifits_dir / "NuHor_F480M.oifits"
    code = run([str(nuhor), "--out", str(tmp_path / "null"), "--no-hmc"])
    assert code == 0
    doc = json.loads((tmp_path / "null" / "companions.json").read_text())
    assert doc["companions"] == []
    assert max(doc["search"]["max_joint_sigma_per_iteration"]) < 5.0

    # The peer test: a companion at dRA=250, dDec=150 mas, flux ratio 5e-4, in data with
    # Nu Hor's uv coverage and errors (closure-phase noise correlated through baselines).
    injected = write_sim_oifits(
        tmp_path / "nuhor_injected.oifits",
        np.random.default_rng(1),
        (250.0, 150.0, 5e-4),
        template=nuhor,
    )
    code = run([str(injected), "--out", str(tmp_path / "inj"), "--no-hmc", "--rmax-mas", "400"])
    assert code == 0
    doc = json.loads((tmp_path / "inj" / "companions.json").read_text())
    (companion,) = doc["companions"]
    within_2_sigma(companion, 250.0, 150.0, {"F480M": -2.5 * np.log10(5e-4)})


ABDOR_CALVIS = Path(os.environ.get("AMIGO_ABDOR_CALVIS", SHARED_DATA / "calvis" / "com1093"))


@pytest.mark.slow
def test_ab_dor_c_from_the_fitter(tmp_path):
    """Real data end to end with issue 4: AB Dor C (paper: 328.85 mas; WCS PA 280.5 deg)."""
    files = sorted(ABDOR_CALVIS.glob("AB-DOR_*_calvis.fits")) if ABDOR_CALVIS.is_dir() else []
    if len(files) < 3:
        pytest.skip(
            f"AB Dor calvis files from `amigo fit` not found in {ABDOR_CALVIS} "
            "(set AMIGO_ABDOR_CALVIS to the folder `amigo fit` wrote)"
        )
    out = tmp_path / "out"
    assert run([*map(str, files), "--out", str(out)]) == 0
    doc = json.loads((out / "companions.json").read_text())
    companion = doc["companions"][0]
    assert abs(companion["sep_mas"] - 328.85) < 3.0
    assert abs((companion["pa_deg"] - 280.5 + 180) % 360 - 180) < 0.7
    for f, paper in {"F380M": 4.313, "F430M": 4.354, "F480M": 4.381}.items():
        assert abs(companion["dmag"][f] - paper) < 0.15


def test_a_file_twice_or_two_targets_are_refused(tmp_path, capsys):
    """A calvis file given twice would count its observables twice (a 3.6-sigma candidate
    read as 5.1); calvis files of two targets are two searches. Each is one line naming
    the file, exit 2, nothing written."""
    rng = np.random.default_rng(3)
    one = write_sim_calvis(tmp_path / "a_F480M_calvis.fits", "F480M", [], rng)
    other = write_sim_calvis(tmp_path / "b_F430M_calvis.fits", "F430M", [], rng, target="OTHER")
    out = tmp_path / "out"
    assert run([str(one), str(one), "--out", str(out)]) == 2
    assert "a_F480M_calvis.fits: is given twice" in capsys.readouterr().err
    assert run([str(one), str(other), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "b_F430M_calvis.fits: is of target 'OTHER'" in err and "one target at a time" in err
    assert len(err.splitlines()) == 1 and not out.exists()


def test_products_of_one_science_exposure_are_refused_together(tmp_path, capsys):
    """A fit's calvis and OIFITS files, or the calvis files of two fits of one exposure
    (against two calibrators), hold the same photons: searched together their information
    would count twice. Refused (one line naming the file and the exposure, exit 2,
    nothing written) where the files name their science exposures, as amigo's do."""
    rng = np.random.default_rng(5)
    one = write_sim_calvis(tmp_path / "a_F480M_calvis.fits", "F480M", [], rng)
    # The same exposure calibrated against another star: other DISCOs, the same photons.
    again = write_sim_calvis(tmp_path / "b_F480M_calvis.fits", "F480M", [], rng)
    out = tmp_path / "out"
    assert run([str(one), str(again), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "b_F480M_calvis.fits: was made from the science exposure jw_sim_F480M_cal.fits," in err
    assert "count twice" in err and len(err.splitlines()) == 1 and not out.exists()

    # the same exposure's slopes: another product of it
    oifits = write_point_source_oifits(
        tmp_path / "a_F480M.oifits", science_files=["jw_sim_F480M_calslope.fits"]
    )
    assert run([str(one), str(oifits), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "a_F480M.oifits: was made from the science exposure jw_sim_F480M_calslope.fits" in err
    assert not out.exists()
    # A damaged count of science files is the reader's to report (one line, exit 2).
    from astropy.io import fits

    fits.setval(again, "NSCI", value="abc")
    assert run([str(again), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "b_F480M_calvis.fits: NSCI is 'abc'" in err and len(err.splitlines()) == 1


def test_an_unknown_sampler_device_is_refused_before_the_search(tmp_path, capsys, monkeypatch):
    """``AMIGO_SAMPLER_DEVICE`` is read only where NUTS runs: a typo is found before the
    grid search, not after it (one line, exit 2, nothing written)."""
    one = write_sim_calvis(tmp_path / "a_F480M_calvis.fits", "F480M", [], np.random.default_rng(1))
    monkeypatch.setenv("AMIGO_SAMPLER_DEVICE", "gpu")
    out = tmp_path / "out"
    assert run([str(one), "--out", str(out), "--no-hmc"]) == 2
    err = capsys.readouterr().err.strip()
    assert "AMIGO_SAMPLER_DEVICE is 'gpu': expected 'default' or 'host'" in err
    assert len(err.splitlines()) == 1 and not out.exists()
