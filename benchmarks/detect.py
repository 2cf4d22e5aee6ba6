"""Timings of the companion search on this machine (prints a table; not a test).

Run: ``python benchmarks/detect.py`` (``--quick`` skips the HMC rows). Target (issue 5): a
1000 mas grid at 10 mas steps in one filter in under 5 s on 2 CPU cores. Each row gives
the first call (including JAX compilation) and the best of three further calls.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from amigo import niriss  # noqa: E402
from amigo.companions import fit, observables, posterior  # noqa: E402
from amigo.companions.grid import Grid, contrast_grid  # noqa: E402
from amigo.io.calvis import nominal_sky_to_uv, write_calvis  # noqa: E402
from amigo.orientation import Orientation  # noqa: E402

NUHOR = Path(__file__).resolve().parents[2] / "shared" / "data" / "oifits" / "NuHor_F480M.oifits"


def calvis_block(tmp: Path, filter_name: str, n_uv: int, n_obs: int, seed: int = 0):
    """A calvis-like block: the 21 baselines (n_uv=21) or n_uv random points in the OTF."""
    rng = np.random.default_rng(seed)
    if n_uv == 21:
        uv = niriss.baselines_m()
    else:
        radius = 6.0 * np.sqrt(rng.uniform(size=n_uv))
        angle = rng.uniform(0, np.pi, size=n_uv)
        uv = np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])
    d = rng.normal(size=(n_obs, 2 * n_uv)) / np.sqrt(2 * n_uv)
    bins = niriss.filter_bins(filter_name, 9)
    orientation = Orientation(pa_aper_deg=172.3)
    path = write_calvis(
        tmp / f"B{n_uv}_{filter_name}_calvis.fits",
        values=rng.normal(size=n_obs) * 1e-3,
        errors=np.full(n_obs, 1e-3),
        kinds=["amplitude"] * (n_obs // 2) + ["phase"] * (n_obs - n_obs // 2),
        disco_matrix=d,
        uv_m=uv,
        wavelengths_m=bins.wavelengths_m,
        weights=bins.weights,
        sky_to_uv=nominal_sky_to_uv(orientation),
        orientation=orientation,
        n_photons=1e8,
        target="BENCH",
        filter_name=filter_name,
    )
    return observables.load(path)


def timed(function, repeats: int = 3) -> tuple[float, float, float]:
    """(first call wall s, best later wall s, CPU s of that best call, all threads)."""
    start = time.perf_counter()
    function()
    first = time.perf_counter() - start
    best, cpu = np.inf, np.nan
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        function()
        wall = time.perf_counter() - start
        if wall < best:
            best, cpu = wall, time.process_time() - start_cpu
    return first, best, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="skip the HMC timings")
    args = parser.parse_args()
    rows = []
    grid = Grid.square(1000.0, 10.0)
    n_pos = int(np.sum(grid.radius_mas <= grid.rmax_mas))
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        cases = []
        if NUHOR.exists():
            cases.append(
                ("OIFITS NuHor F480M: 21 V2 + 35 CP (126 uv, 5 lambda)", observables.load(NUHOR))
            )
        cases.append(
            ("calvis, 21 baselines, 29 DISCOs, 9 lambda", calvis_block(tmp, "F480M", 21, 29))
        )
        cases.append(
            ("calvis, 300 uv points, 200 DISCOs, 9 lambda", calvis_block(tmp, "F480M", 300, 200))
        )
        cases.append(
            ("calvis, 1300 uv points, 600 DISCOs, 9 lambda", calvis_block(tmp, "F480M", 1300, 600))
        )
        for label, block in cases:
            data = observables.Dataset.from_blocks([block])
            first, best, cpu = timed(lambda d=data: contrast_grid(d, grid))
            rows.append(
                (
                    f"grid 1000 mas / 10 mas ({grid.shape[0]}x{grid.shape[1]}, "
                    f"{n_pos} inside): {label}",
                    first,
                    best,
                    cpu,
                )
            )

        if not args.quick:
            three = observables.Dataset.from_blocks(
                [
                    calvis_block(tmp, f, 21, 29, seed=i)
                    for i, f in enumerate(("F380M", "F430M", "F480M"))
                ]
            )
            for label, data in (
                ("1 filter", observables.Dataset.from_blocks([three.blocks[0]])),
                ("3 filters", three),
            ):
                best_fit = fit.fit_companions(
                    data, np.array([[-320.0, 60.0]]), np.full((1, data.n_filters), -2.0)
                )

                def run(d=data, b=best_fit):
                    posterior.sample_posterior(
                        d, b, np.ones(d.n_groups), num_warmup=500, num_samples=1000, num_chains=2
                    )

                start, start_cpu = time.perf_counter(), time.process_time()
                run()
                rows.append(
                    (
                        f"NUTS 1 companion, {label} (calvis 21 baselines), "
                        "2 chains x (500 + 1000), compilation included",
                        time.perf_counter() - start,
                        np.nan,
                        time.process_time() - start_cpu,
                    )
                )

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU "
        f"cores, JAX {jax.__version__} on {jax.devices()[0].platform}, float64"
    )
    width = max(len(r[0]) for r in rows)
    print(
        "(wall: elapsed seconds; cpu: process CPU seconds over all threads, for the same "
        "call: on a loaded machine wall > cpu / 2)"
    )
    print(f"{'case':<{width}}  first call wall  best of 3 wall  its cpu")
    for label, first, best, cpu in rows:
        best_text = "" if not np.isfinite(best) else f"{best:14.2f}"
        print(f"{label:<{width}}  {first:15.2f}  {best_text:>14}  {cpu:7.2f}")


if __name__ == "__main__":
    main()
