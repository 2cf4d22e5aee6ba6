"""Gaussian likelihoods of images (level 2) and of up-the-ramp slopes (calslope).

Both are written as *whitened residuals* ``z`` (unit-variance, independent under the noise
model), because the same ``z`` gives the log-likelihood ``-0.5 * sum(z**2) + const``, the
chi-square, and the z-score standard deviation reported in ``fit_summary.json``.

Slopes of one pixel are correlated: adjacent group differences share a read, so read noise
makes them anti-correlated (``-sigma_read**2``) and photon noise accumulated in a group is
independent. calslope files carry the full covariance of the mean slopes per pixel
(``SLOPE_COV``, (m, m, ny, nx) with m = ngroups - 1); :class:`SlopeNoise` factorises it once
(float64, NumPy) into per-pixel whitening matrices ``W = L^-1`` with ``C = L L^T``, so that
inside a fit whitening is one batched mat-vec.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

LOG_2PI = float(np.log(2.0 * np.pi))


@dataclass(frozen=True)
class SlopeNoise:
    """Noise model of the mean slopes of one exposure.

    Attributes
    ----------
    pixels
        (n,) flat indices (``y * nx + x``) of the pixels used.
    whitening
        (n, m, m) lower-triangular ``L^-1`` per used pixel (or diagonal ``1/sigma``).
    log_det
        Sum over used pixels of ``log det C`` (for the normalised log-likelihood).
    shape
        (m, ny, nx) of the slope arrays.
    """

    pixels: np.ndarray
    whitening: np.ndarray
    log_det: float
    shape: tuple[int, int, int]

    @classmethod
    def from_covariance(
        cls,
        slope_cov: np.ndarray,
        bad: np.ndarray | None = None,
        diagonal: bool = False,
        structure: str = "full",
    ) -> SlopeNoise:
        """Build from ``SLOPE_COV`` (m, m, ny, nx) and an optional bad-pixel map (ny, nx).

        Pixels whose covariance is not finite or not positive definite are dropped.

        ``structure`` says how much of the sample covariance to trust:

        * ``"full"``: as is (the paper's choice, right for thousands of integrations);
        * ``"diagonal"`` (or ``diagonal=True``): ignore correlations between slopes;
        * ``"pooled"``: a structured estimate for few integrations. A sample covariance
          from n integrations of m slopes is singular for n <= m and its inverse is biased
          high by (n - 1) / (n - m - 2) (Wishart). Here each pixel keeps one variance (the
          mean of its diagonal) and every pixel shares one adjacent-slope covariance (read
          noise makes it ``-sigma_read^2 / n``; the median over pixels), zero beyond.
        """
        if diagonal:
            structure = "diagonal"
        if structure not in ("full", "diagonal", "pooled"):
            raise ValueError(f"unknown covariance structure {structure!r}")
        cov = np.asarray(slope_cov, dtype=np.float64)
        m, m2, ny, nx = cov.shape
        if m != m2:
            raise ValueError(f"SLOPE_COV must be (m, m, ny, nx), got {cov.shape}")
        per_pixel = cov.reshape(m, m, ny * nx).transpose(2, 0, 1)  # (npix, m, m)
        if structure == "diagonal":
            per_pixel = per_pixel * np.eye(m)[None]
        elif structure == "pooled":
            variance = np.diagonal(per_pixel, axis1=1, axis2=2).mean(axis=1)  # (npix,)
            adjacent = np.diagonal(per_pixel, offset=1, axis1=1, axis2=2).mean(axis=1)
            usable = np.isfinite(adjacent) if bad is None else np.isfinite(adjacent) & ~bad.ravel()
            shared = float(np.median(adjacent[usable])) if m > 1 and usable.any() else 0.0
            band = np.eye(m, k=1) + np.eye(m, k=-1)
            per_pixel = variance[:, None, None] * np.eye(m)[None] + shared * band[None]
        keep = np.all(np.isfinite(per_pixel), axis=(1, 2))
        if bad is not None:
            keep &= ~np.asarray(bad, dtype=bool).reshape(-1)
        variances = np.diagonal(per_pixel, axis1=1, axis2=2)
        keep &= np.all(variances > 0, axis=1)
        pixels = np.nonzero(keep)[0]
        chol = np.zeros((len(pixels), m, m))
        ok = np.ones(len(pixels), dtype=bool)
        for start in range(0, len(pixels), 4096):
            block = per_pixel[pixels[start : start + 4096]]
            try:
                chol[start : start + len(block)] = np.linalg.cholesky(block)
            except np.linalg.LinAlgError:  # find the offending pixels one by one
                for i, c in enumerate(block):
                    try:
                        chol[start + i] = np.linalg.cholesky(c)
                    except np.linalg.LinAlgError:
                        ok[start + i] = False
        pixels, chol = pixels[ok], chol[ok]
        whitening = np.linalg.inv(chol)
        log_det = float(2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum())
        return cls(pixels=pixels, whitening=whitening, log_det=log_det, shape=(m, ny, nx))

    @property
    def n_values(self) -> int:
        """Number of slope values in the likelihood."""
        return int(self.whitening.shape[0] * self.whitening.shape[1])

    def zscores(
        self, model: Float[Array, "m ny nx"], data: Float[Array, "m ny nx"]
    ) -> Float[Array, "n m"]:
        """Whitened residuals ``W (data - model)`` for the used pixels, shape (n, m)."""
        m = self.shape[0]
        residual = (data - model).reshape(m, -1).T[self.pixels]  # (n, m)
        return jnp.einsum("nij,nj->ni", jnp.asarray(self.whitening, residual.dtype), residual)

    def log_likelihood(self, model: Array, data: Array) -> Array:
        """Normalised Gaussian log-likelihood of the slopes."""
        z = self.zscores(model, data)
        return -0.5 * (jnp.sum(z**2) + self.log_det + self.n_values * LOG_2PI)


def image_zscores(
    model: Float[Array, "... ny nx"],
    data: Float[Array, "... ny nx"],
    err: Float[Array, "... ny nx"],
    usable: np.ndarray,
) -> Array:
    """Residuals over errors of the usable pixels, flattened: (n_usable,)."""
    mask = np.asarray(usable, dtype=bool)
    return ((data - model) / jnp.where(mask, err, 1.0))[mask]


def image_log_likelihood(model: Array, data: Array, err: Array, usable: np.ndarray) -> Array:
    """Normalised Gaussian log-likelihood of an image with independent pixel errors."""
    mask = np.asarray(usable, dtype=bool)
    z = image_zscores(model, data, err, mask)
    log_det = 2.0 * float(np.log(np.asarray(err)[mask]).sum())
    return -0.5 * (jnp.sum(z**2) + log_det + z.size * LOG_2PI)
