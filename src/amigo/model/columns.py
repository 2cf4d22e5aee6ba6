"""Forward-mode Jacobians in batches of columns, for the fit and the latent bases.

:func:`columns_of` linearises a function once per block of its input and pushes unit
tangents through the linear map ``jvp_batch()`` at a time (:data:`JVP_BATCH`, or
``$AMIGO_JVP_BATCH``): the fit's Jacobians (:mod:`amigo.fitting.newton`) and the latent
bases' knot Jacobians (:mod:`amigo.model.basis`) are its callers.
"""

from __future__ import annotations

import itertools
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

#: Columns differentiated together on a CPU (memory: each holds the visibility FFTs of one
#: image). Measured (2-core CPU, a warm one-filter fit of real data): 16 -> 103 s and 2.1 GB
#: peak, 8 -> 80 s and 1.75 GB, 4 -> 85 s and 1.63 GB (smaller batches stay in cache).
JVP_BATCH = 8
#: Environment variable that sets the batch (benchmarks/jacobian_batch.py). On a GPU
#: (an H200, a warm one-filter fit of the real pair in one process, docs/performance.md)
#: the batch hardly matters: fits of 5.1 / 4.9 / 5.3 s at 8 / 64 / 256 columns, of which
#: the Jacobians' calls 0.27 / 0.14 / 0.14 s; so 8 everywhere.
JVP_BATCH_ENV = "AMIGO_JVP_BATCH"


def jvp_batch() -> int:
    """Jacobian columns per batch: :data:`JVP_BATCH`, or ``$AMIGO_JVP_BATCH`` when set.
    Read when a Jacobian is traced: a compiled Jacobian keeps the batch it was traced with."""
    value = os.environ.get(JVP_BATCH_ENV, "").strip()
    if not value:
        return JVP_BATCH
    try:
        batch = int(value)
    except ValueError:
        batch = 0
    if batch < 1:
        raise ValueError(f"{JVP_BATCH_ENV} must be a positive integer, got {value!r}")
    return batch


def columns_of(function, x: Array, blocks: tuple[int, ...] = ()) -> Array:
    """Forward-mode Jacobian of ``function`` at ``x``, (n, *out), in batches of columns.

    The function is linearised once per block of ``x`` (``blocks``: the sizes of the
    leading blocks; the rest of ``x`` is the last block), and each block's linear map is
    applied to its unit tangents in batches. Two savings over ``jax.jvp`` per batch,
    with identical columns:

    * the primal evaluation (and what the tangents reuse of it: the PSFs' transforms,
      the visibilities' exponentials) is computed once, not once per batch;
    * parts of the model that do not depend on a block get symbolic-zero tangents: the
      point source's full spectrum does not move with a latent visibility, and a
      log-amplitude column leaves the phase's interpolation alone.

    The tangents are padded with zero columns to a whole number of batches: ``lax.map``
    would otherwise trace the remainder as a second copy of the model, which doubles the
    compile time (minutes on a CPU) to save a few JVPs.
    """
    n = x.shape[0]
    bounds = np.cumsum([0, *blocks, n - sum(blocks)])
    parts = []
    for lo, hi in itertools.pairwise(bounds.tolist()):
        if hi == lo:
            continue

        def of_block(block, lo=lo, hi=hi):
            return function(jnp.concatenate([x[:lo], block, x[hi:]]))

        _, linear = jax.linearize(of_block, x[lo:hi])
        size = hi - lo
        # As many steps as the batch size asks for, shared evenly: the least padding
        # (71 columns at 64 are 2 steps of 36, not 2 of 64).
        steps = -(-size // jvp_batch())
        batch = -(-size // steps)
        padded = -(-size // batch) * batch
        tangents = jnp.eye(padded, size, dtype=x.dtype)  # rows size.. are zero
        parts.append(jax.lax.map(linear, tangents, batch_size=batch)[:size])
    return jnp.concatenate(parts)
