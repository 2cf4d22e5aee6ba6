"""Calibrate the trials of the companion search on null data sets (prints a table).

    python benchmarks/false_alarm.py [--realisations 40] [--rmax-mas 600] [--seed 1]

Each realisation is a pair of calvis files (F380M, F480M) of a single star with the
project's independent NumPy observables simulator (tests/detect_helpers.py: kernel
observables of the 21 NIRISS baselines, correlated noise), no companion. The joint
detection map of ``amigo detect``'s grid search gives the highest chi2 gain anywhere in
the field; :func:`amigo.companions.significance.significance` turns it into a
false-alarm probability with the trials of :func:`~amigo.companions.significance.
effective_trials`. If the trials are right, these probabilities are uniform on [0, 1]:
the table gives the fraction below 0.05, 0.1, 0.25, 0.5 and 0.75 with its binomial error,
and the Kolmogorov-Smirnov distance to the uniform law. Not a test: nothing is asserted.
About 5 minutes for 40 realisations on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from amigo.companions import observables as obs
from amigo.companions.grid import (
    Grid,
    contrast_grid,
    default_step_mas,
    inner_working_angle_mas,
)
from amigo.companions.significance import effective_trials, significance
from detect_helpers import write_sim_calvis


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realisations", type=int, default=40)
    parser.add_argument("--rmax-mas", type=float, default=600.0)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(args.seed)
    faps, peaks = [], []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.realisations):
            blocks = [
                obs.load(write_sim_calvis(Path(tmp) / f"N{i}_{f}_calvis.fits", f, [], rng))
                for f in ("F380M", "F480M")
            ]
            dataset = obs.Dataset.from_blocks(blocks)
            grid = Grid.square(args.rmax_mas, default_step_mas(dataset))
            result = contrast_grid(dataset, grid, None, None, np.ones(dataset.n_groups), 0.0)
            iwa = inner_working_angle_mas(dataset.blocks)
            trials = effective_trials(args.rmax_mas, iwa)
            best = float(np.nanmax(result.joint_dchi2))
            sig = significance(best, dataset.n_filters, trials)
            faps.append(sig.false_alarm_probability)
            peaks.append(sig.local_sigma)
    seconds = time.perf_counter() - start
    fap = np.asarray(faps)
    n = fap.size
    print(f"{n} null realisations, F380M + F480M, r_max {args.rmax_mas:g} mas, ")
    print(f"inner working angle {iwa:.1f} mas, {trials:.0f} trials, {seconds:.0f} s\n")
    print("| FAP below | fraction | expected | binomial error |")
    print("|---|---|---|---|")
    for q in (0.05, 0.1, 0.25, 0.5, 0.75):
        print(f"| {q:g} | {np.mean(fap < q):.3f} | {q:g} | {np.sqrt(q * (1 - q) / n):.3f} |")
    ks = stats.kstest(fap, "uniform")
    print(f"\nKS distance to uniform {ks.statistic:.3f} (p = {ks.pvalue:.2f});")
    print(f"highest local peak: median {np.median(peaks):.2f} sigma, max {np.max(peaks):.2f}")


if __name__ == "__main__":
    main()
