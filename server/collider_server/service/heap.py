"""The process's heap: settled once the models are loaded, so that garbage collection does not
pause requests in proportion to everything the process ever imported; and, with glibc, told to
keep the memory a batch frees for the next batch.

CPython's full (oldest-generation) collection walks every container object alive: here about a
quarter of a million (torch, numpy, FastAPI and the loaded models), 100-180 ms with the GIL held
on a loaded 2-core machine, during which no request in flight moves. Thousands of connections
opening and closing together (an attack of slow connections, clients reconnecting after a
restart) allocate enough to set one off every few seconds. Objects alive once the service is
ready live as long as the process, so they are moved out of the collector's reach
(``gc.freeze()``, as the ``gc`` docs advise for long-lived servers); a full collection then walks
only what was made since. Measured with ``benchmarks/slow_connections.py`` (docs/service.md).
"""

from __future__ import annotations

import ctypes
import gc
import os

#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Arrays up to this size come from the heap and stay there when freed, bytes (1M points' float64
#: (n, 3) arrays are 24 MB; glibc maps anything above 128 kB to fresh pages by default).
HELD_ARRAY_BYTES = 1 << 30
#: Freed memory at the heap's top beyond this goes back to the system, bytes (the largest glibc
#: takes, an int).
HELD_TOP_BYTES = 2**31 - 1


def settle_heap() -> None:
    """Collect today's garbage (frozen objects are never collected), then freeze what is left."""
    gc.collect()
    gc.freeze()


def hold_freed_memory() -> bool:
    """Keep the memory a batch frees for the next batch instead of returning it to the system
    (glibc's ``mallopt``): otherwise every large query maps its arrays anew and pays a page fault
    per 4 kB of them. The process keeps its peak memory. Returns whether the allocator took it:
    False when it is not glibc, or when ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` are
    set (the user's settings stand)."""
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (musl, macOS)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, HELD_ARRAY_BYTES) and mallopt(_M_TRIM_THRESHOLD, HELD_TOP_BYTES))
