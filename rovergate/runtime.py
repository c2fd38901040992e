"""Process-wide settings every rovergate program applies at start, in either transport.

:func:`tune_allocator`: glibc's malloc hands big freed blocks straight back to the kernel
(blocks over its mmap threshold, and the heap's top over its trim threshold), so a step that
allocates the same arrays as the step before page-faults them in again. The planner took 700
to 900 page faults a step that way, and its compute time rose by up to 1.6 times when other
processes shared the cores. Raising both thresholds keeps the memory mapped (some 10 MB more per
process) and changes no number. Every program applies it, in process or as a process set, so
that a comparison between the two compares transports, not allocators.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

#: mallopt parameters (glibc malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 2**20
TRIM_THRESHOLD_BYTES = 256 * 2**20

_tuned = False


def tune_allocator() -> bool:
    """Keep freed memory mapped (glibc only; elsewhere a no-op). True when applied."""
    global _tuned
    if _tuned or not sys.platform.startswith("linux"):
        return _tuned
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    _tuned = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and \
        bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
    return _tuned
