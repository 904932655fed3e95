"""The process's memory for large queries: glibc told to keep what a query frees for the next.

By default glibc maps every allocation above 128 kB to fresh pages and returns them when freed, so
each 1M-point query page-faults its ~250 MB of arrays in again (one fault per 4 kB: ~0.1 s of a
0.3-0.4 s query on 2 cores; docs/neural.md, "Query fast path"). ``collider serve`` and ``collider
bench`` call :func:`hold_freed_memory` at start; an embedding application can call it, or set
``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` itself.
"""

from __future__ import annotations

import ctypes
import os
import platform

#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Arrays up to this size come from the heap and stay there when freed, bytes (1M points' float64
#: (n, 3) arrays are 24 MB; glibc maps anything above 128 kB to fresh pages by default). glibc
#: before 2.35 takes at most 32 MiB: then that.
HELD_ARRAY_BYTES = (1 << 30, 32 << 20)
#: Freed memory at the heap's top beyond this goes back to the system, bytes (the largest glibc
#: takes, an int).
HELD_TOP_BYTES = 2**31 - 1
#: Settings of the user's that this leaves alone.
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")


def hold_freed_memory() -> int:
    """Keep the memory a batch frees for the next batch instead of returning it to the system
    (glibc's ``mallopt``): otherwise every large query maps its arrays anew and pays a page fault
    per 4 kB of them. The process keeps its peak memory. Returns the largest array size now kept,
    bytes; 0 when nothing changed: not glibc, or the user set ``MALLOC_MMAP_THRESHOLD_`` /
    ``MALLOC_TRIM_THRESHOLD_`` or their ``GLIBC_TUNABLES`` (theirs stand)."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if any(name in os.environ for name in USER_SETTINGS) or "threshold" in tunables:
        return 0
    if platform.libc_ver()[0] != "glibc":  # musl, macOS, Windows: their allocators differ
        return 0
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):
        return 0
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    for size in HELD_ARRAY_BYTES:
        if mallopt(_M_MMAP_THRESHOLD, size):
            return size if mallopt(_M_TRIM_THRESHOLD, HELD_TOP_BYTES) else 0
    return 0
