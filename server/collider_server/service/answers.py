"""From validated queries to fields: each request becomes a :class:`QueryJob` on its model's
batcher, and :func:`answer_batch` answers a whole batch of jobs in the compute thread (points
moved to the collider frame, one compute call, answers assembled in the world frame, vectorised
across the requests that share a pose, eps and fields). The event loop only validates, queues and
encodes; the routers only translate HTTP.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from collider_contract import MAX_COORDINATE_M, Pose

from ..engine.collider import (
    GRADIENT_FIELDS,
    Collider,
    QueryResult,
    assemble_result,
    assemble_scene_result,
    gradient_threshold,
)
from .batching import BatcherClosed, BatchPart, DeadlineExceeded, QueueFull
from .bodies import QuerySpec, SceneSpec
from .problems import Problem
from .registry import LoadedModel

#: Largest float32 magnitude: answers beyond it would be sent as Infinity.
FLOAT32_MAX = float(np.finfo(np.float32).max)


@dataclass(eq=False)
class QueryJob:
    """One request's work for a model's batcher.

    points : (n, 3) float32/float64, world frame, validated (finite)
    pose : collider frame -> world frame
    eps : collision offset, world units (already resolved)
    fields : the fields to answer, canonical order
    local_only : answer ``distance`` and ``normal`` in the collider frame, float64, unassembled
        (the scene query picks the nearest collider per point before assembling)
    only_colliding : ``normal`` and ``contact`` only where ``distance < eps`` (collide-only)
    """

    points: np.ndarray
    pose: Pose
    eps: float
    fields: tuple[str, ...]
    local_only: bool = False
    only_colliding: bool = False

    @property
    def want_gradient(self) -> bool:
        return not GRADIENT_FIELDS.isdisjoint(self.fields)

    def gradient_below(self) -> float:
        """Collider-unit distance below which this job's points need a normal (+inf: all)."""
        if not self.want_gradient:
            return -np.inf
        return gradient_threshold(self.eps, self.pose) if self.only_colliding else np.inf

    def group_key(self) -> tuple:
        """Jobs with equal keys are assembled together in one vectorised step."""
        pose = self.pose
        return (pose.rotation.tobytes(), pose.translation.tobytes(), pose.scale, self.eps,
                self.fields, self.points.dtype.str, self.local_only, self.only_colliding)


def answer_batch(collider: Collider, name: str,
                 parts: Sequence[BatchPart]) -> list[dict[str, np.ndarray] | Exception]:
    """The answers of a batch of :class:`QueryJob` parts (runs in the compute thread).

    Parts are grouped by :meth:`QueryJob.group_key`; each group's points are moved to the
    collider frame in one step, the whole batch is computed in one ``query_local`` call, and each
    group is assembled in one step (:func:`assemble_result`), then cut into the parts' rows.
    A part whose answer is not finite (points astronomically far from the collider) gets a 422
    problem; the others are answered."""
    # Points astronomically far away overflow on the way (checked below): no warnings for that.
    with np.errstate(over="ignore", invalid="ignore"):
        return _answer_batch(collider, name, parts)


def _answer_batch(collider: Collider, name: str, parts: Sequence[BatchPart]) -> list:
    groups: dict[tuple, list[int]] = {}
    for i, part in enumerate(parts):
        groups.setdefault(part.payload.group_key(), []).append(i)
    # Each group's world points, contiguous; the batch's collider-frame points in group order.
    world, locals_ = [], []
    for members in groups.values():
        job = parts[members[0]].payload
        points = _rows(parts, members, lambda p: p.payload.points)
        world.append(points)
        locals_.append(job.pose.to_local(points))
    local = locals_[0] if len(locals_) == 1 else np.concatenate(locals_)
    want_gradient = any(p.payload.want_gradient for p in parts)
    below = None
    if want_gradient and any(p.payload.only_colliding for p in parts):
        # Collide-only jobs: a normal only for their colliding points; the batch's other jobs
        # keep theirs (+inf: every point, -inf: none), one threshold per point in group order.
        below = np.concatenate([np.full(len(points), parts[members[0]].payload.gradient_below())
                                for members, points in zip(groups.values(), world)])
    distance, normal = collider.query_local(local, want_gradient, below)
    answers: list = [None] * len(parts)
    offset = 0
    for members, points in zip(groups.values(), world):
        job = parts[members[0]].payload
        rows = slice(offset, offset + len(points))
        offset += len(points)
        d, n = distance[rows], (None if normal is None else normal[rows])
        if job.local_only:
            group = {"distance": d, **({} if n is None else {"normal": n})}
            bad = None
        else:
            result = assemble_result(points, job.pose, job.eps, job.fields, d, n, job.only_colliding)
            group = result.fields()
            bad = _not_finite(group)
        start = 0
        for i in members:
            part = parts[i]
            cut = slice(start, start + part.rows)
            start += part.rows
            if bad is not None and bad[cut].any():
                answers[i] = _out_of_range(name, part, int(np.flatnonzero(bad[cut])[0]))
            else:
                answers[i] = {k: v[cut] for k, v in group.items()}
    return answers


def _rows(parts: Sequence[BatchPart], members: list[int], array) -> np.ndarray:
    """The members' rows of ``array(part)`` stacked (a view when there is one member)."""
    if len(members) == 1:
        part = parts[members[0]]
        return array(part)[part.start:part.stop]
    return np.concatenate([array(parts[i])[parts[i].start:parts[i].stop] for i in members])


def _not_finite(fields: dict[str, np.ndarray]) -> np.ndarray | None:
    """Rows with an answer that is not a finite number, or None when all are finite. A float32
    field overflows beyond ~3.4e38; the service never sends NaN or Infinity. (Within the
    engine's coordinate range nothing overflows: one cheap check per field, rows only if not.)"""
    floats = [v for v in fields.values() if v.dtype.kind == "f"]
    if all(np.isfinite(v).all() for v in floats):
        return None
    bad = np.zeros(len(floats[0]), dtype=bool)
    for values in floats:
        bad |= ~(np.isfinite(values) if values.ndim == 1 else np.isfinite(values).all(axis=1))
    return bad


def _out_of_range(name: str, part: BatchPart, row: int) -> Problem:
    job: QueryJob = part.payload
    index = part.start + row
    return Problem(422, "out-of-range",
                   f"points row {index} ({job.points[index].tolist()}) has no finite answer: it "
                   f"lies too far from model {name!r} (world frame, with the pose given)")


def absolute_deadline(deadline_ms: float | None, default_ms: float | None) -> float | None:
    """A relative deadline in ms as a ``time.monotonic`` time (the batchers' clock)."""
    ms = deadline_ms if deadline_ms is not None else default_ms
    return None if ms is None else time.monotonic() + ms / 1000.0


def resolve_eps(model: LoadedModel, pose: Pose, eps: float | None) -> float:
    """The request's eps in world units: its own, in ``[0, MAX_COORDINATE_M]``, or 1 mm (the
    collider's default, scaled by the pose). (The bound is the engine's coordinate range, not
    the model's size: a schema can state it, and a large eps is odd but well defined.)"""
    if eps is None:
        return model.collider.info.default_world_eps(pose)
    if not 0 <= eps <= MAX_COORDINATE_M:
        raise Problem(422, "eps-out-of-range",
                      f"eps={eps} is outside [0, {MAX_COORDINATE_M:g}] (world units)")
    return eps


async def submit(model: LoadedModel, job: QueryJob, deadline: float | None) -> dict:
    """``job``'s answer through the model's batcher, with the batcher's errors as problems
    (429, 503, 504)."""
    try:
        return await model.batcher.submit_rows(job, len(job.points), deadline)
    except QueueFull as exc:
        raise Problem(429, "queue-full", f"model {model.name!r}: {exc}",
                      {"Retry-After": str(exc.retry_after_s)}) from None
    except DeadlineExceeded as exc:
        raise Problem(504, "deadline-exceeded", f"model {model.name!r}: {exc}") from None
    except BatcherClosed as exc:
        raise Problem(503, "unavailable", f"model {model.name!r}: {exc}",
                      {"Retry-After": "1"}) from None


async def answer_query(model: LoadedModel, spec: QuerySpec,
                       deadline: float | None) -> dict[str, np.ndarray]:
    """The fields of one model query by name (world frame, see :class:`QueryResult`);
    ``deadline`` is a ``time.monotonic`` time or None."""
    eps = resolve_eps(model, spec.pose, spec.eps)
    job = QueryJob(spec.points, spec.pose, eps, spec.fields, only_colliding=spec.only_colliding)
    return await submit(model, job, deadline)


async def answer_scene(models: list[LoadedModel], spec: SceneSpec,
                       deadline: float | None) -> tuple[QueryResult, np.ndarray]:
    """Per point, the fields of the collider with the smallest world-frame signed distance, and
    that collider's index ``(n,) int32`` into ``spec.colliders`` (the engine's scene rule,
    :func:`~collider_server.engine.collider.nearest_collider`, shared with the embedded backend)."""
    poses = [pose for _, pose in spec.colliders]
    eps = [resolve_eps(m, pose, spec.eps) for m, pose in zip(models, poses)]
    answers = await asyncio.gather(*(
        submit(m, QueryJob(spec.points, pose, e, spec.fields, local_only=True,
                           only_colliding=spec.only_colliding), deadline)
        for m, pose, e in zip(models, poses, eps)))
    with np.errstate(over="ignore", invalid="ignore"):
        result, nearest = assemble_scene_result(
            spec.points, poses, eps, spec.fields,
            [(a["distance"], a.get("normal")) for a in answers], spec.only_colliding)
    bad = _not_finite(result.fields())
    if bad is not None:
        row = int(np.flatnonzero(bad)[0])
        raise Problem(422, "out-of-range",
                      f"points row {row} ({spec.points[row].tolist()}) has no finite answer: it "
                      "lies too far from the colliders (world frame, with the poses given)")
    return result, nearest


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
