"""Real-data validation of ``amigo fit`` on COM 1093: AB Dor (obs 12) against HD 37093 (obs 15).

Runs ``amigo fit`` per filter (F380M, F430M, F480M) on the level-2 files of
``../shared/data/jwst/com1093`` and evaluates, through the calvis matrices alone, the
reduced chi2 of (a) a point source and (b) a binary at the published AB Dor C position
(328.85 mas at PA 280.5 deg east of north in the files' WCS convention; delta-mag
4.313/4.354/4.381). Prints the z-score std of every exposure fit.

    python benchmarks/fit_com1093.py [--out DIR] [--filters F480M ...]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(os.environ.get("AMIGO_SHARED", Path(__file__).resolve().parents[2] / "shared"))
DATA = DATA / "data" / "jwst" / "com1093"
PAIRS = {  # filter: (science, calibrator)
    "F480M": ("jw01093012001_03102_00001_nis_cal.fits", "jw01093015001_03102_00001_nis_cal.fits"),
    "F430M": ("jw01093012001_03103_00001_nis_cal.fits", "jw01093015001_03103_00001_nis_cal.fits"),
    "F380M": ("jw01093012001_03104_00001_nis_cal.fits", "jw01093015001_03104_00001_nis_cal.fits"),
}
SEP_MAS, PA_DEG = 328.85, 280.5
DMAG = {"F380M": 4.313, "F430M": 4.354, "F480M": 4.381}


def binary_chi2(calvis, sep_mas: float, pa_deg: float, dmag: float) -> float:
    from amigo.model.visibility import binary_log_visibility
    from amigo.orientation import offset_from_separation_pa

    dra, ddec = offset_from_separation_pa(sep_mas, pa_deg)
    theta_rad = calvis.sky_to_uv @ np.array([dra, ddec]) * np.pi / 180 / 3600 / 1000
    contrast = 10 ** (-dmag / 2.5)
    log_amp, phase = binary_log_visibility(
        calvis.uv_m, calvis.wavelengths_m, calvis.weights, theta_rad, contrast
    )
    r = (calvis.values - calvis.disco_matrix @ np.concatenate([log_amp, phase])) / calvis.errors
    return float(r @ r)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("com1093_fit"))
    parser.add_argument("--filters", nargs="*", default=list(PAIRS))
    args = parser.parse_args()
    from amigo.io.calvis import read_calvis

    rows, exposures = [], []
    for filter_name in args.filters:
        sci, cal = PAIRS[filter_name]
        out = args.out / filter_name
        start = time.perf_counter()
        subprocess.run(
            [
                sys.executable,
                "-m",
                "amigo",
                "fit",
                "--sci",
                str(DATA / sci),
                "--cal",
                str(DATA / cal),
                "--out",
                str(out),
            ],
            check=True,
        )
        seconds = time.perf_counter() - start
        calvis = read_calvis(out / f"AB-DOR_{filter_name}_calvis.fits")
        n = calvis.n_obs
        point = float(np.sum((calvis.values / calvis.errors) ** 2))
        binary = binary_chi2(calvis, SEP_MAS, PA_DEG, DMAG[filter_name])
        rows.append((filter_name, n, point / n, binary / n, seconds))
        exposures += json.loads((out / "fit_summary.json").read_text())["exposures"]
    print(
        f"\n{'filter':7s} {'n_disco':>8s} {'chi2r point':>12s} {'chi2r binary':>13s} {'seconds':>8s}"
    )
    for f, n, p, b, s in rows:
        print(f"{f:7s} {n:8d} {p:12.2f} {b:13.2f} {s:8.0f}")
    print(f"\n{'file':42s} {'role':10s} {'filter':6s} {'chi2/dof':>9s} {'zscore_std':>10s} conv it")
    for e in exposures:
        if e.get("zscore_std") is None:  # excluded or failed: no fit to report
            print(f"{e['file']:42s} {e['role']:10s} {e['filter']:6s} {e['status']}: {e['problem']}")
            continue
        print(
            f"{e['file']:42s} {e['role']:10s} {e['filter']:6s} {e['chi2'] / e['dof']:9.3f} "
            f"{e['zscore_std']:10.3f} {e['converged']!s:5s} {e['iterations']}"
        )


if __name__ == "__main__":
    main()
