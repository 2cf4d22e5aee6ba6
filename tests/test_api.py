"""The Python API (amigo.open, process, fit, detect, simulate, run, train: amigo.pipeline), as a
notebook user calls it; the commands are thin layers over it (tests/test_cli_*)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import amigo
from test_fuzz_inputs import make_seeds


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    return make_seeds(tmp_path_factory.mktemp("seeds"))


def test_import_amigo_is_cheap_and_exposes_the_api():
    """``import amigo`` loads neither JAX nor the pipeline; the API names resolve on use."""
    code = (
        "import sys, amigo; assert 'jax' not in sys.modules, 'jax'; "
        "assert 'amigo.pipeline' not in sys.modules; f = amigo.fit; "
        "print(f.__module__, sorted(n for n in amigo.API))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split()[0].startswith("amigo.pipeline")
    with pytest.raises(AttributeError):
        amigo.no_such_function  # noqa: B018


def test_open_reads_every_kind_by_its_contents(seeds, tmp_path):
    from amigo.io.calslope import CalSlope
    from amigo.io.calvis import CalVis
    from amigo.io.jwst import Exposure
    from amigo.io.oifits import OIFits

    expected = {
        "uncal": Exposure,
        "cal": Exposure,
        "calints": Exposure,
        "calslope": CalSlope,
        "calvis": CalVis,
        "oifits": OIFits,
    }
    for kind, cls in expected.items():
        opened = amigo.open(seeds[kind])
        assert isinstance(opened, cls), kind
    exposure = amigo.open(seeds["cal"])
    assert exposure.meta.filter == "F430M" and exposure.data.shape == (80, 80)
    # by contents, not by name: a calvis file renamed still opens as one
    renamed = tmp_path / "renamed.fits"
    renamed.write_bytes(seeds["calvis"].read_bytes())
    assert isinstance(amigo.open(renamed), CalVis)
    text = tmp_path / "notes_cal.fits"
    text.write_text("not a FITS file")
    with pytest.raises(amigo.InputError, match=r"notes_cal\.fits"):
        amigo.open(text)


def test_process_reports_each_file_and_keeps_complete_products(seeds, tmp_path, capsys):
    bad = tmp_path / "bad_uncal.fits"
    whole = seeds["uncal"].read_bytes()
    bad.write_bytes(whole[: len(whole) - 20000])  # a truncated download
    out = tmp_path / "out"
    result = amigo.process([seeds["uncal"], bad], out)
    assert [p.name for p in result.written] == ["jw1_calslope.fits"]
    assert list(result.failed) == [bad] and "truncated" in result.failed[bad]
    again = amigo.process([seeds["uncal"]], out)
    assert again.written == [] and again.calslope == [out / "jw1_calslope.fits"]
    assert "up to date" in capsys.readouterr().out
    assert isinstance(amigo.open(again.calslope[0]), type(amigo.open(seeds["calslope"])))


def test_simulate_names_its_files(tmp_path):
    written = amigo.simulate("demo", tmp_path / "raw", only=["jw01093015001"])
    assert [Path(item.uncal).name for item in written] == [
        "jw01093015001_03102_00001_nis_uncal.fits"
    ]
    for item in written:
        assert Path(item.uncal).is_file() and Path(item.truth).is_file()
    with pytest.raises(amigo.InputError, match="matches no exposure"):
        amigo.simulate("demo", tmp_path / "raw", only=["nothing"])


@pytest.mark.slow
def test_fit_and_detect_return_what_they_wrote(tmp_path):
    """A single-filter fit of two simulated level-2 images, then a search: the results
    hold the files, the summary and the figures; the same call again keeps the products
    and still draws the residuals (from the saved figures)."""
    from matplotlib.figure import Figure

    from amigo.model.image import Instrument, save_instrument
    from jwst_files import nominal_star, write_level2

    model = tmp_path / "nominal.eqx"
    save_instrument(Instrument.nominal(n_wavelengths=3), model)
    image = nominal_star("F480M")
    error = np.sqrt(np.maximum(image, 0.0) / 80.0 + 4.0)
    rng = np.random.default_rng(2)
    files = {
        role: write_level2(
            tmp_path / f"{role}_cal.fits",
            image + error * rng.standard_normal(image.shape),
            error,
            overrides={"FILTER": "F480M", "TARGPROP": f"STAR-{role}", "OBSERVTN": obs},
        )
        for role, obs in (("sci", "001"), ("cal", "002"))
    }
    out = tmp_path / "out"
    args = dict(model=model, knots=27, knot_spacing=0.5)
    fitted = amigo.fit([files["sci"]], [files["cal"]], out, **args)
    assert fitted.status == 0
    assert fitted.calvis == [out / "STAR-sci_F480M_calvis.fits"]
    assert fitted.oifits == [out / "STAR-sci_F480M.oifits"]
    assert set(fitted.products) == {"F480M"}
    assert [e["status"] for e in fitted.summary["exposures"]] == ["ok", "ok"]
    for record in fitted.summary["exposures"]:
        assert record["zscore_std"] == pytest.approx(1.0, abs=0.1)
    figures = fitted.plot_residuals()
    assert len(figures) == 2 and all(isinstance(f, Figure) for f in figures)
    assert len(fitted.plot_residuals("cal_cal.fits")) == 1
    with pytest.raises(amigo.InputError, match="no fitted exposure"):
        fitted.plot_residuals("other_cal.fits")
    kept = amigo.fit([files["sci"]], [files["cal"]], out, **args)
    assert kept.products == {} and kept.calvis == fitted.calvis
    assert len(kept.plot_residuals()) == 2  # the figures that the first call saved

    found = amigo.detect(fitted.calvis, out, hmc=False, rmax_mas=300.0)
    assert found.result is not None and found.companions == []
    assert found.document["inputs"] == ["STAR-sci_F480M_calvis.fits"]
    again = amigo.detect(fitted.calvis, out, hmc=False, rmax_mas=300.0)
    assert again.result is None and again.document == found.document


def test_train_refuses_bad_inputs_before_training(seeds, tmp_path):
    """``amigo.train`` checks its inputs in seconds and raises the one-line InputError:
    the steps without a model to keep, stages that do not add up, a file that is not
    training data, and level-2 images mixed with calslope files."""
    out = tmp_path / "model.npz"
    with pytest.raises(amigo.InputError, match="0 needs --init"):
        amigo.train([seeds["calslope"]], out, steps=0)
    with pytest.raises(amigo.InputError, match="summing to --steps"):
        amigo.train([seeds["calslope"]], out, steps=10, stage_steps=(3, 3))
    with pytest.raises(amigo.InputError) as caught:
        amigo.train([seeds["calvis"]], out)
    assert str(seeds["calvis"]) in str(caught.value)
    with pytest.raises(amigo.InputError, match="cannot be mixed"):
        amigo.train([seeds["calslope"], seeds["cal"]], out)
    assert not out.exists()
