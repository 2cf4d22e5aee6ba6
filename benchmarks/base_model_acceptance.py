"""Acceptance figures of a base model on held-out calslope exposures.

For every file: fit the point source's position and flux with the base model (the
instrument fixed), once with the charge-migration network (``--detector full``) and once
with it off (``--detector linear``), and report chi2, degrees of freedom and the z-score
standard deviation, with the slope covariance ``amigo fit`` uses ("auto": the full sample
covariance where every slope averages >= 10 m integrations, the pooled estimate
otherwise) and with its diagonal. Prints a table
per exposure and per filter, and writes the numbers as JSON.

The fit is the training's ramp-level point-source fit (amigo.training.exposure.fit_exposure):
a cross-check of ``amigo fit`` with nothing (latent visibilities, the calibrators'
wavefront) to absorb or add to the detector's residuals.

Run::

    python benchmarks/base_model_acceptance.py FILE_calslope.fits... [--model PATH] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections import defaultdict

import jax
import numpy as np

from amigo.likelihood.slopes import SlopeData
from amigo.model.base import default_model_path, load_base_model
from amigo.training.exposure import fit_exposure


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("files", nargs="+")
    parser.add_argument("--model", default=None)
    parser.add_argument("--json", default=None)
    parser.add_argument("--iterations", type=int, default=8)
    args = parser.parse_args()
    full = load_base_model(args.model)
    linear = full.with_linear_detector()
    cache = full.pupil_cache()
    print(f"model: {args.model or default_model_path()}")
    print(f"machine: {platform.processor() or platform.machine()}, jax {jax.__version__}")
    rows = []
    header = (
        f"{'file':<32} {'filter':<6} {'ng':>3} {'cov':<5} {'detector':<8} "
        f"{'chi2':>12} {'dof':>8} {'chi2/dof':>9} {'z std':>6}"
    )
    print(header)
    for path in args.files:
        for diagonal in (False, True):
            data = SlopeData.read(path, "validation", diagonal=diagonal)
            for name, model in (("full", full), ("linear", linear)):
                start = time.perf_counter()
                _, stats = fit_exposure(model, data, cache, args.iterations)
                row = {
                    **stats.to_json(),
                    "covariance": "diag" if diagonal else "auto",
                    "detector": name,
                    "seconds": round(time.perf_counter() - start, 1),
                }
                rows.append(row)
                print(
                    f"{stats.name:<32} {stats.filter:<6} {stats.ngroups:>3} {row['covariance']:<5} "
                    f"{name:<8} {stats.chi2:>12.1f} {stats.dof:>8} {stats.chi2 / stats.dof:>9.3f} "
                    f"{stats.zscore_std:>6.3f}",
                    flush=True,
                )
    print()
    print("per filter (sum of chi2 over the filter's exposures):")
    print(f"{'filter':<6} {'cov':<5} {'chi2 full':>12} {'chi2 linear':>12} {'reduction':>9} "
          f"{'z std full':>10} {'z std lin':>9}")  # fmt: skip
    summary: defaultdict[tuple, defaultdict[str, list]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        summary[(r["filter"], r["covariance"])][r["detector"]].append(r)
    table = []
    for (filt, cov), by in sorted(summary.items()):
        chi_full = sum(r["chi2"] for r in by["full"])
        chi_lin = sum(r["chi2"] for r in by["linear"])
        n_full = sum(r["dof"] for r in by["full"])
        # Pooled z-score standard deviation: sqrt(sum z^2 / n) (the z have mean ~0).
        z_full = float(np.sqrt(chi_full / n_full))
        z_lin = float(np.sqrt(chi_lin / sum(r["dof"] for r in by["linear"])))
        reduction = 1.0 - chi_full / chi_lin
        table.append({"filter": filt, "covariance": cov, "chi2_full": chi_full,
                      "chi2_linear": chi_lin, "chi2_reduction": reduction,
                      "zscore_rms_full": z_full, "zscore_rms_linear": z_lin})  # fmt: skip
        print(f"{filt:<6} {cov:<5} {chi_full:>12.1f} {chi_lin:>12.1f} {reduction:>9.1%} "
              f"{z_full:>10.3f} {z_lin:>9.3f}")  # fmt: skip
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump({"exposures": rows, "per_filter": table}, handle, indent=1)


if __name__ == "__main__":
    main()
