"""From validated queries to answers, with the contract's steps (:mod:`collider_contract.answers`).

Each request becomes a :class:`QueryJob` on its model's batcher. :func:`answer_batch` answers a
whole batch of jobs in the compute thread: ``prepare`` (points to the collider frame, the eps and
gradient needs), one evaluation of the collider for the whole batch, ``finish`` (the fields in
the world frame), vectorised across the requests that share a pose, eps, fields and mode. A scene
query's colliders are jobs on their own models' batchers; the nearest collider's fields are kept
per point (``finish_scene``) on the event loop, which otherwise only reads, validates, queues and
encodes. The routers only translate HTTP.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from collider_contract import (
    ModelQuery,
    QueryError,
    QueryResult,
    SceneQuery,
    check_finite,
    finish,
    finish_scene,
    prepare,
    require_time,
    resolve_eps,
)

from ..engine.collider import Collider
from .batching import BatcherClosed, BatchPart, DeadlineExceeded, QueueFull
from .problems import Problem
from .registry import LoadedModel


@dataclass(eq=False)
class QueryJob:
    """One request's work for a model's batcher.

    query : the validated query (points world frame, pose, eps, fields, mode)
    local_only : answer ``(distance, normal)`` in the collider frame, float64, unassembled (a
        scene query picks the nearest collider per point before assembling)
    """

    query: ModelQuery
    local_only: bool = False

    def group_key(self) -> tuple:
        """Jobs with equal keys are answered together as one query over their joined points."""
        q = self.query
        return (q.pose.rotation.tobytes(), q.pose.translation.tobytes(), q.pose.scale, q.eps,
                q.fields, q.points.dtype.str, q.only_colliding, q.time,
                None if q.pose_velocity is None else q.pose_velocity.tobytes(),
                None if q.skeleton is None else q.skeleton.key(), self.local_only)


def answer_batch(collider: Collider, name: str,
                 parts: Sequence[BatchPart]) -> list[dict[str, np.ndarray] | Exception]:
    """The answers of a batch of :class:`QueryJob` parts (runs in the compute thread): per part
    its fields by name (or ``distance``/``normal`` for a local-only job), or the
    :class:`~collider_contract.QueryError` of a part whose answer is not finite (the others are
    answered)."""
    # Points astronomically far away overflow on the way (checked by check_finite): no warnings.
    with np.errstate(over="ignore", invalid="ignore"):
        return _answer_batch(collider, name, parts)


def _answer_batch(collider: Collider, name: str, parts: Sequence[BatchPart]) -> list:
    groups: dict[tuple, list[int]] = {}
    for i, part in enumerate(parts):
        groups.setdefault(part.payload.group_key(), []).append(i)
    # Each group as one query over its members' rows; one evaluation for the whole batch.
    queries, evaluations = [], []
    for members in groups.values():
        job = parts[members[0]].payload
        query = dataclasses.replace(job.query, points=_rows(parts, members))
        queries.append(query)
        evaluations.append(prepare(query, collider.info.meters_per_unit))
    # One evaluation per time (and skeleton pose) asked: a static collider ignores time, one
    # evaluation for the whole batch.
    by_time: dict = {}
    for g, evaluation in enumerate(evaluations):
        key = None
        if collider.animated or collider.skinned:
            key = (evaluation.time,
                   None if evaluation.skeleton is None else evaluation.skeleton.key())
        by_time.setdefault(key, []).append(g)
    outputs: list = [None] * len(evaluations)
    for members_of_time in by_time.values():
        together = [evaluations[g] for g in members_of_time]
        for g, output in zip(members_of_time, _evaluate_together(collider, together), strict=True):
            outputs[g] = output
    answers: list = [None] * len(parts)
    for members, query, evaluation, output in zip(groups.values(), queries, evaluations, outputs,
                                                  strict=True):
        if parts[members[0]].payload.local_only:
            group = {name: value for name, value
                     in zip(("distance", "normal", "velocity"), output, strict=True) if value is not None}
        else:
            group = finish(query, evaluation.eps, *output).fields()
        start = 0
        for i in members:
            part = parts[i]
            cut = slice(start, start + part.rows)
            start += part.rows
            answers[i] = {k: v[cut] for k, v in group.items()}
            if not part.payload.local_only:
                try:
                    check_finite(QueryResult(**answers[i]), part.payload.query.points[part.start:part.stop],
                                 f"model {name!r}", first_row=part.start)
                except QueryError as exc:
                    answers[i] = exc
    return answers


def _evaluate_together(collider: Collider, evaluations: list) -> list[tuple]:
    """``evaluations``' points in one ``query_local`` call at their (shared) time and skeleton
    pose, cut back into one ``(distance, normal, velocity)`` per evaluation."""
    local = np.concatenate([e.local for e in evaluations]) if len(evaluations) > 1 else evaluations[0].local
    want_gradient = any(e.want_gradient for e in evaluations)
    below = None
    if want_gradient and any(e.gradient_below is not None for e in evaluations):
        # Collide-only jobs: a normal only for their colliding points; the batch's other jobs
        # keep theirs (+inf: every point, -inf: none), one threshold per point in group order.
        below = np.concatenate([np.full(len(e.local), _threshold(e)) for e in evaluations])
    at = evaluations[0]
    if at.skeleton is None:
        outputs = collider.query_local(local, want_gradient, below, at.time)
    else:
        outputs = collider.query_local(local, want_gradient, below, at.time, at.skeleton)
    cut, offset = [], 0
    for evaluation in evaluations:
        rows = slice(offset, offset + len(evaluation.local))
        offset += len(evaluation.local)
        cut.append(tuple(None if value is None else value[rows] for value in outputs))
    return cut


def _threshold(evaluation) -> float:
    """An evaluation's gradient threshold as a number: +inf (a normal everywhere) or -inf (none)
    when it has no collide-only threshold."""
    if evaluation.gradient_below is not None:
        return evaluation.gradient_below
    return np.inf if evaluation.want_gradient else -np.inf


def _rows(parts: Sequence[BatchPart], members: list[int]) -> np.ndarray:
    """The members' query points, their parts' rows stacked (a view when there is one member)."""
    if len(members) == 1:
        part = parts[members[0]]
        return part.payload.query.points[part.start:part.stop]
    return np.concatenate([parts[i].payload.query.points[parts[i].start:parts[i].stop] for i in members])


def absolute_deadline(deadline_ms: float | None, default_ms: float | None) -> float | None:
    """A relative deadline in ms as a ``time.monotonic`` time (the batchers' clock)."""
    ms = deadline_ms if deadline_ms is not None else default_ms
    return None if ms is None else time.monotonic() + ms / 1000.0


async def submit(model: LoadedModel, job: QueryJob, deadline: float | None) -> dict:
    """``job``'s answer through the model's batcher, with the batcher's errors as problems
    (429, 503, 504)."""
    try:
        return await model.batcher.submit_rows(job, len(job.query.points), deadline)
    except QueueFull as exc:
        raise Problem(429, "queue-full", f"model {model.name!r}: {exc}",
                      {"Retry-After": str(exc.retry_after_s)}) from None
    except DeadlineExceeded as exc:
        raise Problem(504, "deadline-exceeded", f"model {model.name!r}: {exc}") from None
    except BatcherClosed as exc:
        raise Problem(503, "unavailable", f"model {model.name!r}: {exc}",
                      {"Retry-After": "1"}) from None


async def answer_query(model: LoadedModel, query: ModelQuery,
                       deadline: float | None) -> dict[str, np.ndarray]:
    """The fields of one model query by name (world frame, see :class:`QueryResult`);
    ``deadline`` is a ``time.monotonic`` time or None."""
    require_time(query, model.info.animated, f"model {model.name!r}", model.info.skeleton)
    return await submit(model, QueryJob(query), deadline)


async def answer_scene(models: list[LoadedModel], query: SceneQuery,
                       deadline: float | None) -> QueryResult:
    """Per point, the fields of the collider with the smallest world-frame signed distance and
    ``collider``, its index into ``query.colliders`` (the contract's scene rule)."""
    for i, model in enumerate(models):
        require_time(query.of_collider(i), model.info.animated, f"model {model.name!r}",
                     model.info.skeleton)
    answers = await asyncio.gather(*(
        submit(model, QueryJob(query.of_collider(i), local_only=True), deadline)
        for i, model in enumerate(models)))
    eps = [resolve_eps(query.eps, model.collider.info.meters_per_unit, placed.pose)
           for model, placed in zip(models, query.colliders, strict=True)]
    with np.errstate(over="ignore", invalid="ignore"):
        return finish_scene(query, eps, [(a["distance"], a.get("normal"), a.get("velocity"))
                                         for a in answers])


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
