"""amigo.heap: freed memory handed back to the system between a fit's large steps."""

from __future__ import annotations

import platform

import numpy as np
import pytest

from amigo import heap


def _resident_mb() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS in /proc/self/status")


def test_release_is_safe_to_call_anywhere():
    assert isinstance(heap.release(), bool)
    assert isinstance(heap.release(), bool)  # twice: nothing left is fine too


@pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
    reason="malloc_trim is glibc's; elsewhere release() does nothing",
)
def test_release_returns_freed_memory_below_a_live_block_on_glibc():
    # Blocks under glibc's mmap threshold (128 kB) are carved from the heap; once one
    # allocated after them stays alive, freeing them leaves ~450 MB of free pages below
    # it, which free() keeps (it only trims the heap's top) and a trim gives back.
    blocks = [np.ones(12_000) for _ in range(5_000)]  # 96 kB each
    keeper = np.ones(12_000)
    del blocks
    after_free = _resident_mb()
    assert heap.release()
    after_release = _resident_mb()
    assert after_release < after_free - 300.0, (after_free, after_release)
    assert keeper.sum() == 12_000.0
