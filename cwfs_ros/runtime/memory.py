"""The C heap of a process that takes large messages: freed memory kept for reuse (glibc).

Each whole half-chip frame arrives as a 32 MB ``sensor_msgs/Image``: rclpy's take builds a C
message and then a Python ``array.array`` of that size, and both are freed when the image has
been handed on. glibc serves such requests with fresh ``mmap`` regions and unmaps them on
``free``, so every frame page-faults 64 MB in again: measured on the 2-core VM, a 32 MB take
costs ~29 ms from a pool thread with glibc's defaults and ~11 ms with the settings below; in
the live graph takes of 90-240 ms appeared when a worker process was faulting in at the same
time (docs/performance.md, Whole half-chips).

:func:`keep_freed_memory` makes the heap keep what it frees, as the ROS 2 real-time guides
do for a control loop (``mallopt``: no ``mmap`` for large blocks, no trimming, one arena so
that the executor's threads reuse one another's blocks). The process then stays at its
high-water mark, bounded by what it holds at once (``max_pending_mb`` of waiting images,
the messages being taken). :func:`prefault_heap` maps pages ahead (wavefront_node: one
visit's frames, at its frames warm-up), so that the first visit after start finds its pages
mapped too.

Only where the C library is glibc; a user's own ``MALLOC_*`` settings (:data:`HEAP_VARIABLES`)
win, as for BLAS threads (:mod:`.threads`). No ROS here.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from functools import lru_cache

__all__ = ["HEAP_VARIABLES", "keep_freed_memory", "prefault_heap"]

# glibc's environment tunables of the settings below: any of them set means the user chose.
HEAP_VARIABLES = ("MALLOC_ARENA_MAX", "MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_",
                  "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "GLIBC_TUNABLES")

# mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8
_NO_TRIM = 2 ** 31 - 1  # the largest int: free memory at the top of the heap is never returned
_applied = False  # keep_freed_memory() took effect in this process


@lru_cache(maxsize=1)
def _glibc() -> ctypes.CDLL | None:
    """The process's C library when it is glibc (it has ``mallopt``), else None."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018 - only glibc has it
        libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        libc.malloc.argtypes = (ctypes.c_size_t,)
        libc.malloc.restype = ctypes.c_void_p
        libc.free.argtypes = (ctypes.c_void_p,)
        return libc
    except (OSError, AttributeError):
        return None


def keep_freed_memory() -> bool:
    """Make this process's heap keep the memory it frees (module doc); True when applied.

    Call before the process starts threads (one arena serves them all only if none has
    made its own yet). Nothing where the C library is not glibc or the user set any of
    :data:`HEAP_VARIABLES`.
    """
    if any(v in os.environ for v in HEAP_VARIABLES):
        return False
    libc = _glibc()
    if libc is None:
        return False
    global _applied
    settings = ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, _NO_TRIM))
    _applied = all(libc.mallopt(param, value) == 1 for param, value in settings)
    return _applied


def prefault_heap(nbytes: int) -> bool:
    """Grow the heap by ``nbytes`` with every page written, then free it, so that the next
    allocations reuse those pages instead of faulting new ones in. Only where
    :func:`keep_freed_memory` took effect (elsewhere the block would be unmapped on
    ``free``). True when done."""
    libc = _glibc()
    n = int(nbytes)
    if not _applied or libc is None or n <= 0:
        return False
    block = libc.malloc(n)
    if not block:
        return False
    try:
        ctypes.memset(block, 0, n)
    finally:
        libc.free(block)
    return True
