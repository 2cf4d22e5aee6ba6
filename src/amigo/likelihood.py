"""Gaussian pixel likelihood of level-2 images, and the data it is evaluated on.

A level-2 product (``_cal``: one image; ``_calints`` / ``_rateints``: one image per
integration) is reduced to one 80 x 80 image in DN/s with per-pixel 1-sigma errors and a
mask of the pixels the likelihood may use. Pixels are excluded when they are reference
pixels (the 4 bottom rows of SUB80), flagged ``DO_NOT_USE`` in DQ, non-finite, or have a
non-positive error (all handled by :func:`amigo.io.jwst.read_exposure`'s ``usable``).

Per-integration products are averaged over their usable integrations (plain mean; the
error of the mean is ``sqrt(sum err_i^2) / n``): the forward model of a level-2 image is
static, so the mean carries all the information of a Gaussian likelihood with the
STScI errors, at 1/nints of the cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from amigo.errors import InputError
from amigo.io.jwst import Exposure

#: Minimum number of usable pixels for an exposure to be fitted.
MIN_PIXELS = 100


@dataclass(frozen=True)
class ImageData:
    """One exposure as the likelihood sees it (NumPy, float64).

    Attributes
    ----------
    data, error
        (80, 80) image and 1-sigma errors, DN/s. Values at masked pixels are finite
        placeholders (0 and 1) and never used.
    mask
        (80, 80) True where the pixel is used.
    n_integrations
        Integrations averaged into ``data`` (1 for ``_cal``).
    """

    data: np.ndarray
    error: np.ndarray
    mask: np.ndarray
    n_integrations: int = 1

    @property
    def n_pixels(self) -> int:
        return int(self.mask.sum())

    @classmethod
    def from_exposure(cls, exposure: Exposure) -> ImageData:
        """Reduce a level-2 :class:`~amigo.io.jwst.Exposure` to one image."""
        meta = exposure.meta
        if meta.is_ramp:
            raise InputError(meta.path, "is a raw ramp (uncal): run 'amigo process' first")
        if exposure.err is None:
            raise InputError(meta.path, "has no ERR extension: pixel errors are needed")
        data, err, usable = exposure.data, exposure.err, exposure.usable
        if data.ndim == 2:
            data, err, usable = data[None], err[None], usable[None]
        n_used = usable.sum(axis=0)
        safe_data = np.where(usable, data, 0.0)
        safe_err = np.where(usable, err, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = safe_data.sum(axis=0) / n_used
            sigma = np.sqrt((safe_err**2).sum(axis=0)) / n_used
        mask = n_used > 0
        mask &= np.isfinite(mean) & np.isfinite(sigma) & (sigma > 0)
        if mask.sum() < MIN_PIXELS:
            raise InputError(
                meta.path, f"only {int(mask.sum())} usable pixels (at least {MIN_PIXELS} needed)"
            )
        return cls(
            data=np.where(mask, mean, 0.0),
            error=np.where(mask, sigma, 1.0),
            mask=mask,
            n_integrations=int(data.shape[0]),
        )


class PixelData(eqx.Module):
    """The arrays of :class:`ImageData` as a JAX pytree, for the jitted loss.

    Attributes
    ----------
    data, inverse_sigma
        (80, 80) data (DN/s) and ``mask / error`` (zero where masked).
    """

    data: Float[Array, "ny nx"]
    inverse_sigma: Float[Array, "ny nx"]

    @classmethod
    def from_image(cls, image: ImageData, dtype=jnp.float32) -> PixelData:
        inv = np.where(image.mask, 1.0 / image.error, 0.0)
        return cls(jnp.asarray(image.data, dtype), jnp.asarray(inv, dtype))

    @property
    def mask(self) -> Bool[Array, "ny nx"]:
        return self.inverse_sigma > 0


def residuals(model: Float[Array, "ny nx"], pixels: PixelData) -> Float[Array, "ny nx"]:
    """Normalised residuals ``(data - model) / sigma`` (zero at masked pixels)."""
    return (pixels.data - model) * pixels.inverse_sigma


def chi2(model: Float[Array, "ny nx"], pixels: PixelData) -> Float[Array, ""]:
    """``sum ((data - model) / sigma)^2`` over the used pixels."""
    r = residuals(model, pixels)
    return jnp.sum(r * r)


def log_likelihood(model: Float[Array, "ny nx"], pixels: PixelData) -> Float[Array, ""]:
    """Gaussian log-likelihood up to a constant: ``-chi2 / 2``."""
    return -0.5 * chi2(model, pixels)
