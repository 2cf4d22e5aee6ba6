"""``amigo run --manifest``: many targets on Dask distributed (issue 25, docs/interfaces.md).

Fast: a manifest's mistakes are one line naming the manifest (exit status 2).
Slow: three small simulated targets, run on a local Dask cluster of one worker (the
targets wait for it) and killed after the first, then run again on two workers: the
second run runs only the targets that had not finished, and the two it runs side by side
give the same products as serial runs (every JSON number but wall times, byte for byte):
one through ``amigo run --sci --cal`` on the level-2 files, one through ``amigo fit`` and
``amigo detect``.
Three targets are enough for these properties; each costs ~1 min of the suite's CPU time
(the issue's four-target check runs the same code: `amigo run --manifest`). The first
target, run alone on one worker, is not run serially as well: the serial run is the
suite's most expensive reference, and two workers computing side by side (in processes
that start cold) are where products could differ.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from cli_runs import amigo_child, amigo_status
from jwst_files import nominal_star, write_level2


@pytest.fixture
def files(tmp_path) -> dict[str, Path]:
    folder = tmp_path / "in"
    folder.mkdir()
    paths = {}
    for name in ("a_cal.fits", "b_cal.fits", "c_cal.fits"):
        paths[name] = folder / name
        paths[name].write_bytes(b"")  # existence is all the manifest checks
    return paths


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("[[target]\n", "is not valid TOML"),
        ("[options]\nhmc = false\n", "has no [[target]] table"),
        ('[[target]]\nsci = ["a_cal.fits"]\n', "target 1: cal must be a non-empty list"),
        (
            '[[target]]\nsci = ["a_cal.fits"]\ncal = ["nope_cal.fits"]\n',
            "nope_cal.fits does not exist",
        ),
        (
            '[[target]]\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits"]\nrmax = 3\n',
            "unknown key 'rmax'",
        ),
        (
            '[[target]]\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits"]\nknots = "many"\n',
            "knots must be a int",
        ),
        (
            '[[target]]\nname = "x"\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits"]\n'
            '[[target]]\nname = "x"\nsci = ["c_cal.fits"]\ncal = ["b_cal.fits"]\n',
            "a target named 'x' comes earlier",
        ),
        (
            '[[target]]\nname = "../up"\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits"]\n',
            "must be letters, digits",
        ),
        ("[extra]\n", "unknown table 'extra'"),
        # Values are checked as amigo run's options are, for every target before any runs.
        (
            '[[target]]\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits"]\ndetector = "foo"\n',
            "target a: --detector must be one of full, linear",
        ),
        (
            '[[target]]\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits"]\nknots = 4\n',
            "target a: --knots/--knot-spacing",
        ),
        (
            '[options]\nrmax_mas = -5\n[[target]]\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits"]\n',
            "target a: --rmax-mas must be a finite radius of at least 1",
        ),
        (
            '[options]\nrmax_mas = 300\nstep_mas = 300\n[[target]]\nsci = ["a_cal.fits"]\n'
            'cal = ["b_cal.fits"]\n',
            "target a: --step-mas (300.0) must be a positive step smaller than --rmax-mas",
        ),
        (
            '[[target]]\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits"]\n',
            "target a: ",  # the inputs' levels read from their headers: these are empty
        ),
    ],
)
def test_manifest_mistakes_are_one_line_naming_the_manifest(files, text, problem, capsys):
    manifest = _write(files["a_cal.fits"].parent / "targets.toml", text)
    out = files["a_cal.fits"].parent.parent / "out"
    assert amigo_status(["run", "--manifest", str(manifest), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "targets.toml" in err[0] and problem in err[0], err
    assert "Traceback" not in err[0]
    assert not out.exists()  # nothing started


def test_a_level2_target_under_the_physical_account_is_refused_before_any_runs(tmp_path, capsys):
    """--detector boundary measures its strength in group differences: a level-2 target
    is refused with the others' checks, before the first target runs."""
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("a_cal.fits", "b_cal.fits"):
        write_level2(folder / name, np.ones((80, 80)))
    manifest = _write(
        folder / "targets.toml",
        '[[target]]\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits"]\ndetector = "boundary"\n',
    )
    out = tmp_path / "out"
    assert amigo_status(["run", "--manifest", str(manifest), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "target a" in err[0] and "a_cal.fits" in err[0], err
    assert "--detector boundary needs calslope files" in err[0]
    assert not out.exists()


def test_a_manifest_reads_paths_relative_to_itself_and_merges_options(files):
    from amigo.io.manifest import read_manifest

    manifest = _write(
        files["a_cal.fits"].parent / "targets.toml",
        "[options]\nrmax_mas = 500\nhmc = false\n"
        '[[target]]\nsci = ["a_cal.fits"]\ncal = ["b_cal.fits", "c_cal.fits"]\n'
        '[[target]]\nname = "second"\nsci = "c_cal.fits"\ncal = ["b_cal.fits"]\nhmc = true\n',
    )
    first, second = read_manifest(manifest)
    assert first.name == "a" and second.name == "second"
    assert first.cal == (files["b_cal.fits"].resolve(), files["c_cal.fits"].resolve())
    assert first.options == {"rmax_mas": 500.0, "hmc": False}
    assert second.options == {"rmax_mas": 500.0, "hmc": True}


def test_manifest_and_exposures_exclude_each_other(files, tmp_path, capsys):
    manifest = _write(tmp_path / "m.toml", '[[target]]\nsci = ["x"]\ncal = ["y"]\n')
    args = ["run", "--manifest", str(manifest), "--sci", str(files["a_cal.fits"])]
    assert amigo_status([*args, "--out", str(tmp_path / "o")]) == 2
    assert "--manifest" in capsys.readouterr().err
    assert amigo_status(["run", "--out", str(tmp_path / "o")]) == 2
    assert "--sci" in capsys.readouterr().err
    assert amigo_status(["run", "--sci", "a", "--cal", "b", "--workers", "2", "--out", "o"]) == 2
    assert "only with --manifest" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("cores", "targets", "workers"), [(8, 10, 4), (8, 3, 3), (1, 4, 1), (2, 4, 1), (16, 2, 2)]
)
def test_default_workers_follow_the_cores_the_process_may_use(cores, targets, workers, monkeypatch):
    """One local worker per two of the process's cores (its affinity), one at least, one
    per target at most."""
    from amigo import runtime
    from amigo.pipeline._manifest import default_workers

    monkeypatch.setattr(runtime, "cores", lambda: cores)
    assert default_workers(targets) == workers


def test_the_process_cores_are_its_affinity():
    from amigo import runtime

    expected = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    assert runtime.cores() == (expected or max(1, os.cpu_count() or 1))


# ---------------------------------------------------------------------------- slow
N_TARGETS = 3
#: Small and fast: a 3-wavelength instrument, a coarse uv grid, no NUTS, a short search.
OPTIONS = "[options]\nknots = 27\nknot_spacing = 0.5\nhmc = false\nrmax_mas = 300.0\n"


@pytest.fixture(scope="module")
def program(tmp_path_factory) -> Path:
    """Three science stars (different noise) against one calibrator, F480M level-2 images
    through amigo's nominal instrument; the manifest and the instrument file beside them."""
    from amigo.model.image import Instrument, save_instrument

    folder = tmp_path_factory.mktemp("program")
    save_instrument(Instrument.nominal(n_wavelengths=3), folder / "nominal.eqx")
    rng = np.random.default_rng(11)
    image = nominal_star("F480M")
    error = np.sqrt(np.maximum(image, 0.0) / 80.0 + 4.0)

    def write(name: str, target: str, observation: str) -> str:
        noisy = image + error * rng.standard_normal(image.shape)
        overrides = {"FILTER": "F480M", "TARGPROP": target, "OBSERVTN": observation}
        write_level2(folder / name, noisy, error, overrides=overrides)
        return name

    cal = write("cal_cal.fits", "CALSTAR", "090")
    lines = [OPTIONS, 'model = "nominal.eqx"\n']
    for k in range(N_TARGETS):
        sci = write(f"sci{k}_cal.fits", f"STAR-{k}", f"00{k + 1}")
        lines.append(f'[[target]]\nname = "t{k}"\nsci = ["{sci}"]\ncal = ["{cal}"]\n')
    (folder / "targets.toml").write_text("".join(lines))
    return folder


def _numbers(document, wall=("seconds",)) -> object:
    """The JSON document without its wall times (the only numbers that may differ)."""
    if isinstance(document, dict):
        return {k: _numbers(v) for k, v in document.items() if k not in wall}
    if isinstance(document, list):
        return [_numbers(v) for v in document]
    return document


def _products(folder: Path) -> dict[str, object]:
    names = ("fit_summary.json", "companions.json")
    return {name: _numbers(json.loads((folder / name).read_text())) for name in names}


@pytest.mark.slow
def test_a_manifest_on_two_dask_workers_equals_serial_runs_and_resumes(program, tmp_path):
    out = tmp_path / "dask"
    manifest = program / "targets.toml"
    # On one worker, killed once the first target has finished: the second is half way,
    # the third waits for the worker. (On two workers the second target would be as far
    # as the first when the kill comes: its work, a third of this test's, thrown away.)
    job = amigo_child("run", "--manifest", manifest, "--out", out, "--workers", 1,
                 start_new_session=True)  # fmt: skip
    start = time.monotonic()
    while not list(out.glob("*/target.json")):
        assert job.poll() is None, job.communicate()
        assert time.monotonic() - start < 600, "no target finished"
        time.sleep(0.2)
    os.killpg(job.pid, signal.SIGKILL)  # the client, its scheduler and its workers
    job.communicate()
    finished = {p.parent.name for p in out.glob("*/target.json")}
    assert len(finished) == 1

    # The targets left run side by side on two workers.
    rerun = amigo_child("run", "--manifest", manifest, "--out", out, "--workers", 2)
    stdout, stderr = rerun.communicate(timeout=900)
    assert rerun.returncode == 0, stderr
    summary = json.loads((out / "manifest_summary.json").read_text())
    states = {t["name"]: t["state"] for t in summary["targets"]}
    assert {n for n, s in states.items() if s == "skipped"} == finished
    assert {n for n, s in states.items() if s == "done"} == set(states) - finished
    assert "skipped" in stdout and "t0" in stdout  # the table

    # Serial runs of the targets that ran side by side: the same products.
    model = program / "nominal.eqx"
    options = ["--model", model, "--knots", "27", "--knot-spacing", "0.5"]
    serial = tmp_path / "serial"
    side_by_side = sorted(set(states) - finished)
    assert len(side_by_side) == 2
    for i, name in enumerate(side_by_side):
        k = int(name[1:])
        folder = serial / name
        files = ["--sci", program / f"sci{k}_cal.fits", "--cal", program / "cal_cal.fits"]
        search = ["--no-hmc", "--rmax-mas", "300"]
        if i == 0:
            # amigo run on level-2 files: fit and detect in one process, nothing processed.
            run = ["run", *files, "--out", folder, *options, *search]
            assert amigo_status(list(map(str, run))) == 0
            assert not list(folder.glob("*_calslope.fits"))
        else:
            fit = ["fit", *files, "--out", folder, *options]
            assert amigo_status(list(map(str, fit))) == 0
            calvis = sorted(map(str, folder.glob("*_calvis.fits")))
            assert amigo_status(["detect", *calvis, "--out", str(folder), *search]) == 0
        assert _products(out / name) == _products(folder), name
