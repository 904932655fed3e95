"""From validated queries to fields: move points to each collider's frame, queue them on its
batcher, and assemble each request's answer (plain functions; the routers only translate HTTP)."""

from __future__ import annotations

import asyncio
import time

import numpy as np

from ..batching import BatcherClosed, DeadlineExceeded, QueueFull
from ..collider import GRADIENT_FIELDS, QueryResult, assemble_result, assemble_scene_result
from ..pose import Pose
from .bodies import QuerySpec, SceneSpec
from .problems import Problem
from .registry import LoadedModel


def absolute_deadline(deadline_ms: float | None, default_ms: float | None) -> float | None:
    """A relative deadline in ms as a ``time.monotonic`` time (the batchers' clock)."""
    ms = deadline_ms if deadline_ms is not None else default_ms
    return None if ms is None else time.monotonic() + ms / 1000.0


def resolve_eps(model: LoadedModel, pose: Pose, eps: float | None) -> float:
    """The request's eps in world units: its own, checked against ``[0, domain diagonal]``,
    or 1 mm (the collider's default, scaled by the pose)."""
    if eps is None:
        return model.collider.info.default_world_eps(pose)
    limit = model.domain_diagonal * pose.scale
    if not 0 <= eps <= limit:
        raise Problem(422, "eps-out-of-range",
                      f"eps={eps} is outside [0, {limit:.6g}] (world units; the upper bound is "
                      f"the diagonal of model {model.name!r}'s domain box)")
    return eps


async def compute(model: LoadedModel, points: np.ndarray, pose: Pose, want_gradient: bool,
                  deadline: float | None):
    """Collider-frame ``(distance, normal)`` of world-frame ``points`` through the batcher,
    with the batcher's errors as problems (429, 503, 504)."""
    local = pose.to_local(points)
    try:
        return await model.batcher.submit(local, want_gradient, deadline)
    except QueueFull as exc:
        raise Problem(429, "queue-full", f"model {model.name!r}: {exc}",
                      {"Retry-After": str(exc.retry_after_s)}) from None
    except DeadlineExceeded as exc:
        raise Problem(504, "deadline-exceeded", f"model {model.name!r}: {exc}") from None
    except BatcherClosed as exc:
        raise Problem(503, "unavailable", f"model {model.name!r}: {exc}",
                      {"Retry-After": "1"}) from None


async def answer_query(model: LoadedModel, spec: QuerySpec, deadline: float | None) -> QueryResult:
    """The fields of one model query (world frame, see :class:`QueryResult`); ``deadline`` is a
    ``time.monotonic`` time or None."""
    eps = resolve_eps(model, spec.pose, spec.eps)
    want_gradient = not GRADIENT_FIELDS.isdisjoint(spec.fields)
    distance, normal = await compute(model, spec.points, spec.pose, want_gradient, deadline)
    return assemble_result(spec.points, spec.pose, eps, spec.fields, distance, normal)


async def answer_scene(models: list[LoadedModel], spec: SceneSpec,
                       deadline: float | None) -> tuple[QueryResult, np.ndarray]:
    """Per point, the fields of the collider with the smallest world-frame signed distance, and
    that collider's index ``(n,) int32`` into ``spec.colliders`` (the engine's scene rule,
    :func:`~collider_server.collider.nearest_collider`, shared with the embedded backend)."""
    poses = [pose for _, pose in spec.colliders]
    eps = [resolve_eps(m, pose, spec.eps) for m, pose in zip(models, poses)]
    want_gradient = not GRADIENT_FIELDS.isdisjoint(spec.fields)
    answers = await asyncio.gather(*(
        compute(m, spec.points, pose, want_gradient, deadline) for m, pose in zip(models, poses)))
    return assemble_scene_result(spec.points, poses, eps, spec.fields, answers)


async def _cancel_on_disconnect(receive, task: asyncio.Task, gone: list) -> None:
    """Cancel ``task`` when the client disconnects (the body must already be read)."""
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            gone.append(True)
            task.cancel()
            return


async def unless_disconnected(receive, coro):
    """Await ``coro``; if the client disconnects first, cancel it (its request leaves the queue)
    and raise a 499-style problem that nobody will read. One watcher task per request: the work
    itself runs in the request's own task."""
    task = asyncio.current_task()
    gone: list = []
    watcher = asyncio.get_running_loop().create_task(_cancel_on_disconnect(receive, task, gone))
    try:
        return await coro
    except asyncio.CancelledError:
        if not gone:
            raise
        if hasattr(task, "uncancel"):  # Python >= 3.11: this cancellation is handled here
            task.uncancel()
        raise Problem(499, "client-closed", "the client disconnected before the answer was ready")
    finally:
        watcher.cancel()
