"""Time and peak memory of ``amigo process`` on synthetic uncal files of 4 groups.

Usage::

    python benchmarks/process.py [--nints 1000 10000] [--ngroups 4] [--keep DIR]

For each size it writes a synthetic uncal file (80x80, Gaussian photon and read noise,
ADC sinusoid, 1 % cosmic rays), then processes it in a fresh Python process and reports
the wall time of :func:`amigo.processing.ramps.process_file` (reading, both passes, writing) and the
peak resident memory of that process (imports included). Target (issue 7): 10,000
integrations x 4 groups in under 20 s and 1 GB.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.io import fits

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "tests"))


def write_synthetic_uncal(path: Path, nints: int, ngroups: int, seed: int = 0) -> None:
    """Stream a synthetic uncal file to disk, ``chunk`` integrations at a time."""
    from ramp_sim import PRIMARY_KEYWORDS, SCI_KEYWORDS

    rng = np.random.default_rng(seed)
    flux = rng.uniform(10.0, 2000.0, (80, 80))
    bias = rng.uniform(9000.0, 14000.0, (80, 80))
    primary = fits.Header()
    for key, value in {**PRIMARY_KEYWORDS, "NINTS": nints, "NGROUPS": ngroups}.items():
        primary[key] = value
    fits.PrimaryHDU(header=primary).writeto(path, overwrite=True)
    header = fits.Header()
    header["XTENSION"] = "IMAGE"
    header["BITPIX"] = 16
    header["NAXIS"] = 4
    for axis, size in enumerate((80, 80, ngroups, nints), start=1):
        header[f"NAXIS{axis}"] = size
    header["PCOUNT"] = 0
    header["GCOUNT"] = 1
    header["BSCALE"] = 1
    header["BZERO"] = 32768
    header["EXTNAME"] = "SCI"
    for key, value in SCI_KEYWORDS.items():
        header[key] = value
    # Written by hand (header block, big-endian data, padding to 2880 bytes) so that the
    # file never has to fit in memory.
    chunk = 500
    groups = np.arange(ngroups)[None, :, None, None]
    with open(path, "ab") as handle:
        handle.write(header.tostring().encode("ascii"))
        for start in range(0, nints, chunk):
            n = min(chunk, nints - start)
            shape = (n, ngroups, 80, 80)
            photons = rng.normal(flux, np.sqrt(flux / 1.61), shape)
            analog = bias + np.cumsum(photons, axis=1) + rng.normal(0.0, 10.0, shape)
            hit = rng.random((n, 1, 80, 80)) < 0.01
            first = rng.integers(1, ngroups, (n, 1, 80, 80))
            analog += np.where(hit & (groups >= first), 1000.0, 0.0)
            analog += 2.0 * np.sin(2.0 * np.pi * analog / 1024.0)
            raw = np.clip(np.rint(analog), 0, 65535).astype(np.int32) - 32768
            handle.write(raw.astype(">i2").tobytes())
        handle.write(b"\0" * (-(nints * ngroups * 80 * 80 * 2) % 2880))


def child(uncal: Path, out: Path) -> None:
    """Process one file here and print seconds and peak RSS (MB) as one line."""
    from amigo.processing.ramps import process_file

    start = time.perf_counter()
    process_file(uncal, out)
    seconds = time.perf_counter() - start
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kB on Linux
    print(f"{seconds:.3f} {rss_kb / 1024:.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nints", type=int, nargs="+", default=[1000, 10000])
    parser.add_argument("--ngroups", type=int, default=4)
    parser.add_argument("--keep", type=Path, default=None, help="keep the files in this folder")
    parser.add_argument("--child", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(*args.child)
        return

    work = args.keep or Path(tempfile.mkdtemp(prefix="amigo-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU(s), "
        f"Python {platform.python_version()}, NumPy {np.__version__}"
    )
    print(f"{'nints':>7} {'ngroups':>7} {'file MB':>8} {'seconds':>8} {'peak MB':>8}")
    try:
        for nints in args.nints:
            uncal = work / f"bench{nints}_uncal.fits"
            write_synthetic_uncal(uncal, nints, args.ngroups)
            env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "JAX_PLATFORMS": "cpu"}
            result = subprocess.run(
                [sys.executable, __file__, "--child", str(uncal), str(work / "out")],
                capture_output=True,
                text=True,
                env=env,
                check=True,
            )
            seconds, peak_mb = result.stdout.split()[-2:]
            size_mb = uncal.stat().st_size / 2**20
            print(f"{nints:>7} {args.ngroups:>7} {size_mb:>8.0f} {seconds:>8} {peak_mb:>8}")
            uncal.unlink()
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
