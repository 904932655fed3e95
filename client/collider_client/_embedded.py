"""The embedded backend: the engine in this process (needs the ``server`` extras: torch, ...).

``collider_server`` is imported on first use only, so ``import collider_client`` stays light.
Answers are the ones the HTTP service gives for the same request: the same engine code, the same
defaults (eps 1 mm in world units) and the same rule for scene queries (per point, the fields of
the collider with the smallest signed distance; ties go to the first in the list).
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from collider_contract import GRADIENT_FIELDS, ModelInfo, QueryResult

from ._base import SceneCollider
from ._exceptions import InvalidValueError, ModelNotFoundError


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
                "the embedded backend needs the engine: pip install 'neural-collider[server]' "
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
        """The loaded engine collider ``name`` (loads it on first use)."""
        with self._lock:
            if name not in self._colliders:
                try:
                    self._colliders[name] = self.repository.load(name, self.device)
                except FileNotFoundError as exc:
                    raise ModelNotFoundError(str(exc)) from None
                except ValueError as exc:  # an invalid name is as unknown as a missing file
                    raise ModelNotFoundError(str(exc)) from None
            return self._colliders[name]

    def query(self, model: str, points: np.ndarray, fields: list[str], pose,
              eps: float | None, only_colliding: bool = False) -> QueryResult:
        collider = self.collider(model)
        try:
            result = collider.query(points, fields, pose=pose, eps=eps, only_colliding=only_colliding)
        except ValueError as exc:  # PoseError is a ValueError too
            raise InvalidValueError(str(exc)) from None
        return QueryResult(**result.fields(), model=model)

    def scene_query(self, colliders: list[SceneCollider], points: np.ndarray, fields: list[str],
                    eps: float | None, only_colliding: bool = False) -> QueryResult:
        from collider_contract import as_pose
        from collider_server.engine.collider import (
            assemble_scene_result,
            check_eps,
            check_fields,
            check_points,
            gradient_threshold,
        )

        try:
            fields_t = check_fields(fields)
            points = check_points(points)
            poses = [as_pose(c.pose) for c in colliders]
            eps_list = [None if eps is None else check_eps(eps)] * len(colliders)
        except ValueError as exc:
            raise InvalidValueError(str(exc)) from None
        engines = [self.collider(c.model) for c in colliders]
        eps_list = [engine.info.default_world_eps(pose) if e is None else e
                    for engine, pose, e in zip(engines, poses, eps_list)]
        want_gradient = not GRADIENT_FIELDS.isdisjoint(fields_t)
        answers = [engine.query_local(pose.to_local(points), want_gradient,
                                      gradient_threshold(e, pose) if only_colliding else None)
                   for engine, pose, e in zip(engines, poses, eps_list)]
        # The engine's scene rule, the one the service uses: identical answers, ties included.
        result, nearest = assemble_scene_result(points, poses, eps_list, fields_t, answers,
                                                only_colliding)
        return QueryResult(**result.fields(), collider=nearest)

    def list_models(self) -> list[ModelInfo]:
        from collider_server.engine.modelfile import read_info

        out = []
        for name in self.repository.names():
            path = self.repository.path(name)
            info = read_info(path).to_dict()
            # The name a query uses is the file's, whatever name the model was made under.
            info.update(name=name, bytes=path.stat().st_size, device=self._device_name())
            out.append(ModelInfo.from_dict(info))
        return out

    def _device_name(self) -> str:
        from collider_server.engine.devices import resolve_device

        return resolve_device(self.device)

    def close(self) -> None:
        self._colliders.clear()

