"""``amigo info`` through the command line, as a user runs it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from jwst_files import write_uncal


def run(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "amigo", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,
    )


EXPECTED = {
    # file suffix: (target, filter, groups x ints)
    "12001_03102": ("AB-DOR", "F480M", "5 x 69"),
    "12001_03103": ("AB-DOR", "F430M", "4 x 82"),
    "12001_03104": ("AB-DOR", "F380M", "2 x 160"),
    "12001_03105": ("AB-DOR", "F480M", "13 x 29"),
    "15001_03102": ("HD-37093", "F480M", "12 x 61"),
    "15001_03103": ("HD-37093", "F430M", "9 x 78"),
    "15001_03104": ("HD-37093", "F380M", "4 x 118"),
}


def test_info_on_real_and_mirage_files(com1093_dir, mirage_uncal):
    files = sorted(com1093_dir.glob("*.fits"))
    result = run("info", *files, mirage_uncal)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1 + 8
    assert lines[0].split()[:3] == ["file", "kind", "target"]
    for line in lines[1:8]:
        key = line.split()[0][8:19]
        target, filter_name, groups = EXPECTED[key]
        assert f"  {target}  " in line and f"  {filter_name}  " in line and groups in line
        assert " cal " in line and line.rstrip().endswith("ok")
        pa = float(line.split()[-2])
        assert pa == pytest.approx(172.35 if key.startswith("12") else 172.0, abs=0.05)
    mirage = lines[8]
    assert mirage.split()[1] == "uncal" and "F480M" in mirage and "6 x 5" in mirage
    assert "NIS_IMAGE" in mirage


def test_info_lists_all_files_then_exits_2(tmp_path, com1093_dir):
    text = tmp_path / "readme.txt"
    text.write_text("not fits")
    good = write_uncal(tmp_path / "good_uncal.fits", np.full((2, 3, 80, 80), 1000, np.uint16))
    nircam = write_uncal(
        tmp_path / "nircam_uncal.fits", np.zeros((2, 3, 80, 80), np.uint16), {"INSTRUME": "NIRCAM"}
    )
    truncated = tmp_path / "short_cal.fits"
    source = com1093_dir / "jw01093012001_03102_00001_nis_cal.fits"
    truncated.write_bytes(source.read_bytes()[:50000])
    result = run("info", text, good, nircam, truncated)
    assert result.returncode == 2
    assert len(result.stdout.strip().splitlines()) == 5
    assert "Traceback" not in result.stderr
    errors = result.stderr.strip().splitlines()
    assert len(errors) == 3
    assert str(text) in errors[0] and "not a FITS file" in errors[0]
    assert str(nircam) in errors[1] and "NIRCAM" in errors[1]
    assert str(truncated) in errors[2] and "truncated" in errors[2]


@pytest.mark.parametrize("kind", ["text", "nircam", "truncated"])
def test_single_bad_file_one_line_exit_2(tmp_path, kind):
    path = tmp_path / "bad.fits"
    if kind == "text":
        path.write_text("hello")
    else:
        good = write_uncal(
            tmp_path / "g_uncal.fits",
            np.zeros((2, 3, 80, 80), np.uint16),
            {"INSTRUME": "NIRCAM"} if kind == "nircam" else None,
        )
        data = good.read_bytes()
        path.write_bytes(data if kind == "nircam" else data[: len(data) - 5000])
    result = run("info", path)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and str(path) in result.stderr
    assert "Traceback" not in result.stderr


def test_usage_errors_exit_2():
    """Usage errors are the interface's one line, with the command and where the usage is
    (click alone prints the usage, a hint, a blank line and its message)."""
    for args, words in [
        (("info",), "amigo info: error: Missing argument"),
        (("no-such-command",), "amigo: error: No such command"),
        (("detect", "x_calvis.fits", "--out", "o", "--rmax-mas", "0"), "amigo detect: error:"),
    ]:
        result = run(*args)
        assert result.returncode == 2, args
        assert result.stderr.count("\n") == 1 and result.stderr.startswith(words), result.stderr
        assert "-h: usage" in result.stderr
    bare = run()  # "amigo" alone: its help as click formats it, not an error line
    assert "Commands:" in bare.stdout + bare.stderr and "error" not in bare.stderr
    result = run("--help")
    assert result.returncode == 0 and "info" in result.stdout


def test_inputs_never_modified(tmp_path):
    path = write_uncal(tmp_path / "keep_uncal.fits", np.full((2, 3, 80, 80), 7, np.uint16))
    before = path.read_bytes()
    assert run("info", path).returncode == 0
    assert path.read_bytes() == before


def test_info_says_how_the_archive_processed_a_level2_file(tmp_path):
    """A file in MJy/sr is summarised in DN/s (its PHOTMJSR undone), and one the
    pipeline's charge-migration step ran on says so: what ``amigo fit`` will do with it."""
    from astropy.io import fits

    from jwst_files import write_level2

    yy, xx = np.mgrid[:80, :80]
    rate = 10.0 + 1e4 * np.exp(-((xx - 40.0) ** 2 + (yy - 40.0) ** 2) / 8.0)
    path = write_level2(tmp_path / "mjy_cal.fits", rate * 0.5, overrides={"S_CHGMIG": "COMPLETE"})
    with fits.open(path, mode="update") as hdul:
        hdul["SCI"].header["BUNIT"] = "MJy/sr"
        hdul["SCI"].header["PHOTMJSR"] = 0.5
    result = run("info", path)
    assert result.returncode == 0, result.stderr
    assert "10,010 DN/s" in result.stdout
    assert "MJy/sr, read in DN/s through PHOTMJSR" in result.stdout
    assert "charge-migration step ran (S_CHGMIG)" in result.stdout


def test_steps_are_one_line_each_off_a_terminal(capsys):
    """The interface: off a terminal, one line per step (not a start and an end line)."""
    from amigo.progress import track

    assert list(track(range(3), "process x")) == [0, 1, 2]
    assert capsys.readouterr().err == "process x ...\n"
