"""The embedded backend: the engine in this process (needs the ``serve`` extra: torch, ...).

``collider_server`` is imported on first use only, so ``import collider_client`` stays light.
Queries arrive validated by the contract (as the service validates them) and are answered with
its :func:`~collider_contract.answer_model_query` and :func:`~collider_contract.answer_scene_query`
over the engine's colliders: the same code as the service, so the same answers and refusals.
"""

from __future__ import annotations

import threading
from pathlib import Path

from collider_contract import (
    ModelInfo,
    ModelQuery,
    QueryError,
    QueryResult,
    SceneQuery,
    answer_model_query,
    answer_scene_query,
    unknown_model,
)

from ._base import refusal
from ._exceptions import ModelNotFoundError


class EmbeddedBackend:
    """Colliders loaded from a model repository folder (``models``, default ``models/``) on
    ``device`` ("cpu", "cuda", None = CUDA if present). Loaded models are kept for reuse.

    The service's twin: a model is a repository NAME, never a file path; it is loaded as the
    service loads it (:meth:`~collider_server.engine.ModelRepository.load_model`), and the models
    listed (and named in an unknown model's refusal) are the loaded ones, as the service lists
    them (:func:`~collider_server.engine.served_models`), so listing loads every model.

    threads : torch CPU threads for the engine (process-wide, as torch's setting is); None
        leaves torch's default. On a busy CPU, fewer threads than cores avoid spin-waiting
        (``collider serve`` uses cores - 1 for the same reason).
    """

    def __init__(self, models: str | Path | None = None, device: str | None = None,
                 threads: int | None = None):
        try:
            from collider_server.engine import ModelRepository
        except ImportError as exc:  # the light install has no engine
            raise ImportError(
                "the embedded backend needs the engine: pip install 'neural-collider[serve]' "
                f"(or give a server URL to use a running `collider serve`) [{exc}]"
            ) from None
        if threads is not None:
            if threads < 1:
                raise ValueError(f"threads must be >= 1, got {threads}")
            import torch

            torch.set_num_threads(threads)
        self.repository = ModelRepository(models)
        self.device = device
        self._loaded: dict[str, object] = {}  # name -> the engine's LoadedCollider
        self._failed: dict[str, str] = {}  # names whose file did not load, and why
        self._lock = threading.Lock()

    def _load(self, name: str):
        """The loaded model ``name`` (the lock held)."""
        if name not in self._loaded:
            self._loaded[name] = self.repository.load_model(name, self.device)
        return self._loaded[name]

    def _load_all(self) -> None:
        """Every model of the repository, as the service loads them at start: a file that does
        not load is not served (the lock held)."""
        for name in self.repository.names():
            if name not in self._loaded and name not in self._failed:
                try:
                    self._load(name)
                except Exception as exc:  # noqa: BLE001 -- as the service: the others are served
                    self._failed[name] = str(exc)

    def collider(self, name: str):
        """The loaded engine collider ``name`` (loads it on first use); the service's 404 for a
        name the repository does not hold, a path given as a name included."""
        from collider_server.engine import ModelFileError

        with self._lock:
            try:
                return self._load(name).collider
            except ModelFileError as exc:  # a file there, but not a usable model
                raise ModelNotFoundError(f"model {name!r} cannot be loaded: {exc}") from None
            except (FileNotFoundError, ValueError):  # absent, or not a name
                self._load_all()
                raise refusal(unknown_model(name, self._loaded)) from None

    def query(self, model: str, query: ModelQuery) -> QueryResult:
        collider = self.collider(model)
        try:
            result = answer_model_query(query, collider.info.meters_per_unit, collider.query_local,
                                        f"model {model!r}", collider.animated,
                                        collider.info.skeleton)
        except QueryError as exc:
            raise refusal(exc) from None
        result.model = model
        return result

    def scene_query(self, query: SceneQuery) -> QueryResult:
        engines = [self.collider(placed.model) for placed in query.colliders]
        try:
            return answer_scene_query(query, [e.info.meters_per_unit for e in engines],
                                      [e.query_local for e in engines], [e.animated for e in engines],
                                      [e.info.skeleton for e in engines])
        except QueryError as exc:
            raise refusal(exc) from None

    def list_models(self) -> list[ModelInfo]:
        from collider_server.engine import served_models

        with self._lock:
            self._load_all()
            return served_models(self._loaded)

    def close(self) -> None:
        self._loaded.clear()
        self._failed.clear()
