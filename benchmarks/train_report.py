"""Per filter, how well a base model fits the real COM 1093 images before and after
training: pixel z-score std and chi2/dof of the training, validation and science sets
(prints a table; issue 22's report).

    python benchmarks/train_report.py [--before MODEL] [--after MODEL] [--no-stripes]

Each image is fitted as training fits it (``amigo.training.trainer.Trainer``: the
instrument fixed, the star's position and flux by the warm-up's Newton steps, each
level-2 image's 1/f stripes measured and marginalised), under two models: by default
the simulated-ramp model that training started from, seen behind the pipeline
(``before``), and the shipped real-data model (``after``). The sets: the 12 calibrator
images the shipped model was trained on (HD 37093 obs 17 dithers 1-3, HD 36805 obs 18,
obs 20 dithers 1-6), its validation visit (HD 37093 obs 15) and the science target it
never saw (AB Dor obs 12: 2, 4, 5 and 13 groups). Files are read from
``$AMIGO_SHARED/data/jwst``. The z std is the plain ``(data - model) / ERR`` pooled over
a set's pixels of a filter; chi2/dof is the likelihood's (whitened for the stripes).
These are point-source fits: no latent visibilities take up a science target's own
wavefront, as they do in ``amigo fit``. Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from pathlib import Path

SHARED = Path(os.environ.get("AMIGO_SHARED", Path(__file__).resolve().parents[2] / "shared"))
JWST = SHARED / "data" / "jwst"


def _sets() -> dict[str, list[Path]]:
    cal = JWST / "com1093-calibrators"
    return {
        "training": [
            *(cal / f"jw01093017001_03102_0000{k}_nis_cal.fits" for k in (1, 2, 3)),
            *(cal / f"jw01093018001_0310{k}_00001_nis_cal.fits" for k in (2, 3, 4)),
            *(cal / f"jw01093020001_03102_0000{k}_nis_cal.fits" for k in range(1, 7)),
        ],
        "validation": [
            JWST / "com1093" / f"jw01093015001_0310{k}_00001_nis_cal.fits" for k in (2, 3, 4)
        ],
        "AB Dor": [
            JWST / "com1093" / f"jw01093012001_0310{k}_00001_nis_cal.fits" for k in (2, 3, 4, 5)
        ],
    }


def statistics(model_path: Path, sets: dict[str, list[Path]], stripes: bool) -> dict:
    """``{(set, filter): (chi2, dof)}`` of every image fitted under the model."""
    import jax.numpy as jnp

    from amigo.model.base import load_base_model
    from amigo.model.optics import cast
    from amigo.training.data import TrainingData, TrainSettings
    from amigo.training.trainer import Trainer

    others = [p for name, paths in sets.items() if name != "training" for p in paths]
    data = TrainingData.read(sets["training"], (), others, dtype=jnp.float32)
    model = cast(load_base_model(model_path), jnp.float32)
    settings = TrainSettings(steps=0, init=str(model_path), stripes=stripes)
    trainer = Trainer(data, settings, None, initial=model)
    trainer.warm_up()
    trainer.measure_stripes()
    trainer.warm_up()  # the positions and fluxes again, under the stripes' likelihood
    # An image's name is its file's stem without "_cal" (SlopeData.read).
    set_of = {p.name.removesuffix("_cal.fits"): name for name, ps in sets.items() for p in ps}
    table: dict = defaultdict(lambda: [0.0, 0, 0.0, 0])
    for s in trainer.statistics(trainer.state.base):
        row = table[(set_of[s.name], s.filter)]
        row[0] += s.chi2  # whitened for the stripes: the likelihood's
        row[1] += s.dof
        row[2] += s.zscore_std**2 * s.npix  # plain (data - model) / err, as amigo fit's
        row[3] += s.npix
    return dict(table)


def main() -> None:
    from amigo.model.base import default_model_path, level2_model_path

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, default=None, help="default: the simulated")
    parser.add_argument("--after", type=Path, default=None, help="default: the shipped real")
    parser.add_argument("--no-stripes", action="store_true")
    args = parser.parse_args()
    sets = _sets()
    missing = [p for paths in sets.values() for p in paths if not p.is_file()]
    if missing:
        raise SystemExit(f"missing {missing[0]} (set AMIGO_SHARED)")
    models = {
        "before": args.before or default_model_path(),
        "after": args.after or level2_model_path(),
    }
    results = {}
    for label, path in models.items():
        if path is None:
            raise SystemExit(f"no {label} model (this installation ships none)")
        start = time.perf_counter()
        results[label] = statistics(Path(path), sets, not args.no_stripes)
        print(f"{label}: {Path(path).name} ({time.perf_counter() - start:.0f} s)", flush=True)
    print("\n| set | filter | z std before | z std after | chi2/dof before | chi2/dof after |")
    print("|---|---|---|---|---|---|")
    for key in sorted(results["after"], key=lambda k: (list(sets).index(k[0]), k[1])):
        rows = [results[label][key] for label in models]
        z = [(r[2] / r[3]) ** 0.5 for r in rows]
        ratio = [r[0] / r[1] for r in rows]
        print(
            f"| {key[0]} | {key[1]} | {z[0]:.2f} | {z[1]:.2f} | {ratio[0]:.2f} | {ratio[1]:.2f} |"
        )
    print(
        "(z std: plain (data - model) / ERR, pooled over the set's pixels of the filter; "
        "chi2/dof: the likelihood's, whitened for each image's 1/f stripes)"
    )


if __name__ == "__main__":
    main()
