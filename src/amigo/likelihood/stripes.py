"""1/f column stripes of level-2 images, marginalised in the pixel likelihood.

The read-out's 1/f noise adds to every read of a column (the fast-read direction runs
along a column of the image as JWST writes it) one offset, nearly constant along it; the
pipeline's ramp fit turns each column's offsets into one offset of the slope image. A
level-2 image keeps them (``amigo process`` removes them from raw ramps, docs/process.md):
on the real COM 1093 files the halo's column sums scatter 2.2-4.1 times as much as
independent errors allow, the rows' as they should (docs/fidelity.md, "1/f stripes").

**Model.** Each column ``c`` of an exposure has an offset ``b_c ~ N(0, tau^2)`` (DN/s),
independent between columns and exposures, added to every pixel of the column. The
pixels' covariance is then, column by column, ``C = D + tau^2 1 1^T`` with ``D =
diag(err^2)``: marginalised exactly, with no parameter to fit.

**Whitening.** The likelihood works with whitened vectors (``v = (data - model) / err``
and the Jacobian's columns divided by ``err``). With ``a = 1 / err`` over the column's
used pixels (0 where masked) and ``s = a^T a``, the symmetric square root of ``D^(1/2)
C^-1 D^(1/2)`` is ``I - gamma a a^T / s`` with ``gamma = 1 - 1 / sqrt(1 + tau^2 s)``
(Sherman-Morrison). :func:`decorrelate` applies it: ``v - a (k a^T v)``, ``k = gamma /
s`` per column. Applied alike to residuals and Jacobians it gives ``|r'|^2 = r^T C^-1 r``,
``J'^T J' = J^T C^-1 J`` and ``J'^T r' = J^T C^-1 r``: the fit's Gauss-Newton algebra is
unchanged, and the latent Hessians (the DISCOs' covariances) count what the stripes
share along a column. ``tau = 0`` leaves every vector as it is; ``tau -> inf`` removes
each column's weighted mean (free offsets).

**How wide.** ``tau`` is measured per exposure from a model's residuals in the halo (far
from the star, where the model's own errors are smallest), wherever the fit's solver
takes new Jacobians (:meth:`amigo.fitting.newton._Problem.refresh`; the first time at the
start, the last near the optimum): each column's weighted mean residual ``m_c`` (error
``e_c``), and the
differences of neighbouring columns ``d_c = m_(c+1) - m_c``, which scatter by ``2 tau^2 +
e_c^2 + e_(c+1)^2``: ``tau^2 = mean(d_c^2 - e_c^2 - e_(c+1)^2) / 2``
(:func:`stripe_sigma`). The differences, not the means: the stripes are independent from
column to column, a model's errors in the halo vary more smoothly across columns.
Measured on the real COM 1093 files (three filters, AB Dor and HD 37093), against the
column means at the fit's optimum: at the start the column means gave 1.4-2.4 times as
much, the differences 0.8-1.5 times (docs/fidelity.md). Kept only when significant (3
standard errors under pure noise); otherwise 0, as for images without stripes
(simulations, ``amigo process``'s slopes). A model far from the data (a nominal
instrument on real images) has misfit that varies across columns too, and part of it is
taken for stripes (docs/fidelity.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

#: Halo: pixels farther than this from the star (pixels) measure the stripes.
HALO_RADIUS_PIX = 25.0
#: Fewest halo pixels for a column to count in the estimate.
MIN_HALO_PIXELS = 10
#: Significance (standard errors of the estimate under pure noise) for stripes to be kept.
DETECTION_SIGMAS = 3.0


def column_gains(inverse_sigma: npt.ArrayLike, tau_dn_s: npt.ArrayLike) -> np.ndarray:
    """(..., nx) ``k = gamma / s`` of every column (module notes), float64.

    ``inverse_sigma``: (..., ny, nx) ``mask / err`` (DN/s)^-1, 0 where masked;
    ``tau_dn_s``: (...) the stripes' standard deviation (DN/s) of each image.
    """
    a = np.asarray(inverse_sigma, np.float64)
    tau = np.asarray(tau_dn_s, np.float64)[..., None]
    s = np.sum(a * a, axis=-2)
    gamma = 1.0 - 1.0 / np.sqrt(1.0 + tau**2 * s)
    return np.where(s > 0, gamma / np.where(s > 0, s, 1.0), 0.0)


def decorrelate(whitened: Any, inverse_sigma: Any, gains: Any) -> Any:
    """``v - a (k a^T v)`` column by column (module notes): whitened vectors (..., ny, nx)
    whitened again for their images' stripes. NumPy or JAX arrays alike;
    ``inverse_sigma`` (..., ny, nx) and ``gains`` (..., nx) (:func:`column_gains`) of the
    images, broadcast against ``whitened`` (one image's for a stack of Jacobian columns)."""
    shared = (inverse_sigma * whitened).sum(axis=-2, keepdims=True)
    return whitened - inverse_sigma * (gains[..., None, :] * shared)


def stripe_sigma(
    residual_dn_s: npt.ArrayLike, inverse_sigma: npt.ArrayLike, star_yx: tuple[float, float]
) -> float:
    """The stripes' standard deviation ``tau`` (DN/s) of one (ny, nx) image from its
    residual ``data - model`` (DN/s) in the halo around ``star_yx`` (pixels, (y, x)); 0
    when the columns scatter as their errors say (module notes)."""
    r = np.asarray(residual_dn_s, np.float64)
    a = np.asarray(inverse_sigma, np.float64)
    y, x = np.indices(r.shape)
    halo = (a > 0) & (np.hypot(y - star_yx[0], x - star_yx[1]) > HALO_RADIUS_PIX)
    w = np.where(halo, a * a, 0.0)
    total = w.sum(axis=0)
    keep = (halo.sum(axis=0) >= MIN_HALO_PIXELS) & (total > 0)
    means = np.where(keep, (w * r).sum(axis=0) / np.where(keep, total, 1.0), np.nan)
    variances = np.where(keep, 1.0 / np.where(keep, total, 1.0), np.nan)  # e_c^2
    pairs = keep[1:] & keep[:-1]  # neighbouring columns that both count
    if not pairs.any():
        return 0.0
    d = (means[1:] - means[:-1])[pairs]
    noise = (variances[1:] + variances[:-1])[pairs]
    excess = float(np.mean(d**2 - noise)) / 2.0
    # Under pure noise each d_c^2 - noise_c has variance 2 noise_c^2, and neighbouring
    # differences share a column (correlation 1/2 between them, 1/4 between squares):
    # 1.5 times the variance of independent terms, to first order.
    standard_error = float(np.sqrt(3.0 * np.sum(noise**2))) / int(pairs.sum()) / 2.0
    if excess <= DETECTION_SIGMAS * standard_error:
        return 0.0
    return float(np.sqrt(excess))


def decorrelate_rows(
    rows: np.ndarray, inverse_sigma: np.ndarray, gains: np.ndarray, chunk: int = 64
) -> None:
    """:func:`decorrelate` in place on (k, ny * nx) float64 rows of one image (whitened
    Jacobian columns), ``chunk`` rows at a time: a real fit's ~1000 rows of 6400 pixels
    are ~50 MB, and a temporary copy of all of them is what the fit's memory cannot
    spare (docs/performance.md). ``inverse_sigma`` (ny * nx,) or (ny, nx), ``gains``
    (nx,)."""
    if not np.any(gains):
        return
    a = np.asarray(inverse_sigma, np.float64).reshape(-1, gains.size)
    for start in range(0, len(rows), chunk):
        block = rows[start : start + chunk].reshape(-1, *a.shape)  # a view: rows are C-ordered
        shared = np.einsum("kyx,yx->kx", block, a)
        block -= a * (gains * shared)[:, None, :]
