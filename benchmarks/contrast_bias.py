"""Is a faint companion's fitted contrast biased? Injections, with and without noise.

    python benchmarks/contrast_bias.py [--sep 250 --pa 220 --dmag 6.5] [--draws 6] [--out DIR]

The files are those of ``benchmarks/peers.py``'s simulated cases (amigo's simulator at
simulation fidelity, the real F480M calibrator file's headers, bad pixels, flux and noise
law), one science star with a companion and one calibrator, through ``amigo fit`` with the
nominal instrument and ``amigo detect --no-hmc``. Four sets, each a row of the table:

* ``noiseless``: science and calibrator without noise (their ERR as usual): what the fit
  returns for the expected data, i.e. the bias of the method itself;
* ``shared calibrator``: ``--draws`` science noise draws against one calibrator draw (the
  calibrator of peers.py, seed 1000: every case of that benchmark shares it);
* ``that calibrator alone``: the noiseless science against the same calibrator draw;
* ``own calibrators``: ``--draws`` draws of both.

Per set: the mean offset of the delta-mag and of the separation from the truth, their
scatter over the draws, the mean of the errors amigo reports, and the number of draws
in which the companion was found. Nothing is asserted. About 2 minutes per fit on a
2-core CPU (the first compiles, cached on disk after): 14 fits with ``--draws 6``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peers import CALIBRATOR_XY, SCIENCE_XY, _render, run_amigo, simulation_setup, write_calints

SHARED_CALIBRATOR_SEED = 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sep", type=float, default=250.0, help="separation (mas)")
    parser.add_argument("--pa", type=float, default=220.0, help="position angle (deg)")
    parser.add_argument("--dmag", type=float, default=6.5)
    parser.add_argument("--draws", type=int, default=6)
    parser.add_argument("--out", type=Path, default=Path("contrast_bias"))
    args = parser.parse_args()

    filter_name = "F480M"
    out = args.out
    model, template, orientation = simulation_setup(out, filter_name)
    truth = (args.sep, args.pa, args.dmag)
    science = _render(filter_name, orientation, SCIENCE_XY, truth, 0)
    star = _render(filter_name, orientation, CALIBRATOR_XY, (None, None, None), 0)

    def calints(name: str, image, target: str, seed: int, noise: float) -> Path:
        folder = out / name
        folder.mkdir(exist_ok=True)
        observation = "001" if target == "SCI-STAR" else "002"
        return write_calints(folder / f"jw09999{observation}001_03102_00001_nis_calints.fits",
                             template, image, target, observation, seed, noise)  # fmt: skip

    def run(name: str, sci_seed: int, sci_noise: float, cal_seed: int, cal_noise: float):
        sci = calints(name, science, "SCI-STAR", sci_seed, sci_noise)
        cal = calints(f"{name}/cal", star, "CAL-STAR", cal_seed, cal_noise)
        result = run_amigo([sci], [cal], out / name / "amigo", model)
        if result.sep is None:
            print(f"  {name}: not found", flush=True)
            return None
        row = (result.dmag[filter_name] - args.dmag, result.dmag_err[filter_name],
               result.sep - args.sep, result.sep_err)  # fmt: skip
        print(f"  {name}: d dmag {row[0]:+.3f} +- {row[1]:.3f}, d sep {row[2]:+.2f} +- "
              f"{row[3]:.2f} mas ({result.seconds:.0f} s)", flush=True)  # fmt: skip
        return row

    n = args.draws
    sets = {
        "noiseless": [run("noiseless", 0, 0.0, 0, 0.0)],
        "shared calibrator": [
            run(f"shared{i}", 1 + i, 1.0, SHARED_CALIBRATOR_SEED, 1.0) for i in range(n)
        ],
        "that calibrator alone": [run("calibrator", 0, 0.0, SHARED_CALIBRATOR_SEED, 1.0)],
        "own calibrators": [run(f"own{i}", 1 + i, 1.0, 2000 + i, 1.0) for i in range(n)],
    }
    print(f"\n{args.dmag:g} mag at {args.sep:g} mas, PA {args.pa:g} deg, {filter_name}:")
    print(f"{'set':<22} {'found':>5} {'d dmag mean':>11} {'scatter':>8} {'error':>6} "
          f"{'d sep mean':>10} {'scatter':>8} {'error':>6}")  # fmt: skip
    for name, rows in sets.items():
        found = np.array([r for r in rows if r is not None])
        if not len(found):
            print(f"{name:<22} {0:>2}/{len(rows):<2}")
            continue
        mean = found.mean(axis=0)
        spread = found.std(axis=0, ddof=1) if len(found) > 1 else np.full(4, np.nan)
        print(f"{name:<22} {len(found):>2}/{len(rows):<2} {mean[0]:+11.3f} {spread[0]:8.3f} "
              f"{mean[1]:6.3f} {mean[2]:+10.2f} {spread[2]:8.2f} {mean[3]:6.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
