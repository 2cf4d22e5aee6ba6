"""How much of a level-2 fit's misfit is 1/f column stripes (prints a table).

    python benchmarks/column_stripes.py [--sci FILE...] [--cal FILE...] [--out DIR]

The STScI pipeline leaves the read-out's 1/f noise in a level-2 image: each column (the
detector's fast-read direction is along a column of the image as JWST writes it) carries
one offset per group read, and the ramp fit turns them into one offset per column of
the slope image. ``amigo fit`` treats pixels as independent, so stripes count as misfit
and their shared part is not in the DISCOs' errors. This script fits the files with
``amigo.fit`` (the defaults: the shipped real-data model and its detector) and measures,
per exposure, on the whitened residuals ``z = (data - model) / ERR``:

* ``z std``: as ``fit_summary.json`` reports it;
* ``col`` / ``row``: the standard deviation over columns (rows) of ``sum(z) / sqrt(n)``
  over the column's halo pixels (beyond 25 pixels from the peak), 1 for independent
  errors; ``col`` alone well above 1 is stripes;
* ``- cols`` / ``- rows``: the z std once each column (row) has its weighted mean
  residual taken off, ``sum(z^2) / (n - 80)``: what free per-column offsets would leave,
  an upper bound on what a stripe model can gain at this fit (no refit);
* ``stripes``: the rms of those column offsets beyond what the noise alone would give
  (DN/s);
* ``k=16`` / ``k=40``: along a column, the mean product of neighbouring columns' halo
  differences ``d(y) = r_(c+1)(y) - r_c(y)`` at a lag of 16 (40) rows over its value at
  1 row: how fast the stripes decorrelate (1: one offset per column);
* ``tau`` / ``ell``: the stripes' width (DN/s) and correlation length (rows) as the fit
  measures them (:func:`amigo.likelihood.stripes.stripe_covariance`);
* ``dlogL``: the residuals' marginal log-likelihood under that Gaussian process minus
  its largest under one offset per column (widths 0.1-3 times ``tau``; positive: the
  process describes the residuals better, though its own two numbers are measured,
  not fitted for the likelihood).

The default files: AB Dor (COM 1093 obs 12, F480M at 5 and 13 groups) against the five
dithers of HD 37093 obs 17, a dithered-calibrator pair (AB Dor is in no training set;
obs 17 is). Not a test: nothing is asserted. About two minutes on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np

SHARED = Path(os.environ.get("AMIGO_SHARED", Path(__file__).resolve().parents[2] / "shared"))
JWST = SHARED / "data" / "jwst"
SCIENCE = [JWST / "com1093" / f"jw01093012001_{e}_00001_nis_cal.fits" for e in ("03102", "03105")]
CALIBRATORS = [
    JWST / "com1093-calibrators" / f"jw01093017001_03102_0000{k}_nis_cal.fits" for k in range(1, 6)
]
#: Halo: pixels farther than this from the model's peak (pixels).
HALO_PIX = 25.0


def line_scores(z: np.ndarray, used: np.ndarray, axis: int) -> np.ndarray:
    """``sum(z) / sqrt(n)`` over the used pixels of each column (``axis=0``) or row
    (``axis=1``) with at least 10 of them; 1 in standard deviation for independent z."""
    n = used.sum(axis=axis)
    total = np.where(used, z, 0.0).sum(axis=axis)
    keep = n >= 10
    return total[keep] / np.sqrt(n[keep])


def without_lines(
    residual: np.ndarray, inverse_sigma: np.ndarray, axis: int
) -> tuple[float, np.ndarray, np.ndarray]:
    """z std after each column (``axis=0``) or row (``axis=1``) has its inverse-variance
    weighted mean residual removed, with the lines' offsets (DN/s) and their errors."""
    weight = inverse_sigma**2
    used = weight > 0
    total = weight.sum(axis=axis)
    has = total > 0
    offsets = np.where(has, (weight * residual).sum(axis=axis) / np.where(has, total, 1.0), 0.0)
    errors = np.where(has, 1.0 / np.sqrt(np.where(has, total, 1.0)), np.inf)
    shifted = residual - (offsets[None, :] if axis == 0 else offsets[:, None])
    z = shifted * inverse_sigma
    dof = used.sum() - int(has.sum())
    return float(np.sqrt(np.sum(z[used] ** 2) / dof)), offsets[has], errors[has]


def log_likelihood(
    residual: np.ndarray, inverse_sigma: np.ndarray, tau: float, length: float
) -> float:
    """Marginal log-likelihood (up to a constant) of ``residual`` (ny, nx) with each
    column's covariance ``diag(err^2) + tau^2 exp(-|y - y'| / length)`` over its used
    pixels (dense, column by column)."""
    from amigo.likelihood.stripes import stripe_kernel

    kernel = stripe_kernel(residual.shape[0], length)
    total = 0.0
    for c in range(residual.shape[1]):
        used = inverse_sigma[:, c] > 0
        if not used.any():
            continue
        cov = np.diag(1.0 / inverse_sigma[used, c] ** 2) + tau**2 * kernel[np.ix_(used, used)]
        factor = np.linalg.cholesky(cov)
        w = np.linalg.solve(factor, residual[used, c])
        total += -0.5 * float(w @ w) - float(np.sum(np.log(np.diag(factor))))
    return total


def main() -> None:
    import amigo

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sci", nargs="+", type=Path, default=SCIENCE)
    parser.add_argument("--cal", nargs="+", type=Path, default=CALIBRATORS)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    missing = [p for p in [*args.sci, *args.cal] if not p.exists()]
    if missing:
        raise SystemExit(f"not found: {missing[0]} (set AMIGO_SHARED or give --sci/--cal)")
    out = args.out or Path(tempfile.mkdtemp(prefix="column_stripes_"))
    fitted = amigo.fit(sci=args.sci, cal=args.cal, out=out, force=True)
    from amigo.likelihood.stripes import halo_lag_products, stripe_covariance

    print(f"\n{'exposure':<40} {'role':<10} {'z std':>6} {'col':>5} {'row':>5} "
          f"{'- cols':>6} {'- rows':>6} {'stripes':>8} {'k=16':>5} {'k=40':>5} "
          f"{'tau':>6} {'ell':>6} {'dlogL':>7}")  # fmt: skip
    for name, product in fitted.products.items():
        fit = product.fit
        data = np.asarray(fit.pixels.data, np.float64)
        inverse_sigma = np.asarray(fit.pixels.inverse_sigma, np.float64)
        for e, exposure in enumerate(fit.exposures):
            residual = data[e] - product.models[e]
            used = inverse_sigma[e] > 0
            z = residual * inverse_sigma[e]
            peak = np.unravel_index(np.argmax(product.models[e]), residual.shape)
            y, x = np.indices(residual.shape)
            halo = used & (np.hypot(y - peak[0], x - peak[1]) > HALO_PIX)
            col = np.std(line_scores(z, halo, axis=0))
            row = np.std(line_scores(z, halo, axis=1))
            no_cols, offsets, errors = without_lines(residual, inverse_sigma[e], axis=0)
            no_rows, _, _ = without_lines(residual, inverse_sigma[e], axis=1)
            stripes = np.sqrt(max(np.mean(offsets**2 - errors**2), 0.0))
            star = (int(peak[0]), int(peak[1]))
            products, _, _ = halo_lag_products(residual, inverse_sigma[e], star, [1, 16, 40])
            one, at16, at40 = products
            tau, ell = stripe_covariance(residual, inverse_sigma[e], star)
            gain = np.nan
            if tau > 0:  # against the likeliest width of one offset per column
                flat = max(
                    log_likelihood(residual, inverse_sigma[e], width, np.inf)
                    for width in tau * np.geomspace(0.1, 3.0, 13)
                )
                gain = log_likelihood(residual, inverse_sigma[e], tau, ell) - flat
            print(f"{exposure.name[:40]:<40} {exposure.role:<10} {np.std(z[used]):6.3f} "
                  f"{col:5.2f} {row:5.2f} {no_cols:6.3f} {no_rows:6.3f} {stripes:8.3f} "
                  f"{at16 / one:5.2f} {at40 / one:5.2f} {tau:6.3f} {ell:6.1f} {gain:7.1f}"
                  f"  ({name})")  # fmt: skip


if __name__ == "__main__":
    main()
