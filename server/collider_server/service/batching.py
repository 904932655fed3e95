"""Request coalescing sized in rows (points): one queue per model, one compute call per batch.

Concurrent requests for the same model are joined into one call of a batch function, the way
Triton's dynamic batcher and Ray Serve's ``@serve.batch`` join requests, except that a batch is
measured in rows (points), not requests:

- a batch closes when it holds ``max_batch_points`` rows or ``max_wait_ms`` after its oldest
  request was queued, whichever comes first;
- a request larger than ``max_batch_points`` is split across consecutive batches and reassembled;
- the batch function gets every request's part of the batch (:class:`BatchPart`: the request's
  opaque payload and its row range) and returns one answer per part, so whatever work is per
  point (moving points between frames, assembling answers) runs once per batch, vectorised across
  requests, in the compute thread: the event loop only queues and hands out answers;
- each caller gets exactly its own rows back; a part answered with an exception fails only its
  own request, and a failing batch function fails only the requests in that batch;
- the queue is bounded (``max_queue_points``): submitting raises :class:`QueueFull` at once
  instead of waiting;
- a request may carry a deadline (clock seconds): when it passes, the caller gets
  :class:`DeadlineExceeded` and the request leaves the queue; a cancelled caller (a client that
  disconnected) leaves the queue too;
- the batch function runs in a worker thread per device (:class:`DeviceWorkers`), never on the
  event loop.

:class:`RowBatcher` is the queue; the service gives it its batch function
(``collider_server.service.query_jobs.answer_batch``).

Only asyncio and numpy are used here: no HTTP. Policy (which status code "queue full" becomes) is
the web layer's business. The clock is injected (``time.monotonic`` by default) and the loop
waits on events and timers, never polls.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np


class BatchPart(NamedTuple):
    """Rows ``[start, stop)`` of one request (its ``payload``, as submitted) in a batch. (A named
    tuple: the event loop makes one per request per batch, and a frozen dataclass costs ~5x.)"""

    payload: Any
    start: int
    stop: int

    @property
    def rows(self) -> int:
        return self.stop - self.start


#: ``batch(parts) -> answers``: one answer per part, in order: a dict of arrays with
#: ``part.rows`` rows each, or an Exception that fails that part's request only. Runs in the
#: batcher's executor (a compute thread), never on the event loop.
BatchFn = Callable[[Sequence[BatchPart]], "list[dict[str, np.ndarray] | BaseException]"]

log = logging.getLogger(__name__)


#: Batches the throughput estimate (:meth:`RowBatcher.points_per_second`) looks back on.
RATE_WINDOW = 32


class BatchingError(Exception):
    """Root of the batcher's errors."""


class QueueFull(BatchingError):
    """The queue cannot take the request's points now; retry after ``retry_after_s`` seconds."""

    def __init__(self, points: int, queued_points: int, max_queue_points: int, retry_after_s: int):
        super().__init__(
            f"queue full: {queued_points} points queued, {points} more would exceed "
            f"max_queue_points={max_queue_points}"
        )
        self.points = points
        self.queued_points = queued_points
        self.max_queue_points = max_queue_points
        self.retry_after_s = retry_after_s


class DeadlineExceeded(BatchingError):
    """The request's deadline passed before its answer was ready; it left the queue."""


class BatcherClosed(BatchingError):
    """The batcher is shutting down (or its model was unloaded) and takes no new requests."""


class BatchContractError(BatchingError):
    """The batch (or compute) function returned answers that do not match the batch it was
    given: another number of answers than parts, or arrays of another row count."""


@dataclass(frozen=True)
class BatchSettings:
    """How requests are coalesced.

    max_batch_points : most points in one compute call
    max_wait_ms : longest time, milliseconds, a batch waits for more points after its oldest
        request was queued (0: dispatch whatever is queued as soon as the worker is free)
    max_queue_points : most points waiting in one model's queue; beyond it submit raises QueueFull
    coalesce : False computes every request on its own (one request per batch, still split at
        max_batch_points); the benchmark's "coalescing off"
    """

    max_batch_points: int = 65_536
    max_wait_ms: float = 0.0
    max_queue_points: int = 4_000_000
    coalesce: bool = True

    def __post_init__(self):
        for name in ("max_batch_points", "max_queue_points"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if not (isinstance(self.max_wait_ms, (int, float)) and math.isfinite(self.max_wait_ms)
                and self.max_wait_ms >= 0):
            raise ValueError(f"max_wait_ms must be a finite number >= 0, got {self.max_wait_ms!r}")


@dataclass(frozen=True)
class BatchStats:
    """What one compute call did, for metrics.

    points : points computed; requests : request parts in the batch;
    queue_wait_s : per part, seconds from its request's queueing to the batch start;
    compute_s : seconds the compute call took (in the worker thread, including hand-over)
    """

    points: int
    requests: int
    queue_wait_s: tuple[float, ...]
    compute_s: float


@dataclass(eq=False)
class _Pending:
    """One submitted request and, if it is split across batches, its answered pieces."""

    payload: Any
    size: int
    enqueued_at: float
    future: asyncio.Future
    pieces: list = field(default_factory=list)  # answers of a split request, in row order
    taken: int = 0  # rows handed to batches so far
    done: int = 0  # rows answered so far


class _Part(NamedTuple):
    request: _Pending
    start: int
    stop: int


class DeviceWorkers:
    """One compute thread per device, shared by every model on that device, so a device runs one
    batch at a time (a GPU gains nothing from overlapping kernels of different models, and a CPU
    uses its cores inside each call)."""

    def __init__(self, initializer: Callable[[], None] | None = None):
        """initializer : run once in each worker thread before its first batch (e.g. to set
        the compute library's thread count, which some libraries keep per thread)."""
        self._executors: dict[str, ThreadPoolExecutor] = {}
        self._initializer = initializer

    def executor(self, device: str) -> ThreadPoolExecutor:
        if device not in self._executors:
            self._executors[device] = ThreadPoolExecutor(
                1, thread_name_prefix=f"collider-{device}", initializer=self._initializer)
        return self._executors[device]

    def shutdown(self) -> None:
        for executor in self._executors.values():
            executor.shutdown(wait=True)
        self._executors.clear()


class RowBatcher:
    """The queue and batching loop of one model. Create it inside a running event loop.

    batch : see :data:`BatchFn`; called in ``executor`` with the parts of each batch
    settings : :class:`BatchSettings` (its "points" are rows)
    executor : where batch runs (``DeviceWorkers().executor(device)``)
    clock : monotonic seconds; deadlines passed to :meth:`submit_rows` are on this clock
    on_batch : called on the event loop with a :class:`BatchStats` after each batch
    """

    def __init__(self, batch: BatchFn, settings: BatchSettings, executor, *,
                 clock: Callable[[], float] = time.monotonic,
                 on_batch: Callable[[BatchStats], None] | None = None):
        self._batch = batch
        self.settings = settings
        self._executor = executor
        self._clock = clock
        self._on_batch = on_batch
        self._queue: collections.deque[_Pending] = collections.deque()
        self._queued_points = 0
        self._in_flight = 0
        self._wakeup = asyncio.Event()
        self._closing = False
        # (points, compute seconds) of the recent batches, for the Retry-After estimate.
        self._recent: collections.deque[tuple[int, float]] = collections.deque(maxlen=RATE_WINDOW)
        self._task = asyncio.get_running_loop().create_task(self._run())
        self._task.add_done_callback(self._loop_ended)

    # -- state ------------------------------------------------------------------------------

    @property
    def queued_points(self) -> int:
        """Rows (points) waiting for a batch (not yet handed to the batch function)."""
        return self._queued_points

    @property
    def queued_requests(self) -> int:
        return len(self._queue)

    @property
    def in_flight_points(self) -> int:
        return self._in_flight

    @property
    def closed(self) -> bool:
        return self._closing

    # -- the caller's side --------------------------------------------------------------------

    async def submit_rows(self, payload: Any, rows: int,
                          deadline: float | None = None) -> dict[str, np.ndarray]:
        """Queue a request of ``rows`` rows and wait for its answer.

        payload : handed to the batch function (in :class:`BatchPart`), never looked into here
        rows : the request's size in rows (points), >= 0; a request of 0 rows is answered at
            once by calling the batch function on the event loop (it has nothing to compute)
        deadline : clock time (seconds) after which the caller no longer wants the answer
        Returns the request's answer (see :data:`BatchFn`), its pieces joined if it was split.
        Raises :class:`QueueFull`, :class:`DeadlineExceeded`, :class:`BatcherClosed`, the
        exception the batch function gave this request, or whatever the batch function raised.
        """
        if self._closing:
            raise BatcherClosed("the model is shutting down or being unloaded")
        if rows == 0:
            answer = self._batch([BatchPart(payload, 0, 0)])
            _check_answers(answer, [0])
            if isinstance(answer[0], BaseException):
                raise answer[0]
            return answer[0]
        limit = self.settings.max_queue_points
        if self._queued_points + rows > limit:
            raise QueueFull(rows, self._queued_points, limit, self._retry_after_s(rows))
        now = self._clock()
        if deadline is not None and deadline <= now:
            raise DeadlineExceeded("the deadline passed before the request was queued")
        request = _Pending(payload, rows, now, asyncio.get_running_loop().create_future())
        self._queue.append(request)
        self._queued_points += rows
        # Wake the loop only when this changes its plan: the first request of an empty queue,
        # or a batch that is now full. Other arrivals just join the queue (no wake-up per request).
        if len(self._queue) == 1 or self._queued_points >= self.settings.max_batch_points:
            self._wakeup.set()
        try:
            if deadline is None:
                return await request.future
            # A timer (not a poll) ends the wait; wait_for cancels the future on expiry.
            return await asyncio.wait_for(request.future, max(deadline - self._clock(), 0.0))
        except asyncio.TimeoutError:
            self._drop(request)
            raise DeadlineExceeded(
                f"the deadline passed with {request.done} of {rows} points computed"
            ) from None
        except BaseException:  # the caller was cancelled (disconnected): leave the queue
            self._drop(request)
            raise

    def _drop(self, request: _Pending) -> None:
        """The caller left (deadline, cancellation, or its request already failed): its future
        is done, so answers still in flight are discarded (see :func:`_deliver`)."""
        try:
            self._queue.remove(request)
        except ValueError:
            return  # already fully handed to compute; its answers will be discarded
        self._queued_points -= request.size - request.taken

    def points_per_second(self) -> float:
        """The rate the queue drains at, points per second (0 before any batch): the median of the
        last :data:`RATE_WINDOW` batches' rates, each batch weighted by its points. One slow batch
        (a starved CPU, a stall) does not drag it, as it dragged an average of rates (Retry-After
        60 s for a queue that drained in under a second), and tiny batches, whose time is mostly
        overhead, weigh little."""
        if not self._recent:
            return 0.0
        rates = sorted((n / seconds, n) for n, seconds in self._recent)
        half, seen = sum(n for _, n in rates) / 2, 0
        for rate, n in rates:
            seen += n
            if seen >= half:
                return rate
        return rates[-1][0]  # not reached: the weights sum to 2 * half

    def _retry_after_s(self, points: int) -> int:
        """Whole seconds (1 to 60) until the queue has likely drained enough to take ``points``."""
        rate = self.points_per_second()
        if rate <= 0:
            return 1
        backlog = self._queued_points + self._in_flight + points
        return int(min(60, max(1, math.ceil(backlog / rate))))

    # -- shutdown ------------------------------------------------------------------------------

    def close(self) -> None:
        """Take no new requests; the queued ones are still answered (see :meth:`drain`)."""
        self._closing = True
        self._wakeup.set()

    async def drain(self) -> None:
        """Close, then wait until every accepted request has been answered (or failed, if the
        loop died). Never raises the loop's own end: a dead or cancelled loop must not fail, or
        look like a cancellation of, the caller that is shutting the batcher down."""
        self.close()
        # asyncio.wait neither cancels the loop when this caller is cancelled nor re-raises its
        # exception (``await shield(task)`` would do the latter).
        await asyncio.wait({self._task})

    # -- the batching loop ---------------------------------------------------------------------

    def _loop_ended(self, task: asyncio.Task) -> None:
        """If the loop ever dies (a bug, or cancellation), nobody waits forever: every queued
        request fails with :class:`BatcherClosed` (the batch in flight fails in
        :meth:`_execute`) and new ones are refused."""
        error = "cancelled" if task.cancelled() else task.exception()
        if error is None:
            return
        log.error("batching loop ended: %s", error)
        self._closing = True
        for request in self._queue:
            if not request.future.done():
                request.future.set_exception(BatcherClosed(f"the batching loop ended ({error})"))
        self._queue.clear()
        self._queued_points = 0

    async def _run(self) -> None:
        wait_s = self.settings.max_wait_ms / 1000.0
        while True:
            while not self._queue:
                if self._closing:
                    return
                self._wakeup.clear()
                await self._wakeup.wait()
            if self.settings.coalesce:
                # Wait for more points until the batch is full or its oldest request has waited
                # max_wait_ms; a split request's remainder is old, so it goes at once.
                close_at = self._queue[0].enqueued_at + wait_s
                loop = asyncio.get_running_loop()
                while (self._queue and self._queued_points < self.settings.max_batch_points
                       and not self._closing):
                    remaining = close_at - self._clock()
                    if remaining <= 0:
                        break
                    self._wakeup.clear()
                    timer = loop.call_later(remaining, self._wakeup.set)
                    try:
                        await self._wakeup.wait()
                    finally:
                        timer.cancel()
            parts = self._take_batch()
            if parts:
                await self._execute(parts)

    def _take_batch(self) -> list[_Part]:
        """Pop up to max_batch_points points off the queue head (splitting the last request)."""
        budget = self.settings.max_batch_points
        parts: list[_Part] = []
        while self._queue and budget > 0:
            request = self._queue[0]
            count = min(request.size - request.taken, budget)
            parts.append(_Part(request, request.taken, request.taken + count))
            request.taken += count
            budget -= count
            self._queued_points -= count
            if request.taken == request.size:
                self._queue.popleft()
            if not self.settings.coalesce:
                break
        return parts

    async def _execute(self, parts: list[_Part]) -> None:
        batch = [BatchPart(p.request.payload, p.start, p.stop) for p in parts]
        n = sum(p.stop - p.start for p in parts)
        started = self._clock()
        self._in_flight += n
        loop = asyncio.get_running_loop()
        try:
            answers = await loop.run_in_executor(self._executor, self._batch, batch)
            _check_answers(answers, [p.rows for p in batch])
        except BaseException as exc:
            # The batch failed: only this batch's requests see it. (If the loop itself is being
            # cancelled, they learn that the batcher is gone.)
            error = exc if isinstance(exc, Exception) else BatcherClosed(
                "the batching loop ended (cancelled)")
            for part in parts:
                if not part.request.future.done():
                    part.request.future.set_exception(error)
            if not isinstance(exc, Exception):
                raise
            return
        finally:
            self._in_flight -= n
        compute_s = max(self._clock() - started, 1e-9)
        self._recent.append((n, compute_s))
        for part, answer in zip(parts, answers, strict=True):  # _check_answers checked
            _deliver(part, answer)
        if self._on_batch is not None:
            waits = tuple(started - p.request.enqueued_at for p in parts)
            try:
                self._on_batch(BatchStats(n, len(parts), waits, compute_s))
            except Exception:  # a metrics hook must never stop the serving loop
                log.exception("on_batch hook failed")


def _deliver(part: _Part, answer) -> None:
    """Hand one part's answer to its request (joining the pieces of a split request)."""
    request = part.request
    if request.future.done():  # the caller left or the request already failed
        return
    if isinstance(answer, BaseException):
        request.future.set_exception(answer)
        return
    if part.start == 0 and part.stop == request.size:  # the common case: the whole request
        request.future.set_result(answer)
        return
    # Pieces arrive in row order: a request is taken from the queue head front to back, and
    # batches run one after another.
    request.pieces.append(answer)
    request.done += part.stop - part.start
    if request.done == request.size:
        request.future.set_result(
            {k: np.concatenate([a[k] for a in request.pieces]) for k in answer})


def _check_answers(answers, rows: list[int]) -> None:
    """The batch contract: one answer per part, each array with the part's row count."""
    if not isinstance(answers, (list, tuple)) or len(answers) != len(rows):
        got = len(answers) if isinstance(answers, (list, tuple)) else type(answers).__name__
        raise BatchContractError(f"the batch function returned {got} answers for {len(rows)} "
                                 "parts")
    for answer, n in zip(answers, rows, strict=True):
        if isinstance(answer, BaseException):
            continue
        for name, array in answer.items():
            if not isinstance(array, np.ndarray) or len(array) != n:
                shape = getattr(array, "shape", type(array).__name__)
                raise BatchContractError(f"the batch function returned {name} of shape {shape} "
                                         f"for a part of {n} rows")
