"""The heap is settled before the service says it is ready (``service/heap.py``): what is alive
then (the imported modules, the loaded models) is out of the garbage collector's reach, so a full
collection, set off by thousands of connections opening and closing together, walks only what was
made since instead of pausing every request for the whole heap (figures: docs/service.md, "Slow
connections")."""

from __future__ import annotations

import gc

import httpx

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
