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

    threads : torch CPU threads for the engine (process-wide, as torch's setting is); None
        leaves torch's default. On a busy CPU, fewer threads than cores avoid spin-waiting
        (``collider serve`` uses cores - 1 for the same reason).
    """

    def __init__(self, models: str | Path | None = None, device: str | None = None,
                 threads: int | None = None):
        try:
            from collider_server.engine.repository import ModelRepository
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
        self._colliders: dict[str, object] = {}
        self._lock = threading.Lock()

    def collider(self, name: str):
        """The loaded engine collider ``name`` (loads it on first use); the service's 404 for a
        name the repository does not hold."""
        from collider_server.engine.modelfile import ModelFileError

        with self._lock:
            if name not in self._colliders:
                try:
                    self._colliders[name] = self.repository.load(name, self.device)
                except ModelFileError as exc:  # a file there, but not a usable model
                    raise ModelNotFoundError(f"model {name!r} cannot be loaded: {exc}") from None
                except (FileNotFoundError, ValueError):  # absent, or an invalid name
                    raise refusal(unknown_model(name, self.repository.names())) from None
            return self._colliders[name]

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
        from collider_server.engine.devices import device_of, resolve_device
        from collider_server.engine.modelfile import read_info
        from collider_server.engine.repository import model_info

        device = resolve_device(self.device)
        models = []
        for name in self.repository.names():
            path = self.repository.path(name)
            info = read_info(path)
            models.append(model_info(name, info, path.stat().st_size, device_of(info.kind, device)))
        return models

    def close(self) -> None:
        self._colliders.clear()
