"""How many Jacobian columns to push through the model together, on this machine's device.

A fit's Jacobians (:func:`amigo.fitting.newton.local_jacobian` and
:func:`~amigo.fitting.newton.optics_jacobian`) apply the model's linearisation to unit
tangents in batches: a sequential loop whose steps each push ``batch`` columns through the
model. On a CPU a small batch keeps its intermediate images in the caches (8 is the
default, :data:`amigo.model.columns.JVP_BATCH`); on a GPU each step's kernels are small
and a step may cost mostly its launches, so fewer, larger steps may win there: this
measures it.

This runs ``amigo fit`` on the given files in this process once per batch size
(``$AMIGO_JVP_BATCH``), twice each: the first run compiles, the second is timed. Every call
of the two Jacobians is timed to completion. It prints one row per batch size: the warm
fit's wall time, its Jacobian calls, the seconds spent in them, milliseconds per column,
and how far the products (the calvis files' DISCOs) are from the first batch size's, in
units of their errors (the batch changes only the order of floating-point work). That
column is a like-for-like check only where the fits took the same path: a fit that
stops at another point of the optimum's flat valley has its kernel turned with the
fitted wavefront, and its DISCOs are other coordinates of the same information (14
"sigma" on a GPU at a batch of 256, while the companion fitted to them did not move:
docs/performance.md); compare companions (``amigo detect``) then.

    python benchmarks/jacobian_batch.py --sci SCI_cal.fits --cal CAL_cal.fits
        [--model MODEL] [--knots N --knot-spacing M] [--batches 8,32,64] [--platform cpu|any]

``--platform any`` uses JAX's default device (a GPU when there is one); the default is
the CPU. Without ``--model`` the fit uses amigo's default for the files.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sci", nargs="+", required=True, help="science level-2 files")
    parser.add_argument("--cal", nargs="+", required=True, help="calibrator level-2 files")
    parser.add_argument("--model", help="base model or instrument file (amigo fit --model)")
    parser.add_argument("--knots", type=int)
    parser.add_argument("--knot-spacing", type=float)
    parser.add_argument("--batches", default="8,32,64", help="comma-separated batch sizes")
    parser.add_argument("--platform", choices=("cpu", "any"), default="cpu")
    parser.add_argument("--out", type=Path, help="output folder (default: a temporary one)")
    args = parser.parse_args(argv)
    batches = [int(b) for b in args.batches.split(",")]
    if args.platform == "cpu":
        os.environ["JAX_PLATFORMS"] = "cpu"

    from amigo.runtime import configure_xla

    configure_xla()
    import jax
    import numpy as np

    import amigo.fitting.filter_fit as filter_fit
    import amigo.fitting.newton as newton
    from amigo.cli import main as amigo_main
    from amigo.io.calvis import read_calvis
    from amigo.model.columns import JVP_BATCH_ENV

    calls: dict[str, list[float]] = {"local": [], "optics": []}
    columns: dict[str, list[int]] = {"local": [], "optics": []}

    def timed(name: str, function):
        def wrapper(*a, **k):
            start = time.perf_counter()
            result = jax.block_until_ready(function(*a, **k))
            calls[name].append(time.perf_counter() - start)
            columns[name].append(int(result.shape[0]))
            return result

        return wrapper

    # Both modules' names: filter_fit calls the functions it imported from newton.
    local, optics = timed("local", newton.local_jacobian), timed("optics", newton.optics_jacobian)
    for module in (newton, filter_fit):
        setattr(module, "local_jacobian", local)  # noqa: B010  (a module's global, patched)
        setattr(module, "optics_jacobian", optics)  # noqa: B010

    options = ["--model", args.model] if args.model else []
    if args.knots is not None:
        options += ["--knots", str(args.knots)]
    if args.knot_spacing is not None:
        options += ["--knot-spacing", str(args.knot_spacing)]
    out = args.out or Path(tempfile.mkdtemp(prefix="amigo-jacobian-batch-"))
    device = jax.devices()[0]
    print(f"# device: {device.platform} {device.device_kind}; {platform.processor() or '?'}; "
          f"{os.cpu_count()} CPU cores; JAX {jax.__version__}")  # fmt: skip
    rows, reference = [], None
    for batch in batches:
        os.environ[JVP_BATCH_ENV] = str(batch)
        jax.clear_caches()  # the Jacobians are traced again, with this batch
        walls = []
        for run in range(2):
            for timings in calls.values():
                timings.clear()
            for counts in columns.values():
                counts.clear()
            folder = out / f"batch{batch}" / f"run{run}"
            command = ["fit", "--sci", *args.sci, "--cal", *args.cal, "--out", str(folder)]
            start = time.perf_counter()
            try:
                amigo_main([*command, *options])
            except SystemExit as exit_:
                if exit_.code not in (0, None):
                    print(f"amigo fit exited with {exit_.code}", file=sys.stderr)
                    return 1
            walls.append(time.perf_counter() - start)
        products = {p.name: read_calvis(p) for p in sorted(folder.glob("*_calvis.fits"))}
        if reference is None:
            reference, shift = products, 0.0
        else:
            shift = max(
                float(np.max(np.abs(products[n].values - c.values) / c.errors))
                for n, c in reference.items()
            )
        seconds = {k: float(np.sum(v)) for k, v in calls.items()}
        n_columns = {k: int(np.sum(v)) for k, v in columns.items()}
        n_calls = f"{len(calls['local'])} + {len(calls['optics'])}"
        ms = {k: 1e3 * seconds[k] / max(n_columns[k], 1) for k in seconds}
        rows.append(
            f"| {batch} | {walls[0]:.1f} | {walls[1]:.1f} | {n_calls} | {seconds['local']:.2f} "
            f"| {seconds['optics']:.2f} | {ms['local']:.2f} | {ms['optics']:.2f} | {shift:.2g} |"
        )
        print(rows[-1], flush=True)
    print()
    print("| batch | cold fit s | warm fit s | Jacobian calls (local + instrument) | local s |"
          " instrument s | local ms/column | instrument ms/column | DISCO shift (sigma) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
