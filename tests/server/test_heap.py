"""The heap is settled before the service says it is ready (``service/heap.py``): what is alive
then (the imported modules, the loaded models) is out of the garbage collector's reach, so a full
collection, set off by thousands of connections opening and closing together, walks only what was
made since instead of pausing every request for the whole heap (figures: docs/service.md, "Slow
connections")."""

from __future__ import annotations

import gc
import os
import platform
import subprocess
import sys

import httpx
import pytest

from .conftest import ServerThread


def test_once_ready_the_collector_walks_only_what_was_made_since(repo):
    gc.unfreeze()  # this test process may hold a server started earlier
    assert gc.get_freeze_count() == 0
    with ServerThread(models=repo, device="cpu") as server:
        # Ready: the models are loaded and the heap frozen before /readyz said so.
        frozen = gc.get_freeze_count()
        walked = len(gc.get_objects())
        assert frozen > 50_000, frozen  # torch, numpy, FastAPI and the models
        assert walked < frozen / 4, (walked, frozen)
        assert httpx.get(f"{server.url}/v1/models").status_code == 200


#: Ten (1M, 3) float64 arrays, allocated together, freed together, three times: what a 1M-point
#: query does with its temporaries. Prints the page faults of the third round.
ROUNDS_OF_ARRAYS = """
import resource, sys
import numpy as np
from collider_server.service.heap import hold_freed_memory
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
    assert took == "True" and int(faults) < pages // 100, (faults, pages)  # glibc alone: ~8 %
    theirs = subprocess.run([sys.executable, "-c", ROUNDS_OF_ARRAYS], capture_output=True, text=True, timeout=120,
                            env={**env, "MALLOC_TRIM_THRESHOLD_": "131072"})
    assert theirs.stdout.split()[0] == "False", theirs.stdout + theirs.stderr
