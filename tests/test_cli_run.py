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
    for option in ("--sci", "--cal", "--out", "--model", "--detector", "--no-hmc"):
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
