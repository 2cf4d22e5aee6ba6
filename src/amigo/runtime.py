"""XLA settings that amigo makes before JAX starts: the same inputs give the same bits.

A fit takes discrete decisions (accept a step, take one more chord step, stop) on
float32 numbers, so a difference in the last bit of one gradient can move its optimum by
a few hundredths of a sigma and change the products' printed numbers. On the CPU, XLA's
matrix products run on a pool of threads (Eigen's), and a product run that way is not
always bitwise reproducible: on a 2-core CPU under load, the first evaluation of a fit's
gradient in a new process differed in its last bits from the later ones (same inputs,
same compiled program) in 2 of 16 fits started two at a time (2026-11-27; ``amigo run
--manifest`` then gave a target's products 0.05 sigma away from a serial run's). With the
products computed on one thread each, 30 of 30 such fits gave identical bits. The other
parallel parts of a program (its loops and fusions) still use every core. On 2 cores
this costs no time (docs/performance.md); on a many-core CPU the products may be slower:
``XLA_FLAGS=--xla_cpu_multi_thread_eigen=true`` trades the reproducibility back.

This module imports neither JAX nor NumPy, so that the command line can set the flag
before JAX reads its environment.
"""

from __future__ import annotations

import os
import sys

#: XLA's CPU flag for multi-threaded matrix products (its default: on).
EIGEN_THREADS_FLAG = "--xla_cpu_multi_thread_eigen"


def reproducible_cpu() -> bool:
    """Run XLA's CPU matrix products on one thread each (see module notes).

    Appends ``--xla_cpu_multi_thread_eigen=false`` to ``XLA_FLAGS`` unless the flag is
    there already (a user's explicit choice wins). JAX reads ``XLA_FLAGS`` once, when
    its first computation starts a backend: returns whether the setting applies, i.e.
    no backend has started yet in this process.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if EIGEN_THREADS_FLAG not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {EIGEN_THREADS_FLAG}=false".strip()
    return not _backend_started()


def _backend_started() -> bool:
    """Whether JAX has started a backend in this process (then ``XLA_FLAGS`` is read)."""
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge
    except ImportError:  # a JAX without this private module: assume the worst
        return True
    return bool(getattr(xla_bridge, "_backends", None))
