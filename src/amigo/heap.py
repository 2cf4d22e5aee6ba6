"""Hand the memory a fit has freed back to the system, between its large steps.

A fit's large arrays (float64 Jacobians of ~60 MB, Fisher matrices of ~40 MB, XLA's
buffers) are freed by Python and XLA, but glibc's allocator keeps freed memory in its
heaps for reuse, fragmented between the blocks that stay alive, and a process's resident
memory only grows. Measured on the three-filter AB Dor fit of docs/performance.md (2-core
AMD EPYC, 2026-11-29, warm cache): after the first filter's products were written the
process held 1.27 GB, of which the live JAX arrays were 36 MB; ``malloc_trim(0)`` brought
it to 0.55 GB, and each later filter started ~0.7 GB above what it needed. Trimming before
each set of Jacobians (:func:`release`) lowers the peak; glibc's other remedy, a low
``M_MMAP_THRESHOLD`` (every large block its own mapping), lowered it further but cost 15 %
of the wall time (fresh pages for every large buffer of every call), so it is not used.

Only glibc has ``malloc_trim``; elsewhere :func:`release` does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


@functools.cache
def _trim():
    """glibc's ``malloc_trim``, or ``None`` (another C library, or none found)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def release() -> bool:
    """Return the allocator's free pages to the system (``malloc_trim(0)``, which since
    glibc 2.8 releases free pages anywhere in the heaps, not only at their tops).
    Costs a walk over the heaps (milliseconds). Returns whether memory was released."""
    trim = _trim()
    return bool(trim(0)) if trim is not None else False


#: What else holds programs in memory (:func:`holds_programs`), emptied with JAX's caches.
_HOLDERS: list[Callable[[], None]] = []


def holds_programs(forget: Callable[[], None]) -> None:
    """Have :func:`release_programs` call ``forget`` too (a cache of programs above this
    module, e.g. :func:`amigo.programs.release`)."""
    if forget not in _HOLDERS:
        _HOLDERS.append(forget)


def release_programs() -> bool:
    """Drop JAX's in-memory compiled programs and caches (``jax.clear_caches``), then
    :func:`release`: for a step whose programs serve nothing after it (a filter's fit, a
    posterior's sampling loops). What runs later reloads what it needs from the
    persistent compilation cache. Returns whether memory was released."""
    import jax  # here: the rest of this module needs only ctypes

    jax.clear_caches()
    for forget in _HOLDERS:
        forget()
    return release()
