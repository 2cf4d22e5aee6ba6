"""Speed and memory of the simulator's detector for SUB80 ramps (prints a table).

For 10 and 30 groups: integrations per second of the full default detector physics
(4 sub-steps per group, boundary-shift BFE, all noise sources) streamed into a real
level-1b file, the time of 100 integrations, and the peak memory allocated (tracemalloc,
which sees NumPy's buffers) for NINTS = N and 4 N to show that streaming keeps it bounded.
The illumination (the analytic NRM image, 15 wavelengths at 4x) is computed once, timed
separately.

    python benchmarks/simulate.py [--nints 100]
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from amigo import niriss
from amigo.orientation import Orientation
from amigo.simulation.detector import DetectorConfig, RampSimulator, draw_detector
from amigo.simulation.illumination import AnalyticNRM
from amigo.simulation.scene import DetectorScene, DetectorSource
from amigo.simulation.state import StateSpread, draw_instrument_state
from amigo.simulation.writer import UncalWriter, primary_header, sci_header


def run(rate: np.ndarray, ngroups: int, nints: int, folder: Path) -> tuple[float, float]:
    """Seconds and peak traced MiB to simulate and stream ``nints`` integrations."""
    config = DetectorConfig()
    realisation = draw_detector(np.random.default_rng(1), config)
    rng = np.random.default_rng(2)
    sci = sci_header(
        nints=nints,
        ngroups=ngroups,
        orientation=Orientation.from_roll(100.0),
        primary_xy_pix=(45.0, 40.0),
        ra_deg=10.0,
        dec_deg=-20.0,
        reference_xy_pix=(45.0, 40.0),
    )
    primary = primary_header({"DATAMODL": "Level1bModel", "TELESCOP": "JWST"})
    tracemalloc.start()
    start = time.perf_counter()
    simulator = RampSimulator(rate, 4, realisation, config, ngroups)
    with UncalWriter(folder / f"bench_{ngroups}_{nints}_uncal.fits", primary, sci) as writer:
        for _ in range(nints):
            writer.write(simulator.integration(rng)[0])
    seconds = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return seconds, peak / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nints", type=int, default=100)
    args = parser.parse_args()
    state = draw_instrument_state(np.random.default_rng(0), StateSpread())
    start = time.perf_counter()
    unit = AnalyticNRM(n_wavelengths=15).render(
        DetectorScene((DetectorSource(45.1, 40.2, 1.0),)), "F430M", state, 4
    )
    optics_s = time.perf_counter() - start
    pixels = unit.reshape(80, 4, 80, 4).sum(axis=(1, 3))
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"numpy {np.__version__}")  # fmt: skip
    print(f"illumination (analytic NRM, F430M, 15 wavelengths, 4x, 1 source): {optics_s:.2f} s")
    print()
    header = (
        f"{'groups':>6} {'nints':>6} {'seconds':>8} {'ints/s':>8} {'100 ints (s)':>13} "
        f"{'peak MiB':>9}"
    )
    print(header)
    print("-" * len(header))
    with tempfile.TemporaryDirectory() as tmp:
        for ngroups in (10, 30):
            # Peak pixel ~30,000 DN at the last group, as in CAL 4481.
            rate = (
                unit * 30000 * niriss.GAIN_E_PER_DN / (pixels.max() * ngroups * niriss.GROUP_TIME_S)
            )
            for nints in (args.nints, 4 * args.nints):
                seconds, peak = run(rate, ngroups, nints, Path(tmp))
                print(
                    f"{ngroups:>6} {nints:>6} {seconds:>8.2f} {nints / seconds:>8.1f} "
                    f"{100 * seconds / nints:>13.2f} {peak:>9.1f}"
                )


if __name__ == "__main__":
    main()
