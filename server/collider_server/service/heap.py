"""The process's heap, settled once the models are loaded, so that garbage collection does not
pause requests in proportion to everything the process ever imported.

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

import gc


def settle_heap() -> None:
    """Collect today's garbage (frozen objects are never collected), then freeze what is left."""
    gc.collect()
    gc.freeze()
