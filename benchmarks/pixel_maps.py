"""A base model's per-pixel maps against the simulator's per-pixel truth (prints a table).

    python benchmarks/pixel_maps.py [--model PATH ...] [--seed 0] [--centre 40,40]

A model trained on amigo's simulated calibration data (the shipped one: seed 0) learns
each pixel's flat field, quadratic non-linearity and dark current; the simulator drew
those from its seed (``amigo.simulation.detector.draw_detector``), so they can be
compared pixel by pixel. Errors are given in rings of distance from the training star's
position (``--centre``, pixels as (x, y)): where the star is bright, a pixel's dark
current is a few electrons per group under thousands of photons, and a model can take
a misfit for it (docs/detector.md, "The dark current's population prior"). Per map and
ring: the mean error, the error's pixel-to-pixel scatter about that mean (std), and the
truth's own scatter; the flat is compared after dividing each by its mean (its mean is
degenerate with the fluxes, so a common offset of the rings' means is not an error). Seconds on a CPU.
"""

from __future__ import annotations

import argparse

import numpy as np

from amigo import niriss
from amigo.model.base import default_model_path, load_base_model
from amigo.simulation.detector import draw_detector
from amigo.simulation.scenarios import load_scenario

RINGS: tuple[tuple[float, float], ...] = ((0, 5), (5, 10), (10, 20), (20, 40), (40, 60))


def truth_maps(seed: int) -> dict[str, np.ndarray]:
    """The simulator's per-pixel truth for ``seed``, in the model's units: flat over its
    mean, non-linearity (1/e-), dark current (e- per group)."""
    scenario = load_scenario("cal4481")
    # The detector's stream is the second of the seed's spawns, whatever the scenario
    # (amigo.simulation.run.simulate_scenario).
    detector_seq = np.random.SeedSequence(int(seed)).spawn(2 + len(scenario.exposures))[1]
    truth = draw_detector(np.random.default_rng(detector_seq), scenario.detector)
    return {
        "flat": truth.flat / truth.flat.mean(),
        "nonlinearity": truth.nonlinearity_c2_per_e,
        "dark": truth.dark_e_per_s * niriss.GROUP_TIME_S,
    }


def model_maps(path) -> dict[str, np.ndarray]:
    model = load_base_model(path)
    flat = np.asarray(model.ramp.flat, float)
    return {
        "flat": flat / flat.mean(),
        "nonlinearity": np.asarray(model.read.nonlinearity, float),
        "dark": np.asarray(model.read.dark_e_per_group, float),
    }


def ring_errors(
    model: dict[str, np.ndarray], truth: dict[str, np.ndarray], centre: tuple[float, float]
) -> list[dict]:
    """One row per map and ring: the mean error, its scatter (std), the truth's scatter."""
    ny, nx = truth["flat"].shape
    y, x = np.mgrid[:ny, :nx]
    radius = np.hypot(x - centre[0], y - centre[1])
    rows = []
    for name in ("flat", "nonlinearity", "dark"):
        error = model[name] - truth[name]
        for inner, outer in RINGS:
            ring = (radius >= inner) & (radius < outer)
            rows.append(
                {
                    "map": name,
                    "ring": f"{inner:g}-{outer:g}",
                    "mean": float(error[ring].mean()),
                    "scatter": float(error[ring].std()),
                    "truth_scatter": float(truth[name][ring].std()),
                }
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", nargs="+", default=[str(default_model_path())])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--centre", default="40,40", help="the training star's x,y (pixels)")
    args = parser.parse_args()
    x, y = (float(v) for v in args.centre.split(","))
    centre = (x, y)
    truth = truth_maps(args.seed)
    for path in args.model:
        print(f"\n{path} against the simulator's seed-{args.seed} detector")
        print("| map | ring (pixels) | mean error | error's scatter | truth's scatter |")
        print("|---|---|---|---|---|")
        for row in ring_errors(model_maps(path), truth, centre):
            print(
                f"| {row['map']} | {row['ring']} | {row['mean']:+.2g} | {row['scatter']:.3g} "
                f"| {row['truth_scatter']:.3g} |"
            )


if __name__ == "__main__":
    main()
