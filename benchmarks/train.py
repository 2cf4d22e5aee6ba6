"""Training time per step and per epoch of `amigo train` on real level-2 files (prints a table).

    python benchmarks/train.py [--files 6] [--epochs 3] [--batches 5] [--float64]

Fine-tunes the shipped real-data base model (as its second run did, `amigo train --init`)
on the first ``--files`` COM 1093 calibrator images of ../shared/data/jwst/com1093-
calibrators (obs 18 in three filters first, then obs 17 and 20 dithers in F480M) with
HD 37093 obs 15 F480M as validation, through the same :class:`amigo.training.trainer.Trainer`
the command uses, and times each epoch (``--batches`` optimisation steps, then the
validation fit). The first epoch includes the compilation of the step and validation
programs (JAX's persistent cache shortens it on later runs); the table gives it apart
from the median of the others. Runs on whatever JAX finds (the GPU when there is one;
``JAX_PLATFORMS=cpu`` forces the CPU). Nothing is written: the trained state is
discarded. Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

SHARED = Path(os.environ.get("AMIGO_SHARED", Path(__file__).resolve().parents[2] / "shared"))


def _files(n: int) -> tuple[list[Path], list[Path]]:
    folder = SHARED / "data" / "jwst" / "com1093-calibrators"
    ordered = sorted(folder.glob("jw01093018001_*_cal.fits")) + sorted(
        p for p in folder.glob("*_cal.fits") if not p.name.startswith("jw01093018001_")
    )
    validation = SHARED / "data" / "jwst" / "com1093" / "jw01093015001_03102_00001_nis_cal.fits"
    return ordered[:n], [validation]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, default=6)
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--batches", type=int, default=5)
    parser.add_argument("--float64", action="store_true")
    args = parser.parse_args()
    cal, val = _files(args.files)
    if not cal or not val[0].is_file():
        sys.exit(f"no COM 1093 files under {SHARED / 'data' / 'jwst'} (set AMIGO_SHARED)")

    import jax

    jax.config.update("jax_enable_x64", args.float64)
    import jax.numpy as jnp

    from amigo.model.base import level2_model_path, load_base_model
    from amigo.model.optics import cast
    from amigo.training.data import TrainingData, TrainSettings
    from amigo.training.trainer import Trainer, machine_description

    dtype = jnp.float64 if args.float64 else jnp.float32
    start = time.perf_counter()
    data = TrainingData.read(cal, (), val, dtype=dtype)
    initial = cast(load_base_model(level2_model_path()), dtype)
    steps = args.epochs * args.batches
    settings = TrainSettings(steps=steps, n_batches=args.batches, init="shipped level-2 model")
    trainer = Trainer(data, settings, None, initial=initial)
    setup_s = time.perf_counter() - start
    print(f"setup {setup_s:.1f} s on {jax.devices()[0].platform}", flush=True)
    epochs = []
    while trainer.step < steps:
        start = time.perf_counter()
        trainer.epoch()
        jax.block_until_ready(trainer.state)
        epochs.append(time.perf_counter() - start)
        # Each epoch as it ends: a run cut short (a lent machine's time limit) still tells.
        print(f"epoch {len(epochs)}: {epochs[-1]:.1f} s", flush=True)

    later = sorted(epochs[1:])
    median = later[len(later) // 2] if later else float("nan")
    print(f"\n{machine_description()}; JAX {jax.__version__} on {jax.devices()[0].platform}")
    print(
        f"{len(cal)} calibrator images ({', '.join(sorted(data.filters))}), 1 validation "
        f"image, {args.batches} steps per epoch, {'float64' if args.float64 else 'float32'}"
    )
    print(
        "| setup (read, model, first fits) | first epoch (compiles) | later epochs (median) | per step |"
    )
    print("|---|---|---|---|")
    print(
        f"| {setup_s:.1f} s | {epochs[0]:.1f} s | {median:.1f} s | "
        f"{median / args.batches:.1f} s (validation fit included) |"
    )
    print("epochs (s):", ", ".join(f"{e:.1f}" for e in epochs))


if __name__ == "__main__":
    main()
