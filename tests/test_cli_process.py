"""``amigo process`` through the command line, on uncal files written here with astropy."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from amigo.io.calslope import read_calslope
from ramp_sim import simulate, write_uncal

SRC = str(Path(__file__).resolve().parents[1] / "src")


def run_amigo(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": SRC, "JAX_PLATFORMS": "cpu"}
    env.pop("AMIGO_DEBUG", None)
    return subprocess.run(
        [sys.executable, "-m", "amigo", *args], capture_output=True, text=True, env=env, check=False
    )


@pytest.fixture(scope="module")
def good_raw() -> np.ndarray:
    rng = np.random.default_rng(20)
    flux = np.full((80, 80), 40.0)
    flux[30:50, 30:50] = 800.0
    return simulate(rng, 6, 3, flux, cosmic_rate=0.01).raw


def test_processes_a_good_file(tmp_path, good_raw):
    uncal = write_uncal(tmp_path / "jw01093012001_03102_00001_nis_uncal.fits", good_raw)
    before = uncal.read_bytes()
    result = run_amigo("process", str(uncal), "--out", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr
    out = tmp_path / "out" / "jw01093012001_03102_00001_nis_calslope.fits"
    product = read_calslope(out)
    assert product.slope_dn.shape == (2, 80, 80)
    assert product.adc_corrected and product.nsigma == 3.0
    assert np.all(product.badpix[:4])  # reference rows
    bright = product.slope_dn[:, 35:45, 35:45]
    assert abs(np.median(bright) - 800.0) < 10.0
    assert uncal.read_bytes() == before  # the input is never modified
    assert "Traceback" not in result.stderr


def test_options_are_recorded(tmp_path, good_raw):
    uncal = write_uncal(tmp_path / "a_uncal.fits", good_raw)
    result = run_amigo("process", str(uncal), "--out", str(tmp_path), "--sigma", "4", "--no-adc")
    assert result.returncode == 0, result.stderr
    head = fits.getheader(tmp_path / "a_calslope.fits")
    assert head["NSIGCLIP"] == 4.0 and head["ADC_CORR"] is False


def _bad_inputs(tmp_path: Path, good_raw: np.ndarray) -> dict[str, Path]:
    bad = {}
    truncated = write_uncal(tmp_path / "truncated_uncal.fits", good_raw)
    data = truncated.read_bytes()
    truncated.write_bytes(data[: len(data) - 20000])
    bad["truncated"] = truncated
    # (one group per integration is processed since 2026-11-26: its read is the measurement)
    bad["no_groups"] = write_uncal(tmp_path / "nogroups_uncal.fits", good_raw, NGROUPS=0)
    bad["saturated"] = write_uncal(
        tmp_path / "saturated_uncal.fits", np.full(good_raw.shape, 65535.0)
    )
    bad["instrument"] = write_uncal(tmp_path / "nircam_uncal.fits", good_raw, INSTRUME="NIRCAM")
    return bad


def test_bad_inputs_fail_alone_and_the_others_are_processed(tmp_path, good_raw):
    bad = _bad_inputs(tmp_path, good_raw)
    good = write_uncal(tmp_path / "good_uncal.fits", good_raw)
    out = tmp_path / "out"
    result = run_amigo("process", *map(str, bad.values()), str(good), "--out", str(out))
    assert result.returncode == 2
    assert (out / "good_calslope.fits").is_file()
    assert sorted(p.name for p in out.iterdir()) == ["good_calslope.fits"]
    errors = [line for line in result.stderr.splitlines() if line.startswith("amigo: error:")]
    assert len(errors) == len(bad)
    for path, line in zip(bad.values(), errors, strict=True):
        assert str(path) in line
    assert "Traceback" not in result.stderr
    expected = {
        "truncated": "truncated",
        "no_groups": "NGROUPS is 0",
        "saturated": "saturated",
        "instrument": "NIRCAM",
    }
    for (name, word), line in zip(expected.items(), errors, strict=True):
        assert word in line, (name, line)


def test_bad_input_alone_exits_2(tmp_path, good_raw):
    path = write_uncal(tmp_path / "x_uncal.fits", good_raw, INSTRUME="MIRI")
    result = run_amigo("process", str(path), "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and "MIRI" in lines[0]  # one line
    assert not (tmp_path / "out" / "x_calslope.fits").exists()


def test_mirage_file_processes(tmp_path, mirage_uncal):
    result = run_amigo("process", str(mirage_uncal), "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    product = read_calslope(tmp_path / "jw00793001001_01101_00001_nis_calslope.fits")
    assert product.slope_dn.shape == (5, 80, 80)
    with fits.open(mirage_uncal) as hdul:
        sci_header = hdul["SCI"].header
        raw = hdul["SCI"].data.astype(float)
    assert product.slope_header["ROLL_REF"] == sci_header["ROLL_REF"]
    # Pixels kept in every integration: the slope is the plain mean of the ADC-corrected
    # differences (an independent recomputation from the file).
    corrected = raw - 2.0 * np.sin(2.0 * np.pi * raw / 1024.0)
    full = np.all(product.slope_support == raw.shape[0], axis=0)
    assert full.sum() > 1000
    expected = np.diff(corrected, axis=1).mean(axis=0)
    np.testing.assert_allclose(product.slope_dn[:, full], expected[:, full], atol=1e-3)
