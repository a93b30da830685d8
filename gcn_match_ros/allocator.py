"""Freed memory kept in the process for the next window (glibc's malloc).

A window's solve allocates and frees arrays of the same sizes every window: similarity blocks
(1 MB each at 500 keypoints), the graph's edge arrays (~9 MB at 8 x 500), candidate features.
glibc serves a request above its mmap threshold from a fresh mapping and gives the top of its
heap back to the kernel once more than its trim threshold is free there; it raises both itself,
but only up to the largest mapped block freed so far, below what a window keeps live at once.
So every window faults the same pages in again (~6 000 page faults an 8 x 500 window, a large
share of one of its stages: the graph's edge merge 6.0 -> 3.5 ms without them).
:func:`keep_freed_memory` fixes both thresholds high: the heap keeps what a window freed for the
next one, and the process's resident memory stays at its peak instead of going up and down
with every window (8 x 500 stream windows 2.4-3.8 ms faster, 4.6-7.2 ms less CPU a window, in
alternating processes: docs/results.md, "Matcher node latency").

A process-wide setting: the node's entry point applies it (parameter ``keep_freed_memory``),
as do the benchmarks that stand for it; the library never does on its own.
"""
from __future__ import annotations

import ctypes

from .libc import c_function

__all__ = ["keep_freed_memory", "MMAP_THRESHOLD", "TRIM_THRESHOLD"]

#: Requests at least this large get a mapping of their own, returned when freed: 32 MiB, the
#: most glibc accepts on 64-bit systems (a window's arrays are smaller).
MMAP_THRESHOLD = 32 * 2**20
#: Free memory at the top of the heap is given back to the kernel above this: 256 MiB.
TRIM_THRESHOLD = 256 * 2**20

_M_TRIM_THRESHOLD = -1  # mallopt's parameter numbers (malloc.h)
_M_MMAP_THRESHOLD = -3


def keep_freed_memory(mmap_threshold: int = MMAP_THRESHOLD, trim_threshold: int = TRIM_THRESHOLD) -> bool:
    """Fix glibc's mmap and trim thresholds (``mallopt``) for the rest of the process, so that
    freed memory is kept for reuse (module docstring). Both are set together: setting either
    alone also stops glibc raising the other, and a trim threshold alone left the mmap threshold
    at 128 KiB (an 8 x 500 window then took 105 ms instead of 75).

    Returns:
        True when set; False where the C library is not glibc (no ``mallopt``) or refused a value.
    """
    mallopt = c_function("mallopt", (ctypes.c_int, ctypes.c_int), ctypes.c_int)
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold)) == 1
                and mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)) == 1)
