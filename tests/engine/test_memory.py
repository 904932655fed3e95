"""``engine/memory.py``: glibc keeps what a large query frees for the next one (``collider serve``
and ``collider bench`` ask for it at start)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

#: Ten (1M, 3) float64 arrays, allocated together, freed together, three times: what a 1M-point
#: query does with its temporaries. Prints the page faults of the third round.
ROUNDS_OF_ARRAYS = """
import resource, sys
import numpy as np
from collider_server.engine.memory import hold_freed_memory
print(hold_freed_memory())
for round in range(3):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    arrays = [np.ones((1_000_000, 3)) for _ in range(10)]
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    del arrays
print(faults)
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_memory_freed_by_one_query_serves_the_next_without_page_faults():
    """With ``hold_freed_memory`` the arrays of a query come from memory the previous one freed
    (glibc otherwise returns it and maps fresh pages: one fault per 4 kB, 0.1 s of a 1M-point
    query); the user's own MALLOC_* settings stand."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    held = subprocess.run([sys.executable, "-c", ROUNDS_OF_ARRAYS], env=env, capture_output=True, text=True,
                          timeout=120)
    assert held.returncode == 0, held.stderr
    took, faults = held.stdout.split()
    pages = 10 * 24_000_000 // 4096
    assert int(took) >= 32 << 20 and int(faults) < pages // 100, (took, faults, pages)  # glibc alone: ~8 %
    theirs = subprocess.run([sys.executable, "-c", ROUNDS_OF_ARRAYS], capture_output=True, text=True, timeout=120,
                            env={**env, "MALLOC_TRIM_THRESHOLD_": "131072"})
    assert theirs.stdout.split()[0] == "0", theirs.stdout + theirs.stderr
