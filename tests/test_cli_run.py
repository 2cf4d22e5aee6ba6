"""`amigo run` input handling (fast: fails before any fit) and its help."""

from __future__ import annotations

from click.testing import CliRunner

from amigo.cli import cli, main


def _run(args) -> int:
    try:
        main(args)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    return 0


def test_bad_input_is_named_and_exits_2(tmp_path, capsys):
    text = tmp_path / "notes_uncal.fits"
    text.write_text("not a FITS file\n")
    other = tmp_path / "other_uncal.fits"
    other.write_text("not a FITS file either\n")
    out = tmp_path / "out"
    assert _run(["run", "--sci", str(text), "--cal", str(other), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "notes_uncal.fits" in err and "Traceback" not in err
    assert text.read_text() == "not a FITS file\n"  # inputs untouched
    assert _run(["run", "--sci", str(text), "--cal", str(text), "--out", str(out)]) == 2
    assert "both as --sci and --cal" in capsys.readouterr().err


def test_help_lists_run_and_demo():
    result = CliRunner().invoke(cli, ["--help"])
    assert "run" in result.output and "demo" in result.output
    result = CliRunner().invoke(cli, ["run", "--help"])
    for option in ("--sci", "--cal", "--out", "--model", "--detector", "--no-hmc", "--step-mas"):
        assert option in result.output


def test_science_files_of_two_targets_are_refused_before_any_work(tmp_path, capsys):
    """``amigo run`` searches one star: science images of two targets (whose calvis files
    ``amigo detect`` would refuse to search together) are one line and exit 2 before
    anything is processed or fitted."""
    import numpy as np

    from jwst_files import write_level2

    one = write_level2(tmp_path / "a_cal.fits", np.ones((80, 80)), overrides={"TARGPROP": "A"})
    two = write_level2(tmp_path / "b_cal.fits", np.ones((80, 80)), overrides={"TARGPROP": "B"})
    cal = write_level2(tmp_path / "c_cal.fits", np.ones((80, 80)), overrides={"TARGPROP": "C"})
    out = tmp_path / "out"
    assert _run(["run", "--sci", str(one), str(two), "--cal", str(cal), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "b_cal.fits: is of target 'B', a_cal.fits of 'A'" in err
    assert len(err.splitlines()) == 1 and not out.exists()


def test_a_grid_step_beyond_the_radius_is_refused_before_any_work(tmp_path, capsys):
    """``--step-mas`` is the search's (``amigo detect``'s), checked with the radius before
    the fit: one line, exit 2, nothing written."""
    import numpy as np

    from jwst_files import write_level2

    sci = write_level2(tmp_path / "a_cal.fits", np.ones((80, 80)), overrides={"TARGPROP": "A"})
    cal = write_level2(tmp_path / "c_cal.fits", np.ones((80, 80)), overrides={"TARGPROP": "C"})
    out = tmp_path / "out"
    args = ["run", "--sci", str(sci), "--cal", str(cal), "--out", str(out), "--rmax-mas", "200"]
    assert _run([*args, "--step-mas", "250"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--step-mas (250.0) must be a positive step smaller than --rmax-mas (200.0)" in err
    assert len(err.splitlines()) == 1 and not out.exists()


def test_the_console_script_leaves_with_the_commands_status_and_output():
    """``python -m amigo`` (and the console script) end the process without the
    interpreter's teardown (:func:`amigo.cli.console`): what the command printed still
    arrives, to a pipe, and the status is the command's."""
    import subprocess
    import sys

    from cli_runs import amigo_child

    child = amigo_child("--version")
    out, err = child.communicate(timeout=120)
    assert child.returncode == 0 and "amigo" in out, (out, err)
    child = amigo_child("info", "no_such_file_cal.fits")
    out, err = child.communicate(timeout=120)
    assert child.returncode == 2 and "no_such_file_cal.fits" in err, (out, err)
    # Threads still running and exit handlers run first, as at a normal exit.
    code = (
        "import atexit, sys, threading, time\n"
        "from amigo.cli import console\n"
        "threading.Thread(target=lambda: (time.sleep(0.5), print('thread done'))).start()\n"
        "atexit.register(lambda: print('handler ran'))\n"
        "sys.argv = ['amigo', '--version']\n"
        "console()\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[-2:] == ["thread done", "handler ran"] and "amigo" in lines[0], lines
