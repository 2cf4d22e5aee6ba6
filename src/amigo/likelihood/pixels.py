"""Gaussian likelihoods of level-2 images and of up-the-ramp slopes (calslope).

Images. A level-2 product (``_cal``: one image; ``_calints`` / ``_rateints``: one image per
integration) is reduced to one 80 x 80 image in DN/s with per-pixel 1-sigma errors and a
mask of the pixels the likelihood may use. Pixels are excluded when they are reference
pixels (the 4 bottom rows of SUB80), flagged ``DO_NOT_USE`` in DQ, non-finite, or have a
non-positive error (:func:`amigo.io.jwst.read_exposure`'s ``usable``); values flagged
``SATURATED`` too (:meth:`ImageData.from_exposure`: their slopes come from an unstated
number of groups).
Per-integration products are averaged over their usable integrations (plain mean; the
error of the mean is ``sqrt(sum err_i^2) / n``): the forward model of a level-2 image is
static, so the mean carries all the information of a Gaussian likelihood with the
STScI errors, at 1/nints of the cost.

Slopes. Both likelihoods are written with *whitened residuals* ``z`` (unit-variance,
independent under the noise model): the same ``z`` gives the log-likelihood, the
chi-square and the z-score standard deviation reported in ``fit_summary.json``. Slopes of
one pixel are correlated: adjacent group differences share a read, so read noise makes
them anti-correlated (``-sigma_read**2``) and photon noise accumulated in a group is
independent. calslope files carry the full covariance of the mean slopes per pixel
(``SLOPE_COV``, (m, m, ny, nx) with m = ngroups - 1); :class:`SlopeNoise` factorises it once
(float64, NumPy) into per-pixel whitening matrices ``W = L^-1`` with ``C = L L^T``, so that
inside a fit whitening is one batched mat-vec.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, Bool, Float

from amigo import niriss
from amigo.errors import InputError, TooFewPixels
from amigo.io.jwst import DQ_JUMP_DET, DQ_SATURATED, Exposure
from amigo.model.detector.pipeline_slope import (
    CHARGE_LOSS_THRESHOLD_1_12_DN,
    CHARGE_LOSS_THRESHOLD_DN,
    charge_loss_groups,
    group_times_s,
)

if TYPE_CHECKING:
    from amigo.io.calslope import CalSlope

LOG_2PI = float(np.log(2.0 * np.pi))

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
    whitened_slopes
        For an image reduced from a calslope file (:meth:`from_calslope`): (2, ny, nx, m)
        ``W 1`` and ``W s`` per pixel (``W`` the slopes' whitening matrix, ``s`` the
        slopes in DN per group; zero where masked), so that the slope-level residuals of
        any model image can be formed (:meth:`slope_zscores`). ``None`` otherwise.
    group_time_s
        Time per group (s) of the calslope file; 0 for level-2 images.
    """

    data: np.ndarray
    error: np.ndarray
    mask: np.ndarray
    n_integrations: int = 1
    whitened_slopes: np.ndarray | None = None
    group_time_s: float = 0.0

    @property
    def n_pixels(self) -> int:
        return int(self.mask.sum())

    @classmethod
    def from_exposure(cls, exposure: Exposure) -> ImageData:
        """Reduce a level-2 :class:`~amigo.io.jwst.Exposure` to one image: the mean of its
        integrations' usable values. A value the pipeline flagged SATURATED is not used:
        its slope comes from the groups before saturation, a number the file does not
        state, so no model of the ramp can be fitted to it as the pipeline fitted it."""
        meta = exposure.meta
        if meta.is_ramp:
            raise InputError(meta.path, "is a raw ramp (uncal): run 'amigo process' first")
        if exposure.err is None:
            raise InputError(meta.path, "has no ERR extension: pixel errors are needed")
        if not meta.in_dn_per_s:
            raise InputError(
                meta.path, f"BUNIT is {meta.bunit!r}: level-2 images in DN/s are needed"
            )
        data, err, usable = exposure.data, exposure.err, exposure.usable
        if exposure.dq is not None:
            usable = usable & ((exposure.dq & DQ_SATURATED) == 0)
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
            raise TooFewPixels(
                meta.path, f"only {int(mask.sum())} usable pixels (at least {MIN_PIXELS} needed)"
            )
        return cls(
            data=np.where(mask, mean, 0.0),
            error=np.where(mask, sigma, 1.0),
            mask=mask,
            n_integrations=int(data.shape[0]),
        )

    @classmethod
    def from_calslope(
        cls, product: CalSlope, group_time_s: float, structure: str = "auto", leading: int = 0
    ) -> ImageData:
        """Reduce a calslope product to the image of a linear detector, exactly.

        With linear charge accumulation every slope of a pixel has the same expectation
        ``r`` (DN per group), so the slope likelihood ``(s - r 1)^T C^-1 (s - r 1)`` is,
        up to a term that does not depend on ``r``, ``(r_hat - r)^2 / var`` with the
        generalised least-squares estimate ``r_hat = 1^T C^-1 s / 1^T C^-1 1`` and
        ``var = 1 / 1^T C^-1 1``. The image is ``r_hat / group_time_s`` in DN/s. The
        dropped term (the slopes' departure from a constant: non-linearity and
        brighter-fatter signal) is kept in :attr:`whitened_slopes` and added back by
        :meth:`slope_zscores`, so reported chi2 and z-scores are those of the slopes.

        ``structure`` is that of :meth:`SlopeNoise.from_covariance`; ``"auto"`` uses the
        full covariance when every slope was averaged over at least ``10 m`` integrations
        (``m`` slopes per pixel; a sample covariance from fewer is too noisy to invert),
        and the pooled estimate otherwise (see there). ``leading`` values of each pixel
        keep their own variance in the pooled estimate: 1 for a product whose first
        "slope" is the first group less the superbias
        (:func:`amigo.model.detector.reset.with_first_group`), whose variance holds the reset
        noise the slopes do not have.
        """
        path = product.path or "<calslope>"
        slopes = np.asarray(product.slope_dn, dtype=np.float64)
        m, ny, nx = slopes.shape
        if structure == "auto":
            structure = auto_structure(product)
        bad = product.unusable
        bad[: niriss.N_REFERENCE_ROWS] = True
        noise = SlopeNoise.from_covariance(
            product.slope_cov_dn2, bad=bad, structure=structure, leading=leading
        )
        if noise.pixels.size < MIN_PIXELS:
            raise TooFewPixels(
                path, f"only {noise.pixels.size} usable pixels (at least {MIN_PIXELS} needed)"
            )
        flat = slopes.reshape(m, -1).T[noise.pixels]  # (n, m)
        u = noise.whitening @ np.ones(m)  # (n, m): W 1
        v = np.einsum("nij,nj->ni", noise.whitening, flat)  # W s
        information = np.sum(u * u, axis=1)  # 1^T C^-1 1
        rate = np.sum(u * v, axis=1) / information
        data, error = np.zeros(ny * nx), np.ones(ny * nx)
        data[noise.pixels] = rate / group_time_s
        error[noise.pixels] = 1.0 / np.sqrt(information) / group_time_s
        mask = np.zeros(ny * nx, bool)
        mask[noise.pixels] = True
        whitened = np.zeros((2, ny * nx, m))
        whitened[0, noise.pixels], whitened[1, noise.pixels] = u, v
        support = np.asarray(product.slope_support)
        return cls(
            data=data.reshape(ny, nx),
            error=error.reshape(ny, nx),
            mask=mask.reshape(ny, nx),
            n_integrations=int(np.nanmax(support)) if support.size else 1,
            whitened_slopes=whitened.reshape(2, ny, nx, m),
            group_time_s=float(group_time_s),
        )

    def zscores(self, model: np.ndarray) -> np.ndarray:
        """Whitened residuals of a model image (DN/s) over the values in the likelihood.

        Pixels for a level-2 image, (n_pixels,); slopes for an image reduced from a
        calslope file, (n_pixels * m,) (see :meth:`from_calslope`).
        """
        model = np.asarray(model, dtype=np.float64)
        if self.whitened_slopes is None:
            return ((self.data - model) / self.error)[self.mask]
        u, v = self.whitened_slopes
        z = v - u * (model * self.group_time_s)[..., None]
        return z[self.mask].ravel()


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
    def from_image(cls, image: ImageData, dtype: DTypeLike = jnp.float32) -> PixelData:
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


def auto_structure(product: CalSlope) -> str:
    """The covariance structure a calslope product supports: ``"full"`` when every slope
    was averaged over at least ``10 m`` integrations (``m`` slopes per pixel), else
    ``"pooled"`` (a sample covariance from fewer is too noisy to invert; see
    :meth:`SlopeNoise.from_covariance`)."""
    m = np.asarray(product.slope_dn).shape[0]
    support = np.asarray(product.slope_support)[:, ~product.badpix]
    return "full" if support.size and np.nanmin(support) >= 10 * m else "pooled"


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
        leading: int = 0,
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
          noise makes it ``-sigma_read^2 / n``; the median over pixels), zero beyond. The
          first ``leading`` values keep their own variances, out of the mean (the first
          group's, which holds the reset noise; its covariance with the first slope is
          the same ``-sigma_read^2 / n``).
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
            variance = np.diagonal(per_pixel, axis1=1, axis2=2).copy()  # (npix, m)
            if m > leading:
                variance[:, leading:] = variance[:, leading:].mean(axis=1, keepdims=True)
            pairs = np.diagonal(per_pixel, offset=1, axis1=1, axis2=2)  # (npix, m - 1)
            if m - leading > 1:  # the slopes' own pairs, so the slope block is unchanged
                pairs = pairs[:, leading:]
            adjacent = pairs.mean(axis=1)
            usable = np.isfinite(adjacent) if bad is None else np.isfinite(adjacent) & ~bad.ravel()
            shared = float(np.median(adjacent[usable])) if m > 1 and usable.any() else 0.0
            band = np.eye(m, k=1) + np.eye(m, k=-1)
            per_pixel = variance[:, :, None] * np.eye(m)[None] + shared * band[None]
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


#: :attr:`PipelineGroups.source` where the threshold was read from the file's VAR_POISSON.
VARIANCE_SOURCE = "the file's VAR_POISSON"


@dataclass(frozen=True)
class PipelineGroups:
    """What the pipeline's charge-migration step left to the ramp fit of a level-2 image
    (:func:`pipeline_groups`).

    Attributes
    ----------
    groups
        (ny, nx) int, the leading groups of each pixel the ramp fit used; ``None`` where
        the step cut no ramp (the image is fitted as one without the step).
    threshold_dn
        The step's threshold the cut follows (DN); a lower bound where ``at_least``.
    source
        Where the threshold comes from: the step's default in the file's pipeline version,
        or the file's VAR_POISSON (:func:`threshold_from_poisson_variance`).
    at_least
        VAR_POISSON shows only that the threshold lies above every ramp the image holds.
    """

    groups: np.ndarray | None
    threshold_dn: float
    source: str
    at_least: bool = False

    def describe(self) -> str:
        """E.g. ``"threshold 25,000 DN, the step's default in jwst 1.16.0"``."""
        bound = "at least " if self.at_least else ""
        return f"threshold {bound}{self.threshold_dn:,.0f} DN, {self.source}"


def pipeline_groups(exposure: Exposure) -> PipelineGroups | None:
    """The leading groups of each pixel the pipeline's ramp fit used, for a level-2 image
    its charge-migration step ran on (``S_CHGMIG``); ``None`` for other images and ramps
    of 1 or 2 groups (which the step leaves alone).

    The step's rule (:func:`~amigo.model.detector.pipeline_slope.charge_loss_groups`)
    applied to the rates the file holds, whatever the pixels' flags (the step reads the
    ramps, not the pixel DQ, and a flagged pixel cuts its neighbours as well): each
    pixel's mean over the integrations of its finite values (one cut for all of a
    ``_calints``'s integrations, where the step cut each on its own); a pixel without
    one that the pipeline flagged SATURATED passed the threshold in its first group; any
    other (dead, or without a value for another reason) counts as dark. The threshold is
    the one the file's VAR_POISSON shows, where it shows another clearly, else the step's
    default in the file's CAL_VER (:func:`charge_loss_threshold_dn`).
    """
    meta = exposure.meta
    if not meta.charge_migration_flagged or meta.ngroups < 3:
        return None
    data = _by_integration(exposure.data)
    finite = np.isfinite(data)
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(finite, data, 0.0).sum(axis=0) / finite.sum(axis=0)
    if exposure.dq is not None:
        dq = _by_integration(exposure.dq)
        saturated = np.any((dq & DQ_SATURATED) != 0, axis=0)
        rate = np.where(~finite.any(axis=0) & saturated, np.inf, rate)
    cal_ver = str(meta.primary_header.get("CAL_VER", "")).strip()
    threshold = charge_loss_threshold_dn(cal_ver)
    source, at_least = f"the step's default in jwst {cal_ver or '(version unknown)'}", False
    measured = threshold_from_poisson_variance(exposure, rate, threshold)
    if measured is not None:
        threshold, at_least = measured
        source = VARIANCE_SOURCE
    used = charge_loss_groups(
        rate, meta.ngroups, meta.group_time_s, meta.frame_time_s, meta.nframes, threshold
    )
    # Nothing cut: the model as for a file without the step (one compiled program for both).
    cut = used if np.any(used < meta.ngroups) else None
    return PipelineGroups(cut, threshold, source, at_least)


#: Thresholds (DN) a file's VAR_POISSON is held against: the step's parameter can be set
#: by a CRDS parameter file and is not recorded in the level-2 file.
THRESHOLD_GRID_DN = np.arange(10000.0, 65001.0, 250.0)
#: Relative scatter of the groups a pixel's VAR_POISSON implies (its gain and flat against
#: the nominal, the pipeline's median rate against its fitted slope): 2-4 % measured on
#: the COM 1093 images' brightest pixels.
IMPLIED_GROUPS_SCATTER = 0.05
#: How much better (sum of squared, clipped residuals in units of that scatter) another
#: threshold must explain VAR_POISSON than the default for the cut to follow it.
THRESHOLD_EVIDENCE = 25.0
#: A threshold found within this fraction of the default is the default: the flat the
#: level-2 rates are divided by (a few per cent) moves the levels the rule compares by as
#: much, so VAR_POISSON cannot tell them apart.
THRESHOLD_RESOLUTION = 0.05


def threshold_from_poisson_variance(
    exposure: Exposure, rate_dn_s: np.ndarray, default_dn: float
) -> tuple[float, bool] | None:
    """The charge-migration threshold (DN) a level-2 image's VAR_POISSON shows, with
    whether it is only a lower bound, where it shows another than ``default_dn`` clearly;
    ``None`` otherwise (no VAR_POISSON, no pixel bright enough to tell, no clear
    preference, or one within :data:`THRESHOLD_RESOLUTION` of the default).

    The ramp fit's Poisson variance of a pixel is ``R / (g TGROUP (n - 1))`` per
    integration (stcal, :mod:`amigo.model.detector.pipeline_slope`) over the ``n`` groups
    it fitted, so ``rate / (g TGROUP VAR_POISSON)`` (divided by the integrations averaged
    for an exposure's image) is ``n - 1``. Each threshold of :data:`THRESHOLD_GRID_DN`
    predicts ``n`` per pixel through the step's rule; the one whose prediction fits the
    pixels that could be cut best (squared residuals in units of
    :data:`IMPLIED_GROUPS_SCATTER`, clipped at 4 of them against outliers; pixels with a
    jump left out: a jump shortens a segment) is taken if it beats ``default_dn`` by
    :data:`THRESHOLD_EVIDENCE`. Where the thresholds that fit best reach the top of the
    grid, VAR_POISSON shows only a lower bound (the lowest of them).
    """
    meta = exposure.meta
    if exposure.var_poisson is None:
        return None
    data, var = _by_integration(exposure.data), _by_integration(exposure.var_poisson)
    averaged = _integrations_averaged(meta) if exposure.data.ndim == 2 else 1
    with np.errstate(invalid="ignore", divide="ignore"):
        implied = data / (niriss.GAIN_E_PER_DN * meta.group_time_s * averaged * var)
        implied = np.where(np.isfinite(implied) & (implied > 0), implied, np.nan)
        counted = np.sum(np.isfinite(implied), axis=0)
        implied_mean = np.where(counted > 0, np.nansum(implied, axis=0) / counted, np.nan)
    times = group_times_s(meta.ngroups, meta.group_time_s, meta.frame_time_s, meta.nframes)
    level = np.where(np.isfinite(rate_dn_s), rate_dn_s, 0.0) * times[-1]  # the last group's
    usable = exposure.usable if exposure.usable.ndim == 2 else exposure.usable.any(axis=0)
    telling = usable & np.isfinite(implied_mean) & (level > THRESHOLD_GRID_DN[0])
    if exposure.dq is not None:
        dq = _by_integration(exposure.dq)
        telling &= ~np.any((dq & DQ_JUMP_DET) != 0, axis=0)
    if not telling.any():
        return None
    m = implied_mean[telling]
    sigma = IMPLIED_GROUPS_SCATTER * m + 0.2

    def misfit(threshold: float) -> float:
        used = charge_loss_groups(
            rate_dn_s, meta.ngroups, meta.group_time_s, meta.frame_time_s, meta.nframes,
            threshold,
        )  # fmt: skip
        z = (m - (used[telling] - 1)) / sigma
        return float(np.sum(np.minimum(z * z, 16.0)))

    scores = np.array([misfit(t) for t in THRESHOLD_GRID_DN])
    best = int(np.argmin(scores))
    if misfit(default_dn) - scores[best] <= THRESHOLD_EVIDENCE:
        return None
    # The run of thresholds that fit as well as the first best one (they cut the scored
    # pixels the same way): the data cannot tell them apart; its middle, or its lowest
    # where it reaches the top of the grid (then only a lower bound is known).
    last_tied = best
    while last_tied + 1 < scores.size and scores[last_tied + 1] == scores[best]:
        last_tied += 1
    if last_tied == scores.size - 1:
        return float(THRESHOLD_GRID_DN[best]), True
    found = float(np.mean(THRESHOLD_GRID_DN[best : last_tied + 1]))
    if abs(found - default_dn) <= THRESHOLD_RESOLUTION * default_dn:
        return None
    return found, False


def _by_integration(array: np.ndarray) -> np.ndarray:
    """A level-2 array with its integrations first: (nints, ny, nx) as it is, (ny, nx)
    (``_cal``, one image) as (1, ny, nx)."""
    return array if array.ndim == 3 else array[None]


def _integrations_averaged(meta) -> int:
    """How many integrations a level-2 exposure image averages: NINTS, or the segment's
    ``INTEND - INTSTART + 1`` where the file holds part of the exposure."""
    start, end = (meta.primary_header.get(k) for k in ("INTSTART", "INTEND"))
    if isinstance(start, int) and isinstance(end, int) and 1 <= start <= end:
        return end - start + 1
    return int(meta.nints)


def charge_loss_threshold_dn(cal_ver: str) -> float:
    """The charge-migration step's default threshold (DN) in the pipeline version
    ``cal_ver`` (the level-2 file's CAL_VER, e.g. ``"1.14.0"``): 30,000 DN in jwst 1.12.0
    and 1.12.1, 25,000 DN after (and for a version that does not parse)."""
    parts = re.match(r"\s*(\d+)\.(\d+)(?:\.(\d+))?", cal_ver)
    if parts is None:
        return CHARGE_LOSS_THRESHOLD_DN
    version = tuple(int(x or 0) for x in parts.groups())
    if (1, 12, 0) <= version < (1, 12, 2):
        return CHARGE_LOSS_THRESHOLD_1_12_DN
    return CHARGE_LOSS_THRESHOLD_DN
