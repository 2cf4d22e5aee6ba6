"""Compiled pieces of training: the slope loss and its gradient, and the Fisher
information (diagonal, per pixel, of the dark current, and the full matrix of a group)
that preconditions each step (a natural gradient).
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from amigo.likelihood.slopes import (
    FlatParams,
    PointSourceParams,
    SlopeData,
    model_slopes,
    whiten,
    whitened_residuals,
)
from amigo.model.base import (
    BaseModel,
    PupilCache,
)
from amigo.training.groups import calibrator_pixels, dark_mask, false_like, pixel_mask, split


def per_layout(function):
    """``eqx.filter_jit(function)``, called with every :class:`SlopeData` argument reduced
    to what the computation reads (:meth:`SlopeData.layout`): the exposures of one filter
    and number of groups then share one traced and compiled program. With the file name,
    role and value count in the key, every exposure traced and lowered its own (seconds
    each on a CPU: a training on 33 calibrator files traced each program 33 times)."""
    compiled = eqx.filter_jit(function)

    @functools.wraps(function)
    def call(*args):
        return compiled(*(a.layout() if isinstance(a, SlopeData) else a for a in args))

    return call


@per_layout
def loss_and_grad(base: BaseModel, params: Any, data: SlopeData, cache: PupilCache):
    """``(chi2 / 2, (d/dbase, d/dparams))`` of one exposure, the drift's prior included
    (compiled once per filter and number of groups)."""

    def loss(bp):
        b, p = bp
        chi2 = jnp.sum(whitened_residuals(model_slopes(b, cache, p, data), data) ** 2)
        # The exposure's priors (a point source's drift): in its Fisher matrix too.
        return 0.5 * (chi2 + jnp.sum(p.prior_residuals() ** 2))

    return eqx.filter_value_and_grad(loss)((base, params))


@per_layout
def compiled_model(base: BaseModel, params: Any, data: SlopeData, cache: PupilCache):
    return model_slopes(base, cache, params, data)


@per_layout
def _fisher(base: BaseModel, params: Any, data: SlopeData, cache: PupilCache, mask: Any):
    linear = base.with_linear_detector()
    diff, static = eqx.partition((linear, params), (mask, jax.tree.map(lambda _: True, params)))
    vector, unravel = ravel_pytree(diff)

    def residuals(v):
        b, p = eqx.combine(unravel(v), static)
        pixels = whitened_residuals(model_slopes(b, cache, p, data), data).ravel()
        return jnp.concatenate([pixels, p.prior_residuals().astype(pixels.dtype)])

    jac = jax.jacfwd(residuals)(vector)  # (n_values, n_params)
    return jac.T @ jac


def fisher_matrix(
    base: BaseModel, params: Any, data: SlopeData, cache: PupilCache, mask: Any
) -> tuple[np.ndarray, np.ndarray]:
    """Fisher (Gauss-Newton) matrix ``J^T J`` of the whitened residuals ``z`` of the
    *linear-detector* model, from the exact Jacobian (forward mode, one column per
    parameter), for the base-model leaves selected by ``mask`` (a
    :func:`physical_mask`-like tree) and every per-exposure parameter.

    Returns ``(F_base, F_params)``: the block of the selected base parameters, in the
    order of ``ravel_pytree(split(base, mask))``, and the diagonal of the per-exposure
    block (float64 NumPy).
    """
    # The linear view: one compiled function whether or not the network is on.
    linear = base.with_linear_detector()
    matrix = np.asarray(_fisher(linear, params, data, cache, mask), dtype=np.float64)
    n_base = ravel_pytree(split(base, mask))[0].size
    return matrix[:n_base, :n_base], np.diagonal(matrix)[n_base:]


def exposure_fisher_block(
    base: BaseModel, params: Any, data: SlopeData, cache: PupilCache
) -> np.ndarray:
    """The whole Fisher matrix of one exposure's own parameters (its priors included),
    in the order of ``ravel_pytree(params)``, with the instrument fixed (float64)."""
    linear = base.with_linear_detector()
    return np.asarray(_fisher(linear, params, data, cache, false_like(linear)), np.float64)


def fisher_diagonal(
    base: BaseModel, params: Any, data: SlopeData, cache: PupilCache, mask: Any
) -> tuple[Any, Any]:
    """The diagonals of :func:`fisher_matrix`, shaped like ``split(base, mask)`` and
    ``params``."""
    f_base, f_params = fisher_matrix(base, params, data, cache, mask)
    unravel_base = ravel_pytree(split(base, mask))[1]
    unravel_params = ravel_pytree(params)[1]
    return unravel_base(jnp.asarray(np.diagonal(f_base))), unravel_params(jnp.asarray(f_params))


@per_layout
def pixel_fisher(
    base: BaseModel, params: FlatParams, data: SlopeData
) -> tuple[BaseModel, Float[Array, "ny nx"]]:
    """Per-pixel 2 x 2 Fisher matrix of the flat field and the non-linearity from one
    flat field: its diagonal, shaped like ``split(base, pixel_mask(base))``, and the
    (ny, nx) cross term. A pixel's parameters act (IPC aside) on that pixel's slopes
    only, so one forward-mode pass with a tangent of ones gives every pixel's derivative
    at once. Under one light level the two are strongly correlated (the non-linearity
    bends the ramp, the flat scales it): the cross term is what keeps a Newton step of
    the pair from overshooting (see :func:`pixel_newton`)."""

    def slopes(flat, nonlinearity):
        b = eqx.tree_at(lambda m: (m.ramp.flat, m.read.nonlinearity), base, (flat, nonlinearity))
        return model_slopes(b, None, params, data)  # type: ignore[arg-type]

    primals = (base.ramp.flat, base.read.nonlinearity)
    dz = []
    for index in range(2):
        tangents = tuple(
            jnp.ones_like(p) if i == index else jnp.zeros_like(p) for i, p in enumerate(primals)
        )
        _, dslopes = jax.jvp(slopes, primals, tangents)
        dz.append(whiten(dslopes, data))  # the derivative of W (data - model), up to sign
    diagonal = tuple(jnp.sum(d**2, axis=1).reshape(data.shape) for d in dz)
    cross = jnp.sum(dz[0] * dz[1], axis=1).reshape(data.shape)
    mask = pixel_mask(base)
    tree = eqx.tree_at(lambda m: (m.ramp.flat, m.read.nonlinearity), split(base, mask), diagonal)
    return tree, cross


def pixel_newton(grad: BaseModel, fisher: dict[str, Any], damping: float) -> BaseModel:
    """``(F + damping diag F)^-1 g`` per pixel for the (flat, non-linearity) pair, ``F``
    the per-pixel 2 x 2 Fisher matrix (``fisher``: ``"diag"`` shaped like ``grad``,
    ``"cross"`` (ny, nx)); zero where a pixel is not constrained."""
    a = fisher["diag"].ramp.flat * (1.0 + damping)
    b = fisher["diag"].read.nonlinearity * (1.0 + damping)
    c = fisher["cross"]
    g_f, g_n = grad.ramp.flat, grad.read.nonlinearity
    det = a * b - c**2
    ok = (a > 0) & (b > 0) & jnp.isfinite(det) & (det > 0)
    det = jnp.where(ok, det, 1.0)
    step_f = jnp.where(ok, (b * g_f - c * g_n) / det, 0.0)
    step_n = jnp.where(ok, (a * g_n - c * g_f) / det, 0.0)
    return eqx.tree_at(lambda m: (m.ramp.flat, m.read.nonlinearity), grad, (step_f, step_n))


@per_layout
def dark_fisher(
    base: BaseModel, params: PointSourceParams, data: SlopeData, cache: PupilCache
) -> BaseModel:
    """Per-pixel Fisher diagonal of the calibrators' per-pixel leaf (the dark current, or
    a level-2 model's residual sensitivity) from one calibration exposure, shaped like
    ``split(base, dark_mask(base))`` (one forward-mode pass with a tangent of ones, as
    :func:`pixel_fisher`; a pixel's dark charge or sensitivity, IPC and charge migration
    aside, reaches only that pixel's slopes)."""

    def slopes(value):
        b = eqx.tree_at(calibrator_pixels, base, value)
        return model_slopes(b, cache, params, data)

    value = calibrator_pixels(base)
    _, dslopes = jax.jvp(slopes, (value,), (jnp.ones_like(value),))
    dz = whiten(dslopes, data)
    per_pixel = jnp.sum(dz**2, axis=1).reshape(data.shape)
    return eqx.tree_at(calibrator_pixels, split(base, dark_mask(base)), per_pixel)
