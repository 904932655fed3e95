"""The models a service holds: loading (off the event loop), warm-up, unloading, readiness."""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from collider_contract import ModelInfo

from ..engine.collider import Collider
from ..engine.repository import LoadedCollider, ModelRepository
from .batching import BatchPart, BatchSettings, DeviceWorkers, RowBatcher
from .metrics import ServiceMetrics

log = logging.getLogger("collider_server.service")


@dataclass
class LoadedModel:
    """A model being served: its collider, its batcher, and its public info (``GET
    /v1/models/{name}``)."""

    name: str
    collider: Collider
    batcher: RowBatcher
    info: ModelInfo


#: ``answer_batch(collider, name, parts) -> answers``: what a model's batcher runs per batch
#: (the service's :func:`~.query_jobs.answer_batch`, given to the registry by the app).
AnswerBatch = Callable[[Collider, str, Sequence[BatchPart]], list]


def warm_up(collider: Collider) -> None:
    """One small query with gradient, so the first real request pays no lazy initialisation."""
    centre = 0.5 * (collider.domain_min + collider.domain_max)
    collider.query_local(np.tile(centre, (64, 1)), True, None, 0.0 if collider.animated else None)


class ModelRegistry:
    """Models by name. Only :meth:`load`, :meth:`unload` and :meth:`close` change it; lookups
    are plain dict reads on the event loop."""

    def __init__(self, repository: ModelRepository, device: str, batch: BatchSettings,
                 workers: DeviceWorkers, metrics: ServiceMetrics, answer_batch: AnswerBatch,
                 warmup: bool = True):
        self.repository = repository
        self.answer_batch = answer_batch
        self.device = device
        self.batch = batch
        self.workers = workers
        self.metrics = metrics
        self.warmup = warmup
        self.models: dict[str, LoadedModel] = {}
        self.errors: dict[str, str] = {}  # models that failed to load at start-up, and why
        self.ready = False

    def get(self, name: str) -> LoadedModel | None:
        return self.models.get(name)

    async def load_all(self, before_ready: Callable[[], object] = lambda: None) -> None:
        """Load every model of the repository, call ``before_ready()``, then become ready. A
        model that fails to load is logged and listed in ``errors``; the others are served."""
        for name in self.repository.names():
            try:
                await self.load(name)
            except Exception as exc:  # noqa: BLE001 -- a broken file must not keep the others from serving
                self.errors[name] = str(exc)
                log.error("model %s not loaded: %s", name, exc)
        before_ready()
        self.ready = True
        log.info("ready: %d model(s) loaded (%s)", len(self.models), ", ".join(self.models) or "none")

    async def load(self, name: str) -> LoadedModel:
        """Load (or reload) ``name`` from the repository in a thread; the old version, if any,
        answers its queued requests before it goes. Raises ValueError / FileNotFoundError /
        ModelFileError."""
        self.repository.model_file(name)  # an invalid or absent name fails before the thread
        collider, info = await asyncio.to_thread(self._load_and_warm, name)
        # Nothing may fail between creating the batcher (its loop task starts at once) and
        # registering it, or the task would be left running with no one to close it.
        batcher = RowBatcher(functools.partial(self.answer_batch, collider, name), self.batch,
                             self.workers.executor(collider.device),
                             on_batch=self.metrics.batch_observer(name))
        self.metrics.watch_queue(name, batcher)
        model = LoadedModel(name, collider, batcher, info)
        old = self.models.get(name)
        self.models[name] = model
        self.errors.pop(name, None)
        self.metrics.models_loaded.set(len(self.models))
        if old is not None:
            await old.batcher.drain()
        log.info("loaded %s (%s on %s)", name, collider.info.kind, collider.device)
        return model

    def _load_and_warm(self, name: str) -> LoadedCollider:
        """The repository's model ``name``, loaded (as the SDK's embedded backend loads it) and
        warmed up; a file replaced or removed meanwhile fails here, before any batcher exists."""
        loaded = self.repository.load_model(name, self.device)
        if self.warmup:
            warm_up(loaded.collider)
        return loaded

    async def unload(self, name: str) -> bool:
        """Stop serving ``name``: new requests get 404 at once, queued ones are answered."""
        model = self.models.pop(name, None)
        if model is None:
            return False
        self.metrics.models_loaded.set(len(self.models))
        await model.batcher.drain()
        self.metrics.forget(name)
        log.info("unloaded %s", name)
        return True

    async def close(self) -> None:
        """Answer everything queued, then stop every batcher."""
        self.ready = False
        await asyncio.gather(*(m.batcher.drain() for m in self.models.values()))
