"""Hostile *values* through the whole of ``amigo fit``: outcomes by case.

    python benchmarks/fuzz_fit.py [--out DIR] [--only NAME[,NAME...]] [--timeout 600]

benchmarks/fuzz_inputs.py damages the files' structure and runs the readers; this script
takes files that every reader accepts but whose numbers are hostile (a star of 1e-30 or
1e30 DN/s, errors of 1e-20, a single hot pixel instead of a star, a flat field, the star
at the edge, half the image flagged, the calibrator equal to the science image...) and
runs ``amigo fit`` on them end to end, in a fresh process each (as a user would), on one
filter of small simulated level-2 images (amigo's nominal instrument at 3 wavelengths,
27 x 27 knots). Each case ends with its exit status: 0 (fitted), 2 (refused in one line),
3 or 4 (fitted with an exposure left out, or a numerical failure reported per filter:
docs/reliability.md), or BROKEN (status 1, a traceback, or past the time limit); the
table gives the status, the statuses in fit_summary.json, the worst pixel z-score std
and the wall time. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from jwst_files import nominal_star, write_level2  # noqa: E402

FILTER = "F480M"


def star_image() -> tuple[np.ndarray, np.ndarray]:
    """(80, 80) image (DN/s) of a point source through the nominal instrument and its
    error (photon and read noise)."""
    image = nominal_star(FILTER)
    return image, np.sqrt(np.maximum(image, 0.0) / 80.0 + 4.0)


#: case name -> (which file is damaged, damage of (sci, err, dq, rng) -> (sci, err, dq)).
Damage = Callable[[np.ndarray, np.ndarray, np.ndarray, np.random.Generator], tuple]


def _hot_pixel(sci, err, dq, rng):
    noise = err * rng.standard_normal(sci.shape)
    noise[40, 40] += 1e6
    return noise, err, dq


def _flat(sci, err, dq, rng):
    return np.full_like(sci, 100.0) + err * rng.standard_normal(sci.shape), err, dq


def _edge(sci, err, dq, rng):
    return np.roll(sci, (-36, 37), axis=(0, 1)), err, dq


def _half_flagged(sci, err, dq, rng):
    dq = dq.copy()
    dq[:, :40] = 1
    return sci, err, dq


def _ring_flagged(sci, err, dq, rng):
    dq = dq.copy()
    y, x = np.mgrid[:80, :80]
    dq[np.hypot(x - 40, y - 40) < 12] = 1  # the whole core of the PSF
    return sci, err, dq


def _two_stars(sci, err, dq, rng):
    return sci + np.roll(sci, (8, -5), axis=(0, 1)), err, dq


def _negative(sci, err, dq, rng):
    return -sci, err, dq


def _nan_core(sci, err, dq, rng):
    sci = sci.copy()
    sci[35:45, 35:45] = np.nan
    return sci, err, dq


def _saturated(sci, err, dq, rng):
    return np.minimum(sci, 0.2 * sci.max()), err, dq


#: Each case: the exposure it damages ("sci" or "cal") and how; "same" gives the calibrator
#: the science file itself.
CASES: dict[str, tuple[str, Damage | str]] = {
    "none": ("cal", lambda s, e, d, r: (s, e, d)),
    "flux 1e-30": ("cal", lambda s, e, d, r: (s * 1e-30, e * 1e-30, d)),
    "flux 1e30": ("sci", lambda s, e, d, r: (s * 1e30, e * 1e30, d)),
    "err 1e-20": ("cal", lambda s, e, d, r: (s, e * 1e-20, d)),
    "err 1e20": ("sci", lambda s, e, d, r: (s, e * 1e20, d)),
    "err 1e-20 science": ("sci", lambda s, e, d, r: (s, e * 1e-20, d)),
    "hot pixel (no star)": ("cal", _hot_pixel),
    "flat field": ("sci", _flat),
    "star at the edge": ("cal", _edge),
    "half flagged": ("cal", _half_flagged),
    "PSF core flagged": ("sci", _ring_flagged),
    "PSF core NaN": ("cal", _nan_core),
    "two stars": ("cal", _two_stars),
    "negative star": ("sci", _negative),
    "clipped at 20% of the peak": ("sci", _saturated),
    "calibrator = science": ("cal", "same"),
}


def write_case(name: str, folder: Path, image, error) -> tuple[Path, Path]:
    """The science and calibrator files of one case."""
    role, damage = CASES[name]
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    folder.mkdir(parents=True, exist_ok=True)
    files = {}
    science = image + error * rng.standard_normal(image.shape)
    for which, observation in (("sci", "001"), ("cal", "002")):
        sci = (
            science
            if (which == "sci" or damage == "same")
            else (image + error * rng.standard_normal(image.shape))
        )
        err, dq = error, np.zeros(image.shape, np.uint32)
        if which == role and not isinstance(damage, str):  # "same" damages nothing
            sci, err, dq = damage(sci, err, dq, rng)
        files[which] = write_level2(
            folder / f"{which}_cal.fits",
            sci,
            err,
            dq,
            overrides={"FILTER": FILTER, "TARGPROP": f"STAR-{which}", "OBSERVTN": observation},
        )
    return files["sci"], files["cal"]


def run_case(sci: Path, cal: Path, model: Path, out: Path, timeout: float) -> dict:
    args = [sys.executable, "-m", "amigo", "fit", "--sci", str(sci), "--cal", str(cal),
            "--out", str(out), "--model", str(model), "--knots", "27",
            "--knot-spacing", "0.5"]  # fmt: skip
    start = time.perf_counter()
    try:
        done = subprocess.run(
            args,
            capture_output=True,
            text=True,
            timeout=timeout,
            env={**os.environ, "JAX_PLATFORMS": "cpu"},
        )
    except subprocess.TimeoutExpired:
        return {"status": "timeout", "seconds": timeout, "outcome": "BROKEN", "line": ""}
    seconds = time.perf_counter() - start
    lines = [line for line in done.stderr.splitlines() if line.startswith(("amigo:", "warn"))]
    broken = done.returncode not in (0, 2, 3, 4) or "Traceback" in done.stderr
    record: dict[str, object] = {
        "status": done.returncode,
        "seconds": seconds,
        "outcome": "BROKEN" if broken else "ok",
        "line": (lines[-1] if lines else "")[:110],
    }
    summary = out / "fit_summary.json"
    if summary.is_file():
        document = json.loads(summary.read_text())
        record["statuses"] = "/".join(e.get("status", "?") for e in document["exposures"])
        z = [e["zscore_std"] for e in document["exposures"] if e.get("zscore_std") is not None]
        record["z"] = max(z) if z else None
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="work folder (default: temp)")
    parser.add_argument("--only", default="", help="comma-separated case names")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per case")
    args = parser.parse_args()
    from amigo.model.image import Instrument, save_instrument

    root = args.out or Path(tempfile.mkdtemp(prefix="amigo-fuzz-fit-"))
    model = root / "nominal.eqx"
    save_instrument(Instrument.nominal(n_wavelengths=3), model)
    image, error = star_image()
    names = [n for n in args.only.split(",") if n] or list(CASES)
    print("| case | damaged | exit | exposures | worst z std | s | last line |")
    print("|---|---|---|---|---|---|---|")
    start = time.perf_counter()
    n_broken = 0
    for i, name in enumerate(names):
        sci, cal = write_case(name, root / f"case{i:02d}" / "in", image, error)
        r = run_case(sci, cal, model, root / f"case{i:02d}" / "out", args.timeout)
        n_broken += r["outcome"] == "BROKEN"
        z = "" if r.get("z") is None else f"{r['z']:.3g}"
        status = f"{r['status']}" + (" **BROKEN**" if r["outcome"] == "BROKEN" else "")
        print(
            f"| {name} | {CASES[name][0]} | {status} | {r.get('statuses', '')} | {z} | "
            f"{r['seconds']:.0f} | {r['line']} |",
            flush=True,
        )
    print(f"\n{len(names)} cases, {n_broken} broken, {time.perf_counter() - start:.0f} s; "
          f"work folder {root}")  # fmt: skip


if __name__ == "__main__":
    main()
