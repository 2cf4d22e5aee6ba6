"""An interrupted ``amigo process`` leaves complete products or none under their final
names; SIGTERM cleans up and says so in one line; a re-run processes only what is missing
and ends with the products of an uninterrupted run (docs/reliability.md)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cli_runs import amigo_child
from jwst_files import write_uncal

NFILES = 4


@pytest.fixture(scope="module")
def ramps(tmp_path_factory) -> list[Path]:
    """Raw ramps big enough (~1 s each on 2 cores) to be caught half way."""
    folder = tmp_path_factory.mktemp("raw")
    rng = np.random.default_rng(5)
    y, x = np.mgrid[:80, :80]
    rate = 800.0 * np.exp(-((x - 40) ** 2 + (y - 40) ** 2) / 8.0) + 3.0
    paths = []
    for k in range(NFILES):
        counts = 10000.0 + np.cumsum(rng.poisson(np.broadcast_to(rate, (120, 5, 80, 80))), axis=1)
        paths.append(write_uncal(folder / f"jw0{k}_uncal.fits", np.minimum(counts, 65535)))
    return paths


def _wait_for_products(out: Path, count: int, timeout: float = 120.0) -> None:
    start = time.monotonic()
    while len(list(out.glob("*_calslope.fits"))) < count:
        assert time.monotonic() - start < timeout, "no product appeared"
        time.sleep(0.05)


def _arrays(path: Path) -> dict[str, np.ndarray]:
    from amigo.io.calslope import read_calslope

    product = read_calslope(path)
    return {
        name: getattr(product, name)
        for name in ("slope_dn", "slope_cov_dn2", "ramp_dn", "ramp_cov_dn2", "badpix")
    }


@pytest.mark.slow
@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM])
def test_a_killed_process_run_resumes_to_the_same_products(how, ramps, tmp_path):
    from amigo.io.calslope import read_calslope

    reference = tmp_path / "reference"
    done = subprocess.run(
        [sys.executable, "-m", "amigo", "process", *map(str, ramps), "--out", str(reference)],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr

    out = tmp_path / "out"
    out.mkdir()
    job = amigo_child("process", *ramps, "--out", out)
    _wait_for_products(out, 1)
    job.send_signal(how)
    _, stderr = job.communicate(timeout=60)
    products = sorted(out.glob("*_calslope.fits"))
    assert 1 <= len(products) < NFILES, "the kill came too late to test anything"
    for product in products:  # complete and valid, never half written
        read_calslope(product)
    if how == signal.SIGTERM:
        assert job.returncode == 130 and stderr.strip().splitlines()[-1] == "amigo: interrupted"
        assert sorted(out.iterdir()) == products, "a temporary file was left"

    rerun = subprocess.run(
        [sys.executable, "-m", "amigo", "process", *map(str, ramps), "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert rerun.returncode == 0, rerun.stderr
    assert rerun.stdout.count("up to date, skipped") == len(products)
    finals = sorted(out.glob("*_calslope.fits"))
    assert [p.name for p in finals] == sorted(p.name for p in reference.iterdir())
    for path in finals:
        got, want = _arrays(path), _arrays(reference / path.name)
        for name in want:
            np.testing.assert_array_equal(got[name], want[name], err_msg=f"{path.name} {name}")
    forced = subprocess.run(
        [sys.executable, "-m", "amigo", "process", ramps[0], "--out", str(out), "--force"],
        capture_output=True,
        text=True,
    )
    assert forced.returncode == 0 and "skipped" not in forced.stdout
