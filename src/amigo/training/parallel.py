"""Data-parallel training over several devices (``jax.sharding``).

A training step sums the gradient of the base model over the calibration exposures of a
batch (:meth:`amigo.training.trainer.Trainer.train_step`). With several devices (GPUs, or
CPU devices made with ``XLA_FLAGS=--xla_force_host_platform_device_count=N``), the
exposures that share a compiled program (one filter and number of groups: a
:meth:`~amigo.likelihood.slopes.SlopeData.layout`) are stacked along a leading axis,
padded to a whole number per device with zero-weight copies, and laid out across a
one-axis mesh (``NamedSharding(mesh, P("data"))``); the base model and the pupil cache are
replicated. One compiled program then evaluates every exposure's loss and gradients on
its own device (``vmap`` over the sharded axis) and sums the base model's gradient across
devices (XLA's all-reduce). Exposures whose layout is unique, and every exposure on one
device, take the sequential path: the same sums, in another order.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from amigo.likelihood.slopes import SlopeData
from amigo.model.base import BaseModel, PupilCache
from amigo.training.fisher import loss_and_grad

#: The mesh axis the exposures are laid out along.
AXIS = "data"


def data_mesh(devices: Sequence[Any] | None = None) -> Mesh | None:
    """A one-axis mesh over ``devices`` (default: all of JAX's), or ``None`` for one."""
    devices = list(jax.devices() if devices is None else devices)
    return Mesh(np.array(devices), (AXIS,)) if len(devices) > 1 else None


def _layout_key(data: SlopeData) -> tuple:
    """Exposures with equal keys share a compiled program and stack into one array."""
    layout = data.layout()
    leaves, treedef = jax.tree.flatten(layout)
    return (treedef, tuple(np.shape(leaf) for leaf in leaves))


@eqx.filter_jit
def _sharded_loss_and_grads(
    base: BaseModel, params: Any, data: SlopeData, cache: PupilCache, weights: jax.Array
) -> tuple[jax.Array, BaseModel, Any]:
    """Per-exposure losses (n,), the base model's gradient summed over the stacked
    exposures, and per-exposure parameter gradients (stacked), each scaled by
    ``weights`` (0 for padding)."""

    def one(p, d, w):
        value, (grad_base, grad_params) = loss_and_grad(base, p, d, cache)
        scale = lambda g: w * g  # noqa: E731
        return w * value, jax.tree.map(scale, grad_base), jax.tree.map(scale, grad_params)

    values, grad_base, grad_params = jax.vmap(one)(params, data, weights)
    return values, jax.tree.map(lambda g: jnp.sum(g, axis=0), grad_base), grad_params


def _stack(items: Sequence[Any]) -> Any:
    return jax.tree.map(lambda *xs: jnp.stack(xs), *items)


def _put(tree: Any, where: Any) -> Any:
    """``jax.device_put`` of the array leaves of ``tree`` (a model holds other leaves)."""
    return jax.tree.map(lambda x: jax.device_put(x, where) if eqx.is_array(x) else x, tree)


def batch_loss_and_grads(
    base: BaseModel,
    params: Sequence[Any],
    datasets: Sequence[SlopeData],
    cache: PupilCache,
    mesh: Mesh | None,
) -> tuple[list[jax.Array], BaseModel, list[Any]]:
    """Loss and gradients of every exposure of a batch, and their base-model gradient sum.

    Parameters
    ----------
    base, cache
        The model and its pupil cache (replicated on every device of ``mesh``).
    params, datasets
        Each exposure's parameters and data, in the batch's order.
    mesh
        :func:`data_mesh` (``None``: one device, one exposure after the other).

    Returns
    -------
    The losses (``chi2 / 2``) and parameter gradients in the batch's order, and the sum of
    the base model's gradients, all on the default device.
    """
    n = len(datasets)
    values: list[Any] = [None] * n
    grads: list[Any] = [None] * n
    total: Any = None
    groups: dict[tuple, list[int]] = defaultdict(list)
    for k, data in enumerate(datasets):
        groups[_layout_key(data) if mesh is not None else (k,)].append(k)
    home = jax.devices()[0]
    for members in groups.values():
        if mesh is None or len(members) == 1:
            for k in members:
                values[k], (grad_base, grads[k]) = loss_and_grad(
                    base, params[k], datasets[k], cache
                )
                total = grad_base if total is None else jax.tree.map(jnp.add, total, grad_base)
            continue
        per_device = -(-len(members) // mesh.size)
        padded = members + [members[0]] * (per_device * mesh.size - len(members))
        weights = np.zeros(len(padded), np.float32)
        weights[: len(members)] = 1.0
        split = NamedSharding(mesh, PartitionSpec(AXIS))
        replicated = NamedSharding(mesh, PartitionSpec())
        out = _sharded_loss_and_grads(
            _put(base, replicated),
            _put(_stack([params[k] for k in padded]), split),
            _put(_stack([datasets[k].layout() for k in padded]), split),
            _put(cache, replicated),
            _put(jnp.asarray(weights), split),
        )
        group_values, grad_base, group_grads = _put(out, home)
        total = grad_base if total is None else jax.tree.map(jnp.add, total, grad_base)
        for i, k in enumerate(members):
            values[k] = group_values[i]
            grads[k] = jax.tree.map(lambda g, i=i: g[i], group_grads)
    return values, total, grads
