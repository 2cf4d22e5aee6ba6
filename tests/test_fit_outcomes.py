"""Numerical failures are results, not crashes, an interrupted fit resumes to the
products of an uninterrupted one, and a fit that did not converge is written, flagged and
named per exposure (issues 26 and 22, docs/reliability.md) (slow: real fits of two
filters of small simulated level-2 images).

One sequence of runs on the same inputs, each building on the last:

1. a fit whose F430M solver fails (injected: a singular matrix, what numpy raises),
   whose F480M has a calibrator with every pixel flagged and whose F380M has a science
   exposure but no calibrator: F480M is fitted without that calibrator, F430M and F380M
   are reported failed, exit status 3, nothing for them written (the
   later stages, the latent Hessians, covariances and kernel, turn the same errors into
   the same record through the same ``amigo.errors.numerical``);
2. the same command again: F480M is kept (its products are complete and record the same
   inputs), F430M is fitted;
3. a fit of the same exposures killed (SIGKILL) after its first filter and run again:
   its products are byte for byte those of runs 1 and 2;
4. one filter stopped after one solver iteration: written, flagged
   (``CONVERGD = F``), each unconverged exposure named.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cli_runs import amigo_status
from jwst_files import nominal_star, write_level2

pytestmark = pytest.mark.slow

FILTERS = ("F430M", "F480M")  # fitted in this order (sorted)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """Level-2 images of a point source through amigo's nominal instrument (3
    wavelengths), with photon and read noise; and a calibrator with every pixel flagged."""
    from amigo.model.image import Instrument, save_instrument

    folder = tmp_path_factory.mktemp("in")
    instrument = Instrument.nominal(n_wavelengths=3)
    paths = {"model": folder / "nominal.eqx"}
    save_instrument(instrument, paths["model"])
    rng = np.random.default_rng(3)
    for filter_name in FILTERS:
        image = nominal_star(filter_name)
        error = np.sqrt(np.maximum(image, 0.0) / 80.0 + 4.0)
        for role, observation in (("sci", "001"), ("cal", "002")):
            name = f"{role}_{filter_name}"
            paths[name] = write_level2(
                folder / f"{name}_cal.fits",
                image + error * rng.standard_normal(image.shape),
                error,
                overrides={
                    "FILTER": filter_name,
                    "TARGPROP": f"STAR-{role}",
                    "OBSERVTN": observation,
                },
            )
    paths["blue"] = write_level2(  # never fitted: no calibrator in its filter
        folder / "sci_F380M_cal.fits",
        image,
        error,
        overrides={"FILTER": "F380M", "TARGPROP": "STAR-sci", "OBSERVTN": "001"},
    )
    paths["flagged"] = write_level2(
        folder / "flagged_F480M_cal.fits",
        image,
        error,
        dq=np.ones(image.shape, np.uint32),  # DO_NOT_USE everywhere
        overrides={"FILTER": "F480M", "TARGPROP": "STAR-cal", "OBSERVTN": "003"},
    )
    return paths


def _args(inputs: dict[str, Path], out: Path, flagged: bool, blue: bool = False) -> list[str]:
    cal = [inputs[f"cal_{f}"] for f in FILTERS] + ([inputs["flagged"]] if flagged else [])
    sci = [inputs[f"sci_{f}"] for f in FILTERS] + ([inputs["blue"]] if blue else [])
    return [
        "fit",
        "--sci",
        *map(str, sci),
        "--cal",
        *map(str, cal),
        "--out",
        str(out),
        "--model",
        str(inputs["model"]),
        "--knots",
        "27",
        "--knot-spacing",
        "0.5",
    ]


def _products(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.glob("*_calvis.fits"))} | {
        p.name: p.read_bytes() for p in sorted(out.glob("*.oifits"))
    }


def test_failures_are_reported_per_filter_and_runs_resume(inputs, tmp_path, monkeypatch, capsys):
    from amigo.fitting.filter_fit import FilterFit

    out = tmp_path / "out"
    real = FilterFit.fit
    # The OIFITS files' creation DATE is fixed (the child process inherits it): a run
    # resumed after midnight must still write the uninterrupted run's bytes.
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")

    def singular_in_f430m(fit, *args, **kwargs):
        if fit.setup.name == "F430M":  # before any work: this filter's fit is not needed
            raise np.linalg.LinAlgError("Singular matrix")
        return real(fit, *args, **kwargs)

    # 1. F430M fails, F480M is fitted without its calibrator that has no usable pixel
    monkeypatch.setattr(FilterFit, "fit", singular_in_f430m)
    assert amigo_status(_args(inputs, out, flagged=True, blue=True)) == 3
    err = capsys.readouterr().err
    assert "F380M: no calibrator exposure: its science exposures are not fitted" in err
    assert "flagged_F480M_cal.fits: only 0 usable pixels" in err
    assert "F430M: failed (fit: LinAlgError: Singular matrix)" in err
    assert "Traceback" not in err
    summary = json.loads((out / "fit_summary.json").read_text())
    f430, f480 = summary["filters"]["F430M"], summary["filters"]["F480M"]
    assert f430["status"] == "failed" and f430["products"] == []
    assert "Singular matrix" in f430["problem"]
    assert f480["status"] == "ok"
    assert summary["filters"]["F380M"]["status"] == "failed"
    assert f480["products"] == ["STAR-sci_F480M_calvis.fits", "STAR-sci_F480M.oifits"]
    status = {e["file"]: e["status"] for e in summary["exposures"]}
    assert status == {
        "flagged_F480M_cal.fits": "excluded",
        "sci_F380M_cal.fits": "failed",
        "sci_F430M_cal.fits": "failed",
        "cal_F430M_cal.fits": "failed",
        "sci_F480M_cal.fits": "ok",
        "cal_F480M_cal.fits": "ok",
    }
    # Every record has every key (docs/interfaces.md): an exposure without a fit its
    # numbers null, the fitted geometry's included.
    contract = {"file", "role", "target", "filter", "npix", "chi2", "dof", "zscore_std",
                "converged", "iterations", "seconds", "rotation_deg", "rotation_deg_err",
                "anisotropy", "anisotropy_err", "skew_deg", "skew_deg_err", "scale",
                "scale_err", "jitter_mas", "jitter_mas_err"}  # fmt: skip
    for record in summary["exposures"]:
        assert contract <= set(record), (record["file"], contract - set(record))
    assert sorted(_products(out)) == ["STAR-sci_F480M.oifits", "STAR-sci_F480M_calvis.fits"]
    first = _products(out)

    # 2. the same command: F480M kept as it is, F430M fitted
    monkeypatch.setattr(FilterFit, "fit", real)
    assert (
        amigo_status(_args(inputs, out, flagged=True)) == 3
    )  # the flagged calibrator is still out
    err = capsys.readouterr().err
    assert "F480M: products up to date" in err and "F430M: products up to date" not in err
    summary = json.loads((out / "fit_summary.json").read_text())
    assert {f: r["status"] for f, r in summary["filters"].items()} == {
        "F430M": "ok",
        "F480M": "ok",
    }
    uninterrupted = _products(out)
    assert {k: uninterrupted[k] for k in first} == first
    assert len(uninterrupted) == 4

    # 2b. a new reading of the same inputs (READING_REVISION raised): nothing is kept,
    # every filter is fitted again (each fit stopped at its start: which filters were
    # attempted is the point, not their products, and two fits were a minute of the suite)
    import amigo.pipeline._fit as fit_module

    revision = fit_module.READING_REVISION
    monkeypatch.setattr(fit_module, "READING_REVISION", revision + 1)
    attempted = []

    def stopped_at_start(fit, *args, **kwargs):
        attempted.append(fit.setup.name)
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(FilterFit, "fit", stopped_at_start)
    assert amigo_status(_args(inputs, out, flagged=True)) == 4
    assert "products up to date" not in capsys.readouterr().err
    assert sorted(attempted) == ["F430M", "F480M"]
    monkeypatch.setattr(fit_module, "READING_REVISION", revision)
    monkeypatch.setattr(FilterFit, "fit", real)

    # 3. killed after its first filter, then run again: the same bytes. Without the
    # flagged calibrator the fit of each filter is the same (same exposures fitted).
    resumed = tmp_path / "resumed"
    process = subprocess.Popen(
        [sys.executable, "-m", "amigo", *_args(inputs, resumed, flagged=False)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    start = time.monotonic()
    try:
        while '"F430M"' not in _text(resumed / "fit_summary.json"):
            assert process.poll() is None, "the fit ended before it could be interrupted"
            assert time.monotonic() - start < 300, "the first filter did not finish"
            time.sleep(0.05)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    partial = _products(resumed)
    assert sorted(partial) == ["STAR-sci_F430M.oifits", "STAR-sci_F430M_calvis.fits"]
    assert amigo_status(_args(inputs, resumed, flagged=False)) == 0
    assert "F430M: products up to date" in capsys.readouterr().err
    assert _products(resumed) == uninterrupted

    # 4. a fit stopped before it converged (its Levenberg-Marquardt solver given one
    # iteration): products written and flagged, and each exposure that did not converge
    # named on the terminal and in fit_summary.json
    from amigo.fitting.filter_fit import FitConfig

    def one_iteration(fit, config=None, *args, **kwargs):
        config = FitConfig() if config is None else config
        newton = dataclasses.replace(config.newton, max_iterations=1)
        return real(fit, dataclasses.replace(config, newton=newton), *args, **kwargs)

    monkeypatch.setattr(FilterFit, "fit", one_iteration)
    stopped = tmp_path / "stopped"
    args = ["fit", "--sci", str(inputs["sci_F480M"]), "--cal", str(inputs["cal_F480M"])]
    args += ["--out", str(stopped), "--model", str(inputs["model"])]
    args += ["--knots", "27", "--knot-spacing", "0.5"]
    assert amigo_status(args) == 0  # written: a flagged product is still a product
    err = capsys.readouterr().err
    summary = json.loads((stopped / "fit_summary.json").read_text())
    assert summary["filters"]["F480M"]["status"] == "unconverged"
    assert "the fit did not converge in F480M" in err
    unconverged = [e for e in summary["exposures"] if not e["converged"]]
    assert unconverged and all(e["status"] == "unconverged" for e in unconverged)
    for e in unconverged:
        named = f"F480M: {e['file']} ({e['role']}) did not converge (iterations: {e['iterations']}"
        assert named in err
    from astropy.io import fits

    with fits.open(stopped / "STAR-sci_F480M_calvis.fits") as hdul:
        assert hdul[0].header["CONVERGD"] is False


def _text(path: Path) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""
