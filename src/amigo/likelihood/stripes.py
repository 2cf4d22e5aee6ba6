"""1/f column stripes of level-2 images, marginalised in the pixel likelihood.

The read-out's 1/f noise adds to every read of a column (the fast-read direction runs
along a column of the image as JWST writes it) one offset, nearly constant along it; the
pipeline's ramp fit turns each column's offsets into one offset of the slope image. A
level-2 image keeps them (``amigo process`` removes them from raw ramps, docs/process.md):
on the real COM 1093 files the halo's column sums scatter 2.2-4.1 times as much as
independent errors allow, the rows' as they should (docs/fidelity.md, "1/f stripes").

**Model.** Each column ``c`` of an exposure carries a stripe ``b_c(y)`` (DN/s) added to
its pixels, independent between columns and exposures, and correlated along the column
by an exponential kernel: ``cov(b_c(y), b_c(y')) = tau^2 exp(-|y - y'| / ell)``. The
stripes are not one offset per whole column: in the halo residuals of real fits the
upper and lower halves of a column correlate weakly, and the correlation of two rows
falls over ~7-40 rows (docs/fidelity.md). ``ell -> inf`` is one offset per column. The
pixels' covariance is then, column by column, ``C = D + tau^2 K`` with ``D =
diag(err^2)``: marginalised exactly, with no parameter to fit.

**Whitening.** The likelihood works with whitened vectors (``v = (data - model) / err``
and the Jacobian's columns divided by ``err``). With ``A = diag(1 / err)`` over the
column's pixels (0 where masked) and ``M = D^(-1/2) C D^(-1/2) = I + tau^2 A K A``, the
column's whitener is the symmetric ``W = M^(-1/2)`` (:func:`column_whiteners`; a masked
pixel's row and column of ``M`` are the identity's, so it stays 0 and touches nothing).
Symmetric, so that applied twice it is ``M^-1``: the fit's gradient ``J^T C^-1 r``
whitens the whitened residuals once more
(:meth:`amigo.fitting.newton._Problem.gradient`); a Cholesky factor's inverse would need
its transpose there. :func:`decorrelate` applies ``W`` to every column of whitened
images. Applied alike to residuals and Jacobians it gives ``|r'|^2 = r^T C^-1 r``,
``J'^T J' = J^T C^-1 J`` and ``J'^T r' = J^T C^-1 r``: the fit's Gauss-Newton algebra is
unchanged, and the latent Hessians (the DISCOs' covariances) count what the stripes
share along a column. ``tau = 0`` leaves every vector as it is.

**How wide, how long.** ``tau`` and ``ell`` are measured per exposure from a model's
residuals in the halo (far from the star, where the model's own errors are smallest),
wherever the fit's solver takes new Jacobians
(:meth:`amigo.fitting.newton._Problem.refresh`; the first time at the start, the last
near the optimum): the differences of neighbouring columns ``d(y) = r_(c+1)(y) -
r_c(y)`` remove what a model's errors share across columns (they vary smoothly there)
and keep ``2 tau^2 exp(-lag / ell)`` as the covariance of ``d(y)`` and ``d(y + lag)``.
Their mean products (:func:`halo_lag_products`) at lags 1 to :data:`MAX_LAG` rows, each
with its standard error under pure noise, are fitted by weighted least squares over a
grid of ``ell`` (``tau^2`` in closed form at each) (:func:`stripe_covariance`). Lag 0 is
left out: it would need the pixels' variance, and the pipeline's ERR is not that to the
percent (on HD 36805 it exceeds the scatter); the standard errors come from the products
themselves, for the same reason. The stripes are kept only when ``tau^2`` is significant
(:data:`DETECTION_SIGMAS` standard errors; the largest of the grid's ``ell``, so a
little more often than one test at that level: tests/test_stripes.py counts white-noise
images); otherwise 0, as for images without stripes (simulations, ``amigo process``'s
slopes). A model far from the data (a nominal instrument on real images) has misfit that
varies across columns too, and part of it is taken for stripes (docs/fidelity.md)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

#: Halo: pixels farther than this from the star (pixels) measure the stripes.
HALO_RADIUS_PIX = 25.0
#: Longest lag (rows) of the covariances that measure the stripes.
MAX_LAG = 40
#: Fewest pairs of halo differences for a lag to count.
MIN_PAIRS = 50
#: Correlation lengths (rows) tried; the last is one offset per column to 1e-3 over 80 rows.
LENGTHS_PIX = np.geomspace(1.0, 1e5, 161)
#: Significance (standard errors of ``tau^2`` under pure noise) for stripes to be kept.
DETECTION_SIGMAS = 3.0


def stripe_kernel(rows: int, length_pix: float) -> np.ndarray:
    """(rows, rows) ``exp(-|y - y'| / ell)``: the stripes' correlation along a column
    (ones for ``ell = inf``: one offset per column)."""
    lag = np.abs(np.subtract.outer(np.arange(rows), np.arange(rows))).astype(np.float64)
    if not np.isfinite(length_pix):
        return np.ones_like(lag)
    return np.exp(-lag / float(length_pix))


def column_whiteners(
    inverse_sigma: npt.ArrayLike, tau_dn_s: npt.ArrayLike, length_pix: npt.ArrayLike
) -> np.ndarray:
    """(E, nx, ny, ny) float64 symmetric whitener ``W = M^(-1/2)`` of every column of
    every image (module notes); the identity where ``tau = 0``.

    ``inverse_sigma``: (E, ny, nx) ``mask / err`` (DN/s)^-1, 0 where masked;
    ``tau_dn_s``, ``length_pix``: (E,) the stripes' standard deviation (DN/s) and
    correlation length (rows) of each image.
    """
    a = np.asarray(inverse_sigma, np.float64)
    n_images, ny, nx = a.shape
    taus = np.broadcast_to(np.asarray(tau_dn_s, np.float64), (n_images,))
    lengths = np.broadcast_to(np.asarray(length_pix, np.float64), (n_images,))
    out = np.broadcast_to(np.eye(ny), (n_images, nx, ny, ny)).copy()
    for e in range(n_images):
        if taus[e] <= 0:
            continue
        columns = a[e].T  # (nx, ny)
        m = taus[e] ** 2 * stripe_kernel(ny, lengths[e]) * columns[:, :, None] * columns[:, None, :]
        m += np.eye(ny)
        values, vectors = np.linalg.eigh(m)  # values >= 1: M is I plus a covariance
        out[e] = (vectors / np.sqrt(values)[:, None, :]) @ np.swapaxes(vectors, -1, -2)
    return out


def decorrelate(whitened: Any, whiteners: Any) -> Any:
    """``W_c v_c`` for every column ``c`` (module notes): whitened vectors (..., ny, nx)
    whitened again for their images' stripes, with ``whiteners`` (..., nx, ny, ny)
    (:func:`column_whiteners`), broadcast against ``whitened`` (one image's for a stack
    of Jacobian columns). NumPy in, NumPy out; JAX (traced or not) in, JAX out."""
    if isinstance(whitened, np.ndarray) and isinstance(whiteners, np.ndarray):
        return np.einsum("...cyz,...zc->...yc", whiteners, whitened)
    import jax.numpy as jnp

    return jnp.einsum("...cyz,...zc->...yc", whiteners, whitened)


def halo_lag_products(
    residual_dn_s: npt.ArrayLike,
    inverse_sigma: npt.ArrayLike,
    star_yx: tuple[float, float],
    lags: list[int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each lag (rows): half the mean product of neighbouring columns' halo
    differences ``d(y) = r_(c+1)(y) - r_c(y)`` that far apart, (DN/s)^2 (``tau^2 exp(-lag
    / ell)`` for the stripes; module notes), its standard error under pure noise, and the
    number of products (NaN where there are none). ``residual_dn_s`` (ny, nx) ``data -
    model``; the halo lies beyond :data:`HALO_RADIUS_PIX` of ``star_yx`` (pixels, (y, x))."""
    r = np.asarray(residual_dn_s, np.float64)
    a = np.asarray(inverse_sigma, np.float64)
    y, x = np.indices(r.shape)
    halo = (a > 0) & (np.hypot(y - star_yx[0], x - star_yx[1]) > HALO_RADIUS_PIX)
    pair = halo[:, 1:] & halo[:, :-1]  # neighbouring columns that both count
    d = np.where(pair, r[:, 1:] - r[:, :-1], 0.0)
    means, errors, counts = [], [], []
    for lag in lags:
        n = int((pair[lag:] & pair[:-lag]).sum())
        products = d[lag:] * d[:-lag]
        # Under pure noise the products are independent along a column; neighbouring
        # column pairs share a column (products correlated by 1/4, as d's by -1/2):
        # 1.5 times the variance of independent terms. That variance from the products
        # themselves, not from ERR: an ERR too small would make false stripes
        # significant (1 % of white-noise images at 25 % too small, against 6-8 % from
        # ERR; measured in review).
        means.append(float(np.sum(products)) / n / 2.0 if n else np.nan)
        errors.append(float(np.sqrt(1.5 * np.sum(products**2))) / n / 2.0 if n else np.nan)
        counts.append(n)
    return np.array(means), np.array(errors), np.array(counts)


def stripe_covariance(
    residual_dn_s: npt.ArrayLike, inverse_sigma: npt.ArrayLike, star_yx: tuple[float, float]
) -> tuple[float, float]:
    """The stripes' standard deviation ``tau`` (DN/s) and correlation length ``ell``
    (rows) of one (ny, nx) image from its residual ``data - model`` (DN/s) in the halo
    around ``star_yx`` (pixels, (y, x)); ``(0, inf)`` when the columns scatter as their
    errors say (module notes)."""
    all_lags = np.arange(1, min(MAX_LAG, np.shape(residual_dn_s)[0] - 1) + 1)
    means, errors, counts = halo_lag_products(
        residual_dn_s, inverse_sigma, star_yx, all_lags.tolist()
    )
    keep = counts >= MIN_PAIRS
    if not keep.any():
        return 0.0, np.inf
    lag_array, c, w = all_lags[keep].astype(float), means[keep], 1.0 / errors[keep] ** 2
    kernels = np.exp(-lag_array[None, :] / LENGTHS_PIX[:, None])  # (lengths, lags)
    norms = kernels**2 @ w
    tau2 = np.maximum((kernels * w) @ c / norms, 0.0)
    misfit = ((c[None, :] - tau2[:, None] * kernels) ** 2) @ w
    best = int(np.argmin(misfit))
    if tau2[best] <= DETECTION_SIGMAS / np.sqrt(norms[best]):
        return 0.0, np.inf
    return float(np.sqrt(tau2[best])), float(LENGTHS_PIX[best])


def stripes_around_peak(
    residual_dn_s: npt.ArrayLike, inverse_sigma: npt.ArrayLike, model_dn_s: npt.ArrayLike
) -> tuple[float, float]:
    """:func:`stripe_covariance` of one (ny, nx) image with the star at the model's
    brightest used pixel (``inverse_sigma > 0``): how ``amigo fit`` and ``amigo train``
    place the halo. ``model_dn_s`` in any unit proportional to the image's."""
    a = np.asarray(inverse_sigma, np.float64)
    model = np.asarray(model_dn_s, np.float64)
    peak = np.unravel_index(np.argmax(np.where(a > 0, model, -np.inf)), model.shape)
    return stripe_covariance(residual_dn_s, a, (float(peak[0]), float(peak[1])))


def decorrelate_rows(rows: np.ndarray, whitener: np.ndarray, chunk: int = 64) -> None:
    """:func:`decorrelate` in place on (k, ny * nx) float64 rows of one image (whitened
    Jacobian columns), ``chunk`` rows at a time: a real fit's ~1000 rows of 6400 pixels
    are ~50 MB, and a temporary copy of all of them is what the fit's memory cannot
    spare (docs/performance.md). ``whitener`` (nx, ny, ny) of the image
    (:func:`column_whiteners`)."""
    nx, ny, _ = whitener.shape
    for start in range(0, len(rows), chunk):
        block = rows[start : start + chunk].reshape(-1, ny, nx)  # a view: rows are C-ordered
        if not np.shares_memory(block, rows):
            raise ValueError("decorrelate_rows needs C-ordered rows (it works in place)")
        # (nx, ny, ny) @ (nx, ny, k): one small matrix product per column.
        block[...] = np.matmul(whitener, block.transpose(2, 1, 0)).transpose(2, 1, 0)
