"""Joint least-squares fit of a primary and several companions to a dataset.

Parameters: each companion's sky offset (dRA, dDec in mas, shared by all filters) and its
log10 flux ratio in every filter. The fit minimises the sum of squared whitened residuals
(errors multiplied by the fixed group error scales) with Levenberg-Marquardt; the Laplace
covariance is the inverse Gauss-Newton Hessian ``(J^T J)^-1`` at the optimum.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt

from amigo.companions.models import scene_visibility
from amigo.companions.observables import Dataset, Observables

#: Lowest log10 flux ratio allowed in the fits (a companion 25 magnitudes fainter).
LOG10_CONTRAST_FLOOR = -10.0


# Compiled as one program per dataset layout and companion count: evaluated op by op,
# every primitive of every block is compiled on its own (minutes on a small CPU).
@eqx.filter_jit
def block_residuals(
    dataset: Dataset,
    offsets_mas: jax.Array,
    contrasts: jax.Array,
    primary_diameter_mas: float = 0.0,
) -> tuple[jax.Array, ...]:
    """Unscaled whitened residuals of each block for companions ``offsets_mas`` (K, 2) with
    flux ratios ``contrasts`` (K, n_filters)."""
    return tuple(
        block_residual(
            block, offsets_mas, contrasts[:, dataset.filter_index(i)], primary_diameter_mas
        )
        for i, block in enumerate(dataset.blocks)
    )


def block_residual(
    block: Observables,
    offsets_mas: jax.Array,
    contrasts: jax.Array,
    primary_diameter_mas: float = 0.0,
) -> jax.Array:
    """Unscaled whitened residuals (n_obs,) of one block for companions ``offsets_mas``
    (K, 2) with flux ratios ``contrasts`` (K,) in the block's filter."""
    vis = scene_visibility(
        block.uv_m,
        block.wavelengths_m,
        block.weights,
        offsets_mas,
        contrasts,
        primary_diameter_mas,
    )
    return block.residuals(vis)


def group_chi2(dataset: Dataset, residuals: tuple[jax.Array, ...]) -> tuple[np.ndarray, ...]:
    """(chi2, number of observables) per group, from unscaled residuals."""
    chi2 = np.zeros(dataset.n_groups)
    count = np.zeros(dataset.n_groups, dtype=int)
    for i, r in enumerate(residuals):
        g = dataset.group_index(i)
        np.add.at(chi2, g, np.asarray(r) ** 2)
        np.add.at(count, g, 1)
    return chi2, count


def estimate_scales(
    dataset: Dataset,
    offsets_mas: npt.ArrayLike,
    contrasts: npt.ArrayLike,
    primary_diameter_mas: float = 0.0,
) -> np.ndarray:
    """Maximum-likelihood error scales ``sqrt(chi2_g / n_g)`` per group for a given scene."""
    residuals = block_residuals(
        dataset, jnp.asarray(offsets_mas), jnp.asarray(contrasts), primary_diameter_mas
    )
    chi2, count = group_chi2(dataset, residuals)
    return np.sqrt(chi2 / np.maximum(count, 1))


@dataclass(frozen=True)
class CompanionFitResult:
    """Best fit of ``K`` companions in ``F`` filters.

    Attributes
    ----------
    offsets_mas
        (K, 2) sky offsets (dRA, dDec).
    log10_contrasts
        (K, F) log10 flux ratios.
    covariance
        (2K + KF, 2K + KF) Laplace covariance of ``[offsets.ravel(), log10c.ravel()]``.
    chi2
        Total chi2 with the scaled errors.
    group_scales
        (n_groups,) the error scales used.
    converged
        Whether the optimiser met its tolerance.
    """

    offsets_mas: np.ndarray
    log10_contrasts: np.ndarray
    covariance: np.ndarray
    chi2: float
    group_scales: np.ndarray
    converged: bool

    @property
    def contrasts(self) -> np.ndarray:
        return 10.0**self.log10_contrasts

    @property
    def n_companions(self) -> int:
        return int(self.offsets_mas.shape[0])

    def offset_errors_mas(self) -> np.ndarray:
        """(K, 2) 1-sigma errors of dRA, dDec."""
        k = self.n_companions
        return np.sqrt(np.diag(self.covariance)[: 2 * k]).reshape(k, 2)

    def log10_contrast_errors(self) -> np.ndarray:
        """(K, F) 1-sigma errors of log10 flux ratios."""
        k = self.n_companions
        return np.sqrt(np.diag(self.covariance)[2 * k :]).reshape(k, -1)


def _block_columns(k: int, n_filters: int, f: int) -> np.ndarray:
    """Indices, in the flat parameters ``[offsets.ravel(), log10c.ravel()]`` of ``k``
    companions, of those a block of filter ``f`` depends on: every offset and the
    companions' contrasts in ``f``."""
    return np.concatenate([np.arange(2 * k), 2 * k + np.arange(k) * n_filters + f])


@eqx.filter_jit
def _residual_and_jacobian(flat, args):
    """Residual vector and its Jacobian of flattened parameters ``[offsets.ravel(),
    log10c.ravel()]`` (forward mode: few parameters, many residuals).

    ``args = (dataset, scale_vectors, k, diameter)``, ``k`` and ``diameter`` static; a
    module-level function (not a closure) so that the compiled program is reused by every
    fit of the same dataset layout. Each block is differentiated only along the
    parameters it depends on (the offsets and its own filter's contrasts): the other
    filters' contrast columns are zeros that would cost as many products with the
    observable matrix as any other column (2K + K of 2K + KF tangents per block instead
    of all; a third fewer for one companion in three filters).
    """
    dataset, scale_vectors, k, diameter = args
    residuals, jacobians = [], []
    for i, block in enumerate(dataset.blocks):
        columns = _block_columns(k, dataset.n_filters, dataset.filter_index(i))

        def residual(sub, block=block, scale=scale_vectors[i]):
            # A companion brighter than the primary is the same binary seen from the other
            # star: flux ratios are kept in [1e-10, 1] so that each has one representation.
            log10c = jnp.clip(sub[2 * k :], LOG10_CONTRAST_FLOOR, 0.0)
            offsets = sub[: 2 * k].reshape(k, 2)
            return block_residual(block, offsets, 10.0**log10c, diameter) / scale

        jacobian, r = jax.jacfwd(lambda y, f=residual: (f(y),) * 2, has_aux=True)(flat[columns])
        residuals.append(r)
        jacobians.append(jnp.zeros((r.size, flat.size), r.dtype).at[:, columns].set(jacobian))
    return jnp.concatenate(residuals), jnp.concatenate(jacobians, axis=0)


def levenberg_marquardt(
    function: Callable[[np.ndarray], tuple[Any, Any]],
    x0: np.ndarray,
    max_steps: int = 200,
    rtol: float = 1e-10,
    decrement_tol: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Minimise ``|r(x)|^2`` by Levenberg-Marquardt with Marquardt's diagonal scaling.

    ``function(x) -> (r, J)``. A small host-side loop around one jitted residual+Jacobian
    call: the problems have at most a few tens of parameters, and compiling this is much
    cheaper than compiling a general solver. Returns ``(x, r, J, converged)``; converged
    means the relative chi2 decrease fell below ``rtol``, or, before any further
    evaluation, the Gauss-Newton decrement ``g^T (J^T J)^+ g`` (``g = J^T r``: the chi2
    the linearised model could still gain) fell to ``decrement_tol`` or below.

    The decrement matters for fits that end slowly: a candidate at a noise peak whose
    flux ratio runs towards zero in log10 flattens chi2 without a minimum, and Gauss-
    Newton then gains a nearly constant fraction per step (0.93 on AB Dor's search:
    100-odd evaluations to reach ``rtol``) while the chi2 left to gain is already
    negligible.
    """
    x = np.asarray(x0, dtype=float)
    r, j = (np.asarray(a) for a in function(x))
    chi2 = float(r @ r)
    damping = 1e-3
    for _ in range(max_steps):
        fisher = j.T @ j
        gradient = j.T @ r
        if decrement_tol > 0.0:
            newton = np.linalg.lstsq(fisher, gradient, rcond=None)[0]
            if float(gradient @ newton) <= decrement_tol:
                return x, r, j, True
        scale = np.maximum(np.diag(fisher), 1e-30)
        try:
            step = np.linalg.solve(fisher + damping * np.diag(scale), -gradient)
        except np.linalg.LinAlgError:
            damping *= 10.0
            continue
        r_new, j_new = (np.asarray(a) for a in function(x + step))
        chi2_new = float(r_new @ r_new)
        if np.isfinite(chi2_new) and chi2_new <= chi2:
            x, r, j = x + step, r_new, j_new
            gain, chi2 = chi2 - chi2_new, chi2_new
            damping = max(damping / 3.0, 1e-12)
            if gain <= rtol * max(chi2, 1.0):
                return x, r, j, True
        else:
            damping *= 4.0
            if damping > 1e10:
                return x, r, j, True  # no downhill step left: a (local) minimum
    return x, r, j, False


def fit_companions(
    dataset: Dataset,
    offsets_mas: np.ndarray,
    log10_contrasts: np.ndarray,
    group_scales: np.ndarray | None = None,
    primary_diameter_mas: float = 0.0,
    max_steps: int = 200,
    chi2_tolerance: float = 0.0,
) -> CompanionFitResult:
    """Levenberg-Marquardt fit of all companions jointly, from the given starting point.

    Parameters
    ----------
    offsets_mas, log10_contrasts
        (K, 2) and (K, F) starting values.
    group_scales
        (n_groups,) fixed error scales (``None``: ones).
    chi2_tolerance
        Stop once the linearised model could gain no more than this in chi2
        (:func:`levenberg_marquardt`'s ``decrement_tol``); 0 (default): converge to the
        relative chi2 change of ``1e-10``.
    """
    scales = np.ones(dataset.n_groups) if group_scales is None else np.asarray(group_scales)
    scale_vectors = dataset.scale_vectors(scales)
    offsets0 = np.asarray(offsets_mas, dtype=float).reshape(-1, 2)
    log10c0 = np.clip(
        np.asarray(log10_contrasts, dtype=float).reshape(offsets0.shape[0], -1),
        LOG10_CONTRAST_FLOOR + 1,
        -1e-3,
    )
    k = offsets0.shape[0]
    args = (dataset, scale_vectors, k, float(primary_diameter_mas))
    y0 = np.concatenate([offsets0.ravel(), log10c0.ravel()])
    best, residual, jacobian, converged = levenberg_marquardt(
        lambda y: _residual_and_jacobian(jnp.asarray(y), args),
        y0,
        max_steps,
        decrement_tol=chi2_tolerance,
    )
    covariance = np.linalg.pinv(jacobian.T @ jacobian, rcond=1e-12, hermitian=True)
    return CompanionFitResult(
        offsets_mas=best[: 2 * k].reshape(k, 2),
        log10_contrasts=np.clip(best[2 * k :].reshape(k, -1), LOG10_CONTRAST_FLOOR, 0.0),
        covariance=covariance,
        chi2=float(residual @ residual),
        group_scales=scales,
        converged=converged,
    )


def scaled_chi2(
    dataset: Dataset,
    offsets_mas: jax.Array,
    contrasts: jax.Array,
    group_scales: np.ndarray,
    primary_diameter_mas: float = 0.0,
) -> float:
    """chi2 of a scene (companions at ``offsets_mas`` (n, 2) with linear ``contrasts``
    (n, F)) with every group's errors multiplied by its scale (summed in NumPy)."""
    parts = block_residuals(dataset, offsets_mas, contrasts, primary_diameter_mas)
    scales = dataset.scale_vectors(group_scales)
    return float(
        sum(
            np.sum((np.asarray(r) / np.asarray(s)) ** 2) for r, s in zip(parts, scales, strict=True)
        )
    )


def background_chi2(
    dataset: Dataset, group_scales: np.ndarray, primary_diameter_mas: float = 0.0
) -> float:
    """chi2 of the primary alone (no companion), with scaled errors."""
    empty = jnp.zeros((0, 2))
    no_contrast = jnp.zeros((0, dataset.n_filters))
    return scaled_chi2(dataset, empty, no_contrast, group_scales, primary_diameter_mas)
