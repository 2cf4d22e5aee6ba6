"""HD 206893-like end to end: two faint companions from raw ramps (prints a table).

    python benchmarks/go1843.py [--out DIR] [--seed 0] [--quick] [--no-hmc] [--scenario FILE]
                                [--noise-seeds M ...] [--run-args "OPTIONS"]

``amigo simulate go1843 --full`` writes raw ramps of the built-in GO 1843-like scenario
(HD 206893 with B at 197.1 mas, delta-mag 8.33 / 7.98 / 7.49 in F380M / F430M / F480M,
and c at 103 mas, 9.14 / 8.32 / 8.07; a calibrator; the paper's integrations and photon
counts), then ``amigo run`` processes, fits and searches them (subtract-and-refit: each
found companion joins the background scene of the next search). The table compares every
reported companion with the simulated truth (separation, position angle and delta-mag
per filter, in units of the reported errors), lists what was rejected, and times each
step. ``--quick`` uses the scenario's quick integrations (about 1 % of the photons: a
check of the plumbing, the companions are then below the photon limit). Nothing is
asserted. The full run writes about 1.4 GB of ramps; on a 2-core CPU it took 6.8 min on
2026-11-30 (simulation 3.9, ``amigo run`` 2.9 without NUTS). ``--scenario FILE``
simulates an edited copy of ``amigo/data/scenarios/go1843.toml`` instead (docs/detect.md:
the calibrator moved to the science star's groups and pixel offset).

``--noise-seeds M [M ...]`` repeats the whole run for each noise draw of the same
telescope and detector (``amigo simulate --seed S --noise-seed M``; each in
``--out/noise_M``, its raw ramps deleted once processed unless ``--keep-ramps``), then
prints every draw's offsets in units of the reported errors and their rms over the
draws: whether the errors are honest (rms 1) needs draws, not one run. ``--run-args``
passes options to ``amigo run`` (``"--detector boundary"``; the demo's coarser grid for
another scenario, docs/detect.md "Near the inner working angle").
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

#: Offsets of one reported companion from its truth, in units of its reported errors.
Offsets = dict[str, float]


def _run(args: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "amigo", *args], check=True)
    return time.perf_counter() - start


def _truth(raw: Path) -> tuple[list[Path], list[Path], list[dict]]:
    """Science and calibrator ramps, and the companions with their delta-mag per filter
    (each truth file gives the delta-mag in its own filter)."""
    sci: list[Path] = []
    cal: list[Path] = []
    companions: list[dict] = []
    for path in sorted(raw.glob("*_truth.json")):
        doc = json.loads(path.read_text())
        uncal = raw / doc["uncal"]
        if doc["exposure"]["role"] != "science":
            cal.append(uncal)
            continue
        sci.append(uncal)
        scene = doc["scene"]["companions"]
        if not companions:
            companions = [{**c, "dmag": {}} for c in scene]
        for mine, c in zip(companions, scene, strict=True):
            mine["dmag"][doc["exposure"]["filter"]] = c["dmag"]
    return sci, cal, companions


def _name(k: int) -> str:
    """HD 206893's companions are B and c; a third (another scenario's) is #3."""
    return ("B", "c")[k] if k < 2 else f"#{k + 1}"


def _slopes(uncal: Path, out: Path) -> Path:
    """The raw ramps if they are there, else what ``amigo run`` made of them in ``out``."""
    slopes = out / uncal.name.replace("_uncal.fits", "_calslope.fits")
    return uncal if uncal.exists() or not slopes.exists() else slopes


def _angle(a: float, b: float) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


def _simulate_and_run(out: Path, args: argparse.Namespace, noise_seed: int | None) -> dict:
    """Simulate (unless ``out/raw`` holds ramps) and ``amigo run`` into ``out``; times in s.

    A run whose ``companions.json`` exists is not repeated (a killed series of draws
    resumes where it stopped) unless ``--rerun``."""
    raw = out / "raw"
    times: dict[str, float] = {}
    if args.report or ((out / "companions.json").exists() and not args.rerun):
        return times
    if not any(raw.glob("*_uncal.fits")):
        simulate = ["simulate", args.scenario, "--out", str(raw), "--seed", str(args.seed)]
        if noise_seed is not None:
            simulate += ["--noise-seed", str(noise_seed)]
        times["simulate"] = _run(simulate + ([] if args.quick else ["--full"]))
    sci, cal, _ = _truth(raw)
    # A draw rerun after its ramps were deleted starts from its calslope files.
    sci, cal = ([_slopes(p, out) for p in files] for files in (sci, cal))
    run = ["run", "--sci", *map(str, sci), "--cal", *map(str, cal), "--out", str(out)]
    run += ["--no-hmc"] if args.no_hmc else []
    times["amigo run"] = _run(run + args.run_args.split())
    if noise_seed is not None and not args.keep_ramps:
        # The truth files stay (the report reads them); the ramps are 1.4 GB a draw.
        for path in raw.glob("*_uncal.fits"):
            path.unlink()
    return times


def _report(out: Path, label: str, times: dict[str, float]) -> dict[str, Offsets | None]:
    """Print the table of one run; return each true companion's offsets (None: not found)."""
    _, _, truth = _truth(out / "raw")
    doc = json.loads((out / "companions.json").read_text())
    found = doc["companions"]
    filters = doc["filters"]
    print(f"\nGO 1843-like, {label}")
    print("sigma_scale:", ", ".join(f"{f} {doc['sigma_scale'][f]:.2f}" for f in filters))
    print(
        "photon rule (dmag):",
        ", ".join(f"{f} {v:.2f}" for f, v in doc["photon_limit_dmag"].items()),
    )
    header = "| companion | sep (mas) | PA (deg) | " + " | ".join(f"dmag {f}" for f in filters)
    print(header + " | sigma |")
    print("|" + "---|" * (4 + len(filters)))
    unmatched = list(found)
    offsets: dict[str, Offsets | None] = {}
    for k, t in enumerate(truth):
        # Each true companion takes the nearest reported one not taken yet.
        name = _name(k)
        truth_row = f"| {name} truth | {t['sep_mas']:.1f} | {t['pa_deg'] % 360:.1f} | "
        print(truth_row + " | ".join(f"{t['dmag'][f]:.2f}" for f in filters) + " | |")
        offsets[name] = None
        if not unmatched:
            print(f"| {name} found | not found | | " + " | " * len(filters))
            continue
        c = min(
            unmatched,
            key=lambda c: np.hypot(c["dra_mas"] - t["dra_mas"], c["ddec_mas"] - t["ddec_mas"]),
        )
        unmatched.remove(c)
        z = {
            "sep": (c["sep_mas"] - t["sep_mas"]) / c["sep_err_mas"],
            "PA": _angle(c["pa_deg"], t["pa_deg"]) / c["pa_err_deg"],
        }
        z.update({f: (c["dmag"][f] - t["dmag"][f]) / c["dmag_err"][f] for f in filters})
        offsets[name] = z
        cells = [
            f"{c['sep_mas']:.1f} +- {c['sep_err_mas']:.1f} ({z['sep']:+.1f} sigma)",
            f"{c['pa_deg']:.1f} +- {c['pa_err_deg']:.1f} ({z['PA']:+.1f} sigma)",
        ]
        cells += [f"{c['dmag'][f]:.2f} +- {c['dmag_err'][f]:.2f} ({z[f]:+.1f})" for f in filters]
        print(
            f"| {name} found ({c['method']}) | "
            + " | ".join(cells)
            + f" | {c['detection_sigma']:.1f} |"
        )
    rejected = [(r["sep_mas"], r["reason"]) for r in doc.get("rejected_candidates", [])]
    print(f"other companions reported: {len(unmatched)}; rejected candidates: {rejected}")
    if times:
        print("times:", ", ".join(f"{k} {v / 60:.1f} min" for k, v in times.items()))
    return offsets


def _summary(draws: dict[int, dict[str, Offsets | None]]) -> None:
    """Every draw's offsets (sigma) and, per quantity, their rms and mean over the draws."""
    for name in dict.fromkeys(n for d in draws.values() for n in d):
        found: dict[int, Offsets] = {}
        for m, d in draws.items():
            z = d.get(name)
            if z is not None:
                found[m] = z
        print(f"\n{name}: found in {len(found)} of {len(draws)} draws")
        if not found:
            continue
        keys = list(next(iter(found.values())))
        print("| noise seed | " + " | ".join(keys) + " |")
        print("|" + "---|" * (1 + len(keys)))
        for m, z in found.items():
            print(f"| {m} | " + " | ".join(f"{z[k]:+.2f}" for k in keys) + " |")
        values = np.array([[z[k] for k in keys] for z in found.values()])
        rms = np.sqrt(np.mean(values**2, axis=0))
        print("| rms | " + " | ".join(f"{v:.2f}" for v in rms) + " |")
        print("| mean | " + " | ".join(f"{v:+.2f}" for v in values.mean(axis=0)) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("go1843_benchmark"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--noise-seeds",
        type=int,
        nargs="+",
        help="draw the noise anew for each (same telescope and detector), one run each",
    )
    parser.add_argument(
        "--keep-ramps", action="store_true", help="keep each noise draw's raw ramps"
    )
    parser.add_argument(
        "--rerun", action="store_true", help="run amigo again where a draw has its products"
    )
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--run-args", default="", help="more options for amigo run, as one string")
    parser.add_argument("--no-hmc", action="store_true")
    parser.add_argument(
        "--scenario", default="go1843", help="the scenario to simulate (a name or a TOML file)"
    )
    parser.add_argument(
        "--report", action="store_true", help="only print the table of an earlier run in --out"
    )
    args = parser.parse_args()
    depth = "quick" if args.quick else "full"
    if not args.noise_seeds:
        times = _simulate_and_run(args.out, args, None)
        _report(args.out, f"seed {args.seed}, {depth} depth", times)
        return
    draws = {}
    for m in args.noise_seeds:
        out = args.out / f"noise_{m}"
        times = _simulate_and_run(out, args, m)
        draws[m] = _report(out, f"seed {args.seed}, noise seed {m}, {depth} depth", times)
    _summary(draws)


if __name__ == "__main__":
    main()
