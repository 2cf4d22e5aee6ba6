"""Where the time and memory of ``amigo fit`` and ``amigo detect`` go, per stage, cold and warm.

Runs the commands on the real COM 1093 level-2 files (AB Dor, obs 12, against HD 37093,
obs 15; one exposure each per filter), each in a fresh process, twice: *cold* (an empty
cache folder: no compiled programs, no latent bases) and *warm* (the same folder again,
``--force``: what a user's second target costs). For every run it prints the stages of the
command, with the wall seconds of each, the part of them spent in XLA's compiler, and the
process's peak memory (resident set).

    python benchmarks/profile_fit.py [--filters F480M F430M F380M] [--out DIR] [--no-detect]
                                     [--no-hmc] [--runs cold|warm|both] [--wavelengths N]
                                     [--reference DIR] [--seed-cache DIR] [--platform cpu|any]
                                     [--spy DIR] [--cache DIR]

``--wavelengths N`` fits with the shipped real-data model sampling each filter at ``N``
wavelengths instead of its own number (:meth:`amigo.model.base.BaseModel.with_config`:
the same parameters, a finer or coarser sum over the band); with ``--reference`` (the
output folder of a run at another setting) it measures the bias a sampling adds, in units
of the errors.

A stage is what the command announces on stderr (``amigo.progress``) until its next line:
the line's kind (basis, Jacobians, Levenberg-Marquardt steps, Hessians, ...) names the
time that follows it. Compilation is read from JAX's compile log (``jax_log_compiles``)
and charged to the stage in which it happened.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import os
import platform
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DATA = Path(os.environ.get("AMIGO_SHARED", Path(__file__).resolve().parents[2] / "shared"))
DATA = DATA / "data" / "jwst" / "com1093"
EXPOSURE = {"F480M": "03102", "F430M": "03103", "F380M": "03104"}

#: (stage, pattern of the progress line that begins it), first match wins.
STAGES: tuple[tuple[str, str], ...] = (
    ("startup and reading", r"^(amigo|reading|fit:|run:)"),
    ("latent basis", r"basis"),
    ("Jacobians", r"Jacobian of"),
    ("Levenberg-Marquardt steps", r"Gauss-Newton|chord steps|float64|damped step"),
    ("natural gradient", r"Fisher information|iteration \d|loss rose"),
    ("detector model", r"detector"),
    ("Hessians", r"Hessian of|kernel Jacobians"),
    ("DISCOs and files", r"^wrote "),
    ("reading observables", r"observables, \d+ uv points"),
    ("grid search and companion fits", r"^grid search \d|best candidate"),
    ("HMC", r"NUTS"),
    ("contrast limits", r"contrast limits"),
)
_COMPILED = re.compile(r"Finished XLA compilation of (\S+) in ([0-9.eE+-]+) sec")


def stage_of(line: str) -> str | None:
    for name, pattern in STAGES:
        if re.search(pattern, line):
            return name
    return None


class _Stamped:
    """stderr that keeps every line with the time it was written (and still shows it)."""

    def __init__(self, stream, start: float) -> None:
        self.stream, self.start, self._part = stream, start, ""
        self.lines: list[tuple[float, str]] = []

    def write(self, text: str) -> int:
        self.stream.write(text)
        self._part += text
        *done, self._part = self._part.split("\n")
        now = time.perf_counter() - self.start
        self.lines.extend((now, line) for line in done if line.strip())
        return len(text)

    def flush(self) -> None:
        self.stream.flush()

    def isatty(self) -> bool:
        return False


class _Compiles(logging.Handler):
    def __init__(self, start: float) -> None:
        super().__init__(level=logging.DEBUG)
        self.start = start
        self.events: list[tuple[float, float]] = []

    def emit(self, record: logging.LogRecord) -> None:
        found = _COMPILED.match(record.getMessage())
        if found:
            self.events.append((time.perf_counter() - self.start, float(found.group(2))))


def child(argv: list[str], report: Path) -> None:
    """Run one ``amigo`` command in this process and write its timeline to ``report``."""
    start = time.perf_counter()
    stamped = _Stamped(sys.stderr, start)
    sys.stderr = stamped
    # amigo's settings before JAX is imported, as the command line makes them (one source
    # line per operation, and its cache folder, needs JAX not yet started).
    from amigo.runtime import configure_xla

    configure_xla()
    import jax

    from amigo.cli import main as amigo

    jax.config.update("jax_log_compiles", True)
    compiles = _Compiles(start)
    for name in ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.compiler"):
        logger = logging.getLogger(name)
        logger.addHandler(compiles)
        logger.setLevel(logging.DEBUG)
        logger.propagate = False
    stamped.lines.append((time.perf_counter() - start, "amigo started"))
    status = 0
    try:
        amigo(argv)
    except SystemExit as exit_:
        status = int(exit_.code or 0)
    wall = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB
    report.write_text(
        json.dumps(
            {
                "argv": argv,
                "status": status,
                "wall_s": wall,
                "peak_mb": peak_mb,
                "lines": stamped.lines,
                "compiles": compiles.events,
            }
        )
    )


def stages(run: dict) -> list[tuple[str, float, float]]:
    """(stage, wall s, compile s) in order of first appearance."""
    marks = [(t, stage_of(line)) for t, line in run["lines"]]
    marks = [(t, s) for t, s in marks if s is not None]
    bounds = [*marks, (run["wall_s"], None)]
    table: dict[str, list[float]] = {}
    for (t0, name), (t1, _) in itertools.pairwise(bounds):
        assert name is not None
        row = table.setdefault(name, [0.0, 0.0])
        row[0] += t1 - t0
        row[1] += sum(s for t, s in run["compiles"] if t0 <= t < t1)
    return [(name, wall, comp) for name, (wall, comp) in table.items()]


def run_command(
    argv: list[str], cache: Path, label: str, platform_: str = "cpu", spy: Path | None = None
) -> dict:
    """Run ``amigo ARGV`` in a new process (under py-spy, its samples written to ``spy /
    <label>_<command>.spy``, where ``spy`` is given) and return its timeline."""
    with tempfile.TemporaryDirectory() as folder:
        report = Path(folder) / "report.json"
        env = {**os.environ, "AMIGO_CACHE_DIR": str(cache)}
        if platform_ == "cpu":
            env["JAX_PLATFORMS"] = "cpu"
        else:  # what amigo does by itself: a GPU when there is one
            env.pop("JAX_PLATFORMS", None)
        env.pop("JAX_COMPILATION_CACHE_DIR", None)
        cmd = [sys.executable, __file__, "--child", str(report), "--", *argv]
        if spy is not None:  # every thread's samples, waits included (raw: folded stacks)
            samples = spy / f"{label}_{argv[0]}.spy"
            cmd = [os.environ.get("SPY", "py-spy"), "record", "--idle", "-r", "50", "-f", "raw",
                   "-o", str(samples), "--", *cmd]  # fmt: skip
        print(f"[{label}] amigo {' '.join(argv)}", flush=True)
        done = subprocess.run(cmd, env=env, stderr=subprocess.PIPE, text=True)
        if done.returncode != 0 or not report.is_file():
            tail = "\n".join(done.stderr.splitlines()[-40:])
            sys.exit(f"amigo {argv[0]} failed (exit {done.returncode}):\n{tail}")
        return json.loads(report.read_text())


def print_run(label: str, run: dict) -> None:
    print(f"\n{label}: amigo {run['argv'][0]} (exit {run['status']})")
    print(f"{'stage':30s} {'wall s':>8s} {'compile s':>10s} {'run s':>8s}")
    for name, wall, comp in stages(run):
        print(f"{name:30s} {wall:8.1f} {comp:10.1f} {wall - comp:8.1f}")
    total_compile = sum(s for _, s in run["compiles"])
    print(
        f"{'all':30s} {run['wall_s']:8.1f} {total_compile:10.1f} {run['wall_s'] - total_compile:8.1f}"
    )
    print(f"peak memory (resident): {run['peak_mb']:.0f} MB")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--filters", nargs="+", default=list(EXPOSURE), choices=list(EXPOSURE))
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: temp)")
    parser.add_argument("--no-detect", action="store_true", help="profile amigo fit only")
    parser.add_argument("--no-hmc", action="store_true", help="amigo detect --no-hmc")
    parser.add_argument(
        "--platform",
        choices=("cpu", "any"),
        default="cpu",
        help="cpu: JAX on the CPU (the reference figures); any: what amigo picks (a GPU "
        "when there is one)",
    )
    parser.add_argument(
        "--reference",
        type=Path,
        default=None,
        help="an output folder of an earlier run of the same files: report how far this "
        "run's results moved, in units of their errors",
    )
    parser.add_argument(
        "--runs",
        choices=("cold", "warm", "both"),
        default="both",
        help="cold: an empty cache folder; warm: run again with it (both: cold then warm)",
    )
    parser.add_argument(
        "--wavelengths",
        type=int,
        default=None,
        help="fit with the shipped real-data model at this many wavelengths per filter",
    )
    parser.add_argument(
        "--seed-cache",
        type=Path,
        default=None,
        help="copy the latent bases (basis_*.npz) of this cache folder into the cold run's "
        "empty one: a cold run without the bases' construction (a lent machine's short time)",
    )
    parser.add_argument(
        "--spy",
        type=Path,
        default=None,
        help="sample the warm commands with py-spy ($SPY, else py-spy on the PATH) into this "
        "folder (warm_fit.spy, warm_detect.spy)",
    )
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="the cache folder (default: a temporary one, deleted at the end); kept for the "
        "commands run after this benchmark. With --runs warm and a cache folder that exists, "
        "the cold run is not made again",
    )
    parser.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        child([a for a in args.rest if a != "--"], args.child)
        return
    if not DATA.is_dir():
        sys.exit(f"no COM 1093 files at {DATA} (set AMIGO_SHARED)")
    sci = [DATA / f"jw01093012001_{EXPOSURE[f]}_00001_nis_cal.fits" for f in args.filters]
    cal = [DATA / f"jw01093015001_{EXPOSURE[f]}_00001_nis_cal.fits" for f in args.filters]
    with tempfile.TemporaryDirectory() as scratch:
        out = args.out or Path(scratch) / "out"
        cache = args.cache or Path(scratch) / "cache"
        filled = cache.is_dir() and any(cache.iterdir())
        if filled and args.runs != "warm":
            sys.exit(f"--cache {cache} holds a cache already: a cold run needs an empty folder")
        if args.spy is not None:
            args.spy.mkdir(parents=True, exist_ok=True)
        if args.seed_cache is not None:
            cache.mkdir(parents=True, exist_ok=True)
            for basis in sorted(args.seed_cache.glob("basis_*.npz")):
                shutil.copy2(basis, cache / basis.name)
                print(f"seeded the cache with {basis.name}", flush=True)
        fit = ["fit", "--sci", *map(str, sci), "--cal", *map(str, cal), "--out", str(out)]
        if args.wavelengths is not None:
            fit += ["--model", str(model_with_wavelengths(args.wavelengths, Path(scratch)))]
        extra = ["--force", *(["--no-hmc"] if args.no_hmc else [])]
        print(machine(args.platform), f"filters {' '.join(args.filters)}", flush=True)
        if args.wavelengths is not None:
            print(f"wavelengths per filter: {args.wavelengths}", flush=True)
        # A warm run needs the cold one before it (it fills the caches), shown or not.
        labels = ("cold",) if args.runs == "cold" else ("cold", "warm")
        if args.runs == "warm" and filled:
            labels = ("warm",)  # the caller's cache holds what the cold run would write
        for label in labels:
            shown = args.runs in (label, "both")
            # Each table as soon as its run ends: a run cut short still reports the others.
            spy = args.spy if label == "warm" else None
            run = run_command([*fit, "--force"], cache, label, args.platform, spy)
            if shown:
                print_run(f"{label} fit", run)
            if not args.no_detect:
                calvis = sorted(out.glob("*_calvis.fits"))
                detect = ["detect", *map(str, calvis), "--out", str(out / "detect"), *extra]
                run = run_command(detect, cache, label, args.platform, spy)
                if shown:
                    print_run(f"{label} detect", run)
            sys.stdout.flush()
        if args.reference is not None:
            print()
            compare(out, args.reference)


def model_with_wavelengths(n_wavelengths: int, folder: Path) -> Path:
    """The shipped real-data base model sampling each filter at ``n_wavelengths``, written
    to ``folder`` with the shipped file's record (what it was trained on) and a note."""
    from amigo.model.base import (
        level2_model_path,
        load_base_model,
        read_metadata,
        save_base_model,
    )

    source = level2_model_path()
    if source is None:
        sys.exit("this installation has no shipped real-data model")
    own = ("format", "format_version", "config", "network", "dtype")
    record = {k: v for k, v in read_metadata(source).items() if k not in own}
    record["derived_from"] = f"{source.name}, n_wavelengths={n_wavelengths} (profile_fit.py)"
    model = load_base_model(source).with_config(n_wavelengths=n_wavelengths)
    return save_base_model(model, folder / f"model_{n_wavelengths}wl.npz", record)


def machine(platform_: str) -> str:
    """The machine, as the tables' header names it (JAX's device in a child process)."""
    env = {**os.environ, **({"JAX_PLATFORMS": "cpu"} if platform_ == "cpu" else {})}
    if platform_ != "cpu":
        env.pop("JAX_PLATFORMS", None)
    code = "import jax; d = jax.devices()[0]; print(jax.__version__, d.platform, d.device_kind)"
    found = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.split(maxsplit=2)
    return (
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"JAX {found[0]} on {found[1]} ({found[2].strip()});"
    )


def compare(out: Path, reference: Path) -> None:
    """How far the results in ``out`` moved from those in ``reference``, in units of their
    errors: the fitted geometry and jitter (``fit_summary.json``), every DISCO (each row's
    sign aligned with the reference's) and the
    companions' separation, PA and contrast (``detect/companions.json``)."""
    import numpy as np

    from amigo.io.calvis import read_calvis

    print(f"results against {reference} (|difference| / error)")
    new, old = (json.loads((d / "fit_summary.json").read_text()) for d in (out, reference))
    worst: dict[str, float] = {}
    for a, b in zip(new["exposures"], old["exposures"], strict=True):
        for key, value in a.items():
            error = b.get(f"{key}_err")
            if isinstance(value, float) and isinstance(error, float) and error > 0:
                worst[key] = max(worst.get(key, 0.0), abs(value - b[key]) / error)
    for key, z in worst.items():
        print(f"  {key:30s} max {z:.4f}")
    for path in sorted(out.glob("*_calvis.fits")):
        if not (reference / path.name).is_file():
            continue  # a reference without its calvis files (tens of MB each)
        a, b = read_calvis(path), read_calvis(reference / path.name)
        if a.values.shape != b.values.shape:  # another sampling can keep other modes
            print(f"  {path.name:30s} DISCOs: {a.values.size} vs {b.values.size}, not compared")
            continue
        # A DISCO and its row change sign together; where a row's largest entries are
        # nearly tied, the sign convention can pick either: align each row to the
        # reference's.
        same = np.sign(np.sum(a.disco_matrix * b.disco_matrix, axis=1))
        z = np.abs(same * a.values - b.values) / b.errors
        print(f"  {path.name:30s} DISCOs: max {z.max():.4f}, rms {np.sqrt(np.mean(z * z)):.4f}")
    listed = [d / "detect" / "companions.json" for d in (out, reference)]
    if not all(path.is_file() for path in listed):  # --no-detect, here or there
        return
    found = [json.loads(path.read_text()).get("companions", []) for path in listed]
    for a, b in zip(*found, strict=False):
        pairs = [("sep_mas", a["sep_mas"], b["sep_mas"], b["sep_err_mas"]),
                 ("pa_deg", a["pa_deg"], b["pa_deg"], b["pa_err_deg"])]  # fmt: skip
        pairs += [(f"dmag {f}", a["dmag"][f], v, b["dmag_err"][f]) for f, v in b["dmag"].items()]
        for key, x, y, error in pairs:
            if error:
                print(f"  companion {b['id']} {key:19s} {abs(x - y) / error:.4f}")


if __name__ == "__main__":
    main()
