"""The point batcher alone: no server, no torch; compute is gated with events, not timing."""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np
import pytest

from collider_server.service.batching import (
    BatchContractError,
    BatcherClosed,
    BatchPart,
    BatchSettings,
    BatchStats,
    DeadlineExceeded,
    DeviceWorkers,
    QueueFull,
    RowBatcher,
)


class PointBatcher(RowBatcher):
    """A :class:`RowBatcher` around a plain ``compute(local, want_gradient) -> (distance,
    normal)``, the tests' batch function: the batch's points are concatenated and computed in
    one call (with the gradient if any request wants it), and each request gets its rows. (The
    service's batch function is ``answers.answer_batch``; this one keeps the batcher's tests free
    of colliders.)"""

    def __init__(self, compute, settings: BatchSettings, executor, *,
                 clock: Callable[[], float] = time.monotonic,
                 on_batch: Callable[[BatchStats], None] | None = None):
        self._compute = compute
        super().__init__(self._batch_points, settings, executor, clock=clock, on_batch=on_batch)

    async def submit(self, local: np.ndarray, want_gradient: bool,
                     deadline: float | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Queue ``local`` and wait for its answers.

        local : (n, 3) float64, collider frame and units (already validated)
        want_gradient : whether ``normal`` is needed
        deadline : clock time (seconds) after which the caller no longer wants the answer
        Returns ``(distance (n,) float64, normal (n, 3) float64 or None)`` in the collider frame.
        Raises as :meth:`RowBatcher.submit_rows`.
        """
        answer = await self.submit_rows((local, want_gradient), len(local), deadline)
        return answer["distance"], answer.get("normal")

    def _batch_points(self, parts: Sequence[BatchPart]) -> list[dict[str, np.ndarray]]:
        if len(parts) == 1:
            part = parts[0]
            local = part.payload[0][part.start:part.stop]  # a view, no copy
        else:
            local = np.concatenate([p.payload[0][p.start:p.stop] for p in parts])
        want_gradient = any(p.payload[1] for p in parts)
        n = len(local)
        if n == 0:
            distance, normal = np.empty(0), np.empty((0, 3))  # (only handed to who wants it)
        else:
            distance, normal = self._compute(local, want_gradient)
        answers, offset = [], 0
        for part in parts:
            rows = slice(offset, offset + part.rows)
            answer = {"distance": distance[rows]}
            if part.payload[1]:
                answer["normal"] = normal[rows]
            answers.append(answer)
            offset += part.rows
        return answers


class GatedCompute:
    """distance = x + 10 y + 100 z, normal = 2 * point; records every batch's size.

    While ``gate`` is clear, a call blocks after setting ``started``, so a test can fill the
    queue while the worker is busy."""

    def __init__(self, gated: bool = False):
        self.gate = threading.Event()
        if not gated:
            self.gate.set()
        self.started = threading.Event()
        self.batches: list[int] = []

    def __call__(self, local: np.ndarray, want_gradient: bool):
        self.batches.append(len(local))
        self.started.set()
        assert self.gate.wait(10)
        distance = local @ np.array([1.0, 10.0, 100.0])
        return distance, (2.0 * local if want_gradient else None)

    async def wait_started(self):
        ok = await asyncio.get_running_loop().run_in_executor(None, self.started.wait, 10)
        assert ok
        self.started.clear()


def expected(local):
    return local @ np.array([1.0, 10.0, 100.0]), 2.0 * local


def points(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 3))


@pytest.fixture
def workers():
    w = DeviceWorkers()
    yield w
    w.shutdown()


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 20))


def test_concurrent_requests_share_one_batch_and_get_their_own_rows(workers):
    compute = GatedCompute(gated=True)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(max_wait_ms=0), workers.executor("cpu"))
        first = asyncio.create_task(batcher.submit(points(7, 0), True))
        await compute.wait_started()  # the worker is busy with the first request
        inputs = [points(10 + i, i + 1) for i in range(6)]
        tasks = [asyncio.create_task(batcher.submit(p, i % 2 == 0)) for i, p in enumerate(inputs)]
        await asyncio.sleep(0)
        assert batcher.queued_points == sum(len(p) for p in inputs)
        compute.gate.set()
        await first
        results = await asyncio.gather(*tasks)
        await batcher.drain()
        return inputs, results

    inputs, results = run(main())
    assert compute.batches == [7, sum(len(p) for p in inputs)]
    for i, (p, (distance, normal)) in enumerate(zip(inputs, results)):
        d, n = expected(p)
        np.testing.assert_array_equal(distance, d)
        if i % 2 == 0:
            np.testing.assert_array_equal(normal, n)
        else:
            assert normal is None


def test_batch_closes_when_full_without_waiting(workers):
    compute = GatedCompute()

    async def main():
        settings = BatchSettings(max_batch_points=100, max_wait_ms=60_000)
        batcher = PointBatcher(compute, settings, workers.executor("cpu"))
        results = await asyncio.gather(*(batcher.submit(points(50, i), False) for i in range(2)))
        await batcher.drain()
        return results

    results = run(main())  # a 60 s wait would time the test out
    assert compute.batches == [100]
    np.testing.assert_array_equal(results[1][0], expected(points(50, 1))[0])


def test_batch_closes_after_max_wait(workers):
    compute = GatedCompute()

    async def main():
        batcher = PointBatcher(compute, BatchSettings(max_wait_ms=20), workers.executor("cpu"))
        distance, _ = await batcher.submit(points(5, 0), False)
        await batcher.drain()
        return distance

    np.testing.assert_array_equal(run(main()), expected(points(5, 0))[0])
    assert compute.batches == [5]


def test_large_request_is_split_and_reassembled(workers):
    compute = GatedCompute()
    big = points(2500, 3)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(max_batch_points=1000), workers.executor("cpu"))
        result = await batcher.submit(big, True)
        await batcher.drain()
        return result

    distance, normal = run(main())
    assert compute.batches == [1000, 1000, 500]
    d, n = expected(big)
    np.testing.assert_array_equal(distance, d)
    np.testing.assert_array_equal(normal, n)


def test_split_request_shares_batches_with_small_ones(workers):
    compute = GatedCompute(gated=True)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(max_batch_points=1000, max_wait_ms=0),
                               workers.executor("cpu"))
        blocker = asyncio.create_task(batcher.submit(points(1, 9), False))
        await compute.wait_started()
        big = asyncio.create_task(batcher.submit(points(1500, 4), False))
        small = asyncio.create_task(batcher.submit(points(300, 5), False))
        await asyncio.sleep(0)
        compute.gate.set()
        await blocker
        return await big, await small

    (big, _), (small, _) = run(main())
    assert compute.batches == [1, 1000, 800]
    np.testing.assert_array_equal(big, expected(points(1500, 4))[0])
    np.testing.assert_array_equal(small, expected(points(300, 5))[0])


def test_queue_full_raises_at_once(workers):
    compute = GatedCompute(gated=True)

    async def main():
        settings = BatchSettings(max_queue_points=100, max_wait_ms=0)
        batcher = PointBatcher(compute, settings, workers.executor("cpu"))
        busy = asyncio.create_task(batcher.submit(points(10, 0), False))
        await compute.wait_started()
        queued = asyncio.create_task(batcher.submit(points(80, 1), False))
        await asyncio.sleep(0)
        with pytest.raises(QueueFull) as info:
            await batcher.submit(points(30, 2), False)
        assert info.value.retry_after_s >= 1 and info.value.queued_points == 80
        compute.gate.set()
        await busy
        return await queued

    distance, _ = run(main())
    np.testing.assert_array_equal(distance, expected(points(80, 1))[0])


def test_deadline_leaves_the_queue(workers):
    compute = GatedCompute(gated=True)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(max_wait_ms=0), workers.executor("cpu"))
        busy = asyncio.create_task(batcher.submit(points(10, 0), False))
        await compute.wait_started()
        loop = asyncio.get_running_loop()
        with pytest.raises(DeadlineExceeded):
            await batcher.submit(points(40, 1), False, deadline=loop.time() + 0.05)
        assert batcher.queued_points == 0 and batcher.queued_requests == 0
        other = asyncio.create_task(batcher.submit(points(5, 2), False))
        await asyncio.sleep(0)
        compute.gate.set()
        await busy
        result = await other
        await batcher.drain()
        return result

    distance, _ = run(main())
    np.testing.assert_array_equal(distance, expected(points(5, 2))[0])
    assert compute.batches == [10, 5]  # the expired request was never computed


def test_past_deadline_is_refused_with_an_injected_clock(workers):
    compute = GatedCompute()
    now = [1000.0]

    async def main():
        batcher = PointBatcher(compute, BatchSettings(), workers.executor("cpu"), clock=lambda: now[0])
        with pytest.raises(DeadlineExceeded):
            await batcher.submit(points(3, 0), False, deadline=999.0)
        await batcher.drain()

    run(main())
    assert compute.batches == []


def test_cancelled_caller_is_dropped_from_the_queue(workers):
    compute = GatedCompute(gated=True)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(max_wait_ms=0), workers.executor("cpu"))
        busy = asyncio.create_task(batcher.submit(points(10, 0), False))
        await compute.wait_started()
        gone = asyncio.create_task(batcher.submit(points(40, 1), False))
        stays = asyncio.create_task(batcher.submit(points(6, 2), False))
        await asyncio.sleep(0)
        gone.cancel()
        await asyncio.sleep(0)
        assert batcher.queued_points == 6
        compute.gate.set()
        await busy
        result = await stays
        await batcher.drain()
        return result

    distance, _ = run(main())
    assert compute.batches == [10, 6]
    np.testing.assert_array_equal(distance, expected(points(6, 2))[0])


def test_a_failing_batch_fails_only_its_own_requests(workers):
    def compute(local, want_gradient):
        if (local[:, 0] > 100).any():
            raise RuntimeError("device error")
        return local[:, 0].copy(), None

    async def main():
        batcher = PointBatcher(compute, BatchSettings(coalesce=False), workers.executor("cpu"))
        bad = np.full((4, 3), 500.0)
        good = points(4, 1)
        results = await asyncio.gather(batcher.submit(bad, False), batcher.submit(good, False),
                                       return_exceptions=True)
        await batcher.drain()
        return good, results

    good, (bad_result, good_result) = run(main())
    assert isinstance(bad_result, RuntimeError)
    np.testing.assert_array_equal(good_result[0], good[:, 0])


def test_coalescing_off_computes_each_request_alone(workers):
    compute = GatedCompute(gated=True)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(coalesce=False), workers.executor("cpu"))
        first = asyncio.create_task(batcher.submit(points(2, 0), False))
        await compute.wait_started()
        rest = [asyncio.create_task(batcher.submit(points(3, i), False)) for i in range(1, 4)]
        await asyncio.sleep(0)
        compute.gate.set()
        await asyncio.gather(first, *rest)
        await batcher.drain()

    run(main())
    assert compute.batches == [2, 3, 3, 3]


def test_drain_answers_queued_requests_and_refuses_new_ones(workers):
    compute = GatedCompute(gated=True)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(max_wait_ms=0), workers.executor("cpu"))
        tasks = [asyncio.create_task(batcher.submit(points(5, i), False)) for i in range(3)]
        await compute.wait_started()
        draining = asyncio.create_task(batcher.drain())
        await asyncio.sleep(0)
        with pytest.raises(BatcherClosed):
            await batcher.submit(points(5, 9), False)
        compute.gate.set()
        await draining
        return await asyncio.gather(*tasks)

    results = run(main())
    for i, (distance, _) in enumerate(results):
        np.testing.assert_array_equal(distance, expected(points(5, i))[0])


def test_empty_request_needs_no_batch(workers):
    compute = GatedCompute()

    async def main():
        batcher = PointBatcher(compute, BatchSettings(), workers.executor("cpu"))
        result = await batcher.submit(np.empty((0, 3)), True)
        await batcher.drain()
        return result

    distance, normal = run(main())
    assert distance.shape == (0,) and normal.shape == (0, 3) and compute.batches == []


@pytest.mark.parametrize("kwargs, message", [
    ({"max_batch_points": 0}, "max_batch_points"),
    ({"max_queue_points": -5}, "max_queue_points"),
    ({"max_wait_ms": float("nan")}, "max_wait_ms"),
    ({"max_wait_ms": -1}, "max_wait_ms"),
])
def test_settings_are_validated(kwargs, message):
    with pytest.raises(ValueError, match=message):
        BatchSettings(**kwargs)


def test_a_dead_loop_fails_its_waiting_requests_instead_of_hanging(workers):
    compute = GatedCompute(gated=True)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(), workers.executor("cpu"))
        busy = asyncio.create_task(batcher.submit(points(3, 0), False))
        await compute.wait_started()
        queued = asyncio.create_task(batcher.submit(points(3, 1), False))
        await asyncio.sleep(0)
        batcher._task.cancel()  # stands for a bug that kills the loop
        for waiting in (busy, queued):
            with pytest.raises(BatcherClosed, match="loop ended"):
                await waiting
        with pytest.raises(BatcherClosed):
            await batcher.submit(points(3, 2), False)
        compute.gate.set()
        # Shutting the dead batcher down (server stop, model unload) returns normally instead of
        # raising the loop's CancelledError into the caller.
        await batcher.drain()
        return "drained"

    assert run(main()) == "drained"


# -- the row batcher itself: exact parts, numbers and messages ------------------------------------


class Clock:
    """An injected clock (seconds): moves only when a test (or a batch function) moves it."""

    def __init__(self, now: float = 0.0):
        self.now = now

    def __call__(self) -> float:
        return self.now


class RowRecorder:
    """A batch function for RowBatcher. Request ``payload`` (an int) has rows whose answer is
    ``row = 1000 * payload + row index``; payloads in ``fail`` are answered with
    ``ValueError("bad request <payload>")``. Records every call's parts as (payload, start, stop)
    and the thread it ran in. While ``gated``, each call waits for one :meth:`release`; each call
    moves ``clock`` by the next value of ``advance`` (its compute time, seconds; 0 when none)."""

    def __init__(self, gated: bool = False, clock: Clock | None = None, advance=(), fail=()):
        self.gated = gated
        self.clock = clock
        self.advance = list(advance)
        self.fail = set(fail)
        self.calls: list[list[tuple]] = []
        self.threads: list[str] = []
        self._permits = threading.Semaphore(0)
        self._called = threading.Condition()

    def release(self, n: int = 1):
        for _ in range(n):
            self._permits.release()

    def __call__(self, parts):
        with self._called:
            self.calls.append([(p.payload, p.start, p.stop) for p in parts])
            self.threads.append(threading.current_thread().name)
            self._called.notify_all()
        if self.gated:
            assert self._permits.acquire(timeout=10)
        if self.clock is not None and self.advance:
            self.clock.now += self.advance.pop(0)
        return [ValueError(f"bad request {p.payload}") if p.payload in self.fail
                else {"row": 1000 * p.payload + np.arange(p.start, p.stop)} for p in parts]

    async def wait_calls(self, count: int):
        """Wait (off the event loop) until ``count`` calls have started."""
        def wait():
            with self._called:
                return self._called.wait_for(lambda: len(self.calls) >= count, 10)
        assert await asyncio.get_running_loop().run_in_executor(None, wait)


def rows_of(payload: int, size: int) -> np.ndarray:
    return 1000 * payload + np.arange(size)


async def settle(steps: int = 20):
    """Let every ready task run (no real time passes)."""
    for _ in range(steps):
        await asyncio.sleep(0)


def test_queue_full_reports_its_numbers_and_message(workers):
    recorder = RowRecorder(gated=True)

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_queue_points=100), workers.executor("cpu"))
        busy = asyncio.create_task(batcher.submit_rows(0, 10))
        await recorder.wait_calls(1)
        waiting = [asyncio.create_task(batcher.submit_rows(1, 80)),
                   asyncio.create_task(batcher.submit_rows(2, 20))]  # exactly fills the queue
        await settle()
        assert batcher.queued_points == 100 and batcher.queued_requests == 2
        assert batcher.in_flight_points == 10
        with pytest.raises(QueueFull) as info:
            await batcher.submit_rows(3, 1)
        recorder.release(2)
        results = await asyncio.gather(busy, *waiting)
        await batcher.drain()
        return info.value, results

    error, results = run(main())
    assert str(error) == "queue full: 100 points queued, 1 more would exceed max_queue_points=100"
    assert (error.points, error.queued_points, error.max_queue_points) == (1, 100, 100)
    assert error.retry_after_s == 1  # no batch has finished yet: no throughput to estimate from
    for payload, size, answer in zip((0, 1, 2), (10, 80, 20), results):
        np.testing.assert_array_equal(answer["row"], rows_of(payload, size))
    assert recorder.calls == [[(0, 0, 10)], [(1, 0, 80), (2, 0, 20)]]


def retry_after_after(workers, history, in_flight: int, queued: int, points: int,
                      max_queue_points: int) -> QueueFull:
    """The :class:`QueueFull` a batcher raises after batches of ``history`` ((rows, seconds) each,
    on an injected clock), with ``in_flight`` rows computing and ``queued`` waiting, for a request
    of ``points`` rows (batches of at most 1000 rows)."""
    clock = Clock()
    recorder = RowRecorder(gated=True, clock=clock, advance=[s for _, s in history])

    async def main():
        settings = BatchSettings(max_batch_points=1000, max_queue_points=max_queue_points)
        batcher = RowBatcher(recorder, settings, workers.executor("cpu"), clock=clock)
        for payload, (rows, _) in enumerate(history):
            recorder.release()
            await batcher.submit_rows(payload, rows)
        busy = asyncio.create_task(batcher.submit_rows(10_000, in_flight))
        await recorder.wait_calls(len(history) + 1)
        waiting = asyncio.create_task(batcher.submit_rows(10_001, queued))
        await settle()
        assert (batcher.in_flight_points, batcher.queued_points) == (in_flight, queued)
        with pytest.raises(QueueFull) as info:
            await batcher.submit_rows(10_002, points)
        recorder.release(1 + math.ceil(queued / 1000))
        await asyncio.gather(busy, waiting)
        await batcher.drain()
        return info.value

    error = run(main())
    assert (error.points, error.queued_points, error.max_queue_points) == (
        points, queued, max_queue_points)
    return error


@pytest.mark.parametrize("history, in_flight, queued, points, max_queue_points, expected_s", [
    # (rows, seconds) per finished batch; the throughput is the median of the batches' rates,
    # each weighted by its rows (the lower one when the weights split evenly):
    # 100 / 2 s = 50/s and 100 / 0.25 s = 400/s -> 50/s;
    # backlog 100 in flight + 100 queued + 50 asked = 250 points -> ceil(250 / 50) = 5 s
    ([(100, 2.0), (100, 0.25)], 100, 100, 50, 100, 5),
    ([(100, 2.0), (100, 0.25), (100, 0.25)], 100, 100, 50, 100, 1),  # 400/s holds 2/3: 0.6 s
    # 50/s holds 100 of 201 rows, just under half: 404/s, 0.62 s
    ([(100, 2.0), (101, 0.25)], 100, 100, 50, 101, 1),
    ([(100, 2.0), (100, 1.0), (100, 0.25)], 100, 100, 50, 100, 3),  # 50, 100, 400/s: 100/s, 2.5 s
    # only the last RATE_WINDOW (32) batches count: 15 at 50/s and 17 at 400/s -> 400/s, 0.62 s
    ([(100, 2.0)] * 32 + [(100, 0.25)] * 17, 100, 100, 50, 100, 1),
    ([(100, 0.25)], 1, 99, 2, 100, 1),  # 102 points at 400/s: 0.26 s, rounded up to 1 s
    ([(1, 2.0)], 1, 9, 2, 10, 24),  # 0.5 point/s (below 1/s): 12 points take 24 s
    ([(1, 10.0)], 1, 9, 2, 10, 60),  # 0.1 point/s: 120 s, capped at 60 s
])
def test_queue_full_retry_after_comes_from_the_measured_throughput(
        workers, history, in_flight, queued, points, max_queue_points, expected_s):
    error = retry_after_after(workers, history, in_flight, queued, points, max_queue_points)
    assert error.retry_after_s == expected_s


FAST = (1000, 1.0)  # a batch of 1000 rows in 1 s: the queue drains at 1000 points/s


@pytest.mark.parametrize("history", [
    [(1000, 30.0), FAST, FAST],  # a stall first (a starved CPU, a cold start)
    [FAST, FAST, (1000, 30.0), FAST, FAST],  # among fast ones
    [FAST, FAST, FAST, FAST, (1000, 60.0)],  # the latest one
    [(10, 0.1)] * 12 + [FAST] * 2,  # many tiny batches, mostly overhead (100 points/s)
], ids=["slow-first", "slow-between", "slow-last", "tiny-batches"])
def test_retry_after_stays_within_twice_the_true_drain_time(workers, history):
    """Issue 35, item 2: the server sent Retry-After 60 s for a queue that drained in under a
    second. Backlog 1000 in flight + 8000 queued + 1000 asked at 1000 points/s: 10 s."""
    error = retry_after_after(workers, history, 1000, 8000, 1000, 8500)
    assert 10 <= error.retry_after_s <= 20


def test_batches_take_queued_rows_in_order_and_never_exceed_max_batch_points(workers):
    recorder = RowRecorder(gated=True)
    sizes = {1: 4, 2: 7, 3: 3, 4: 9}
    stats = []

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_batch_points=10), workers.executor("cpu"),
                             on_batch=stats.append)
        busy = asyncio.create_task(batcher.submit_rows(0, 1))
        await recorder.wait_calls(1)
        tasks = [asyncio.create_task(batcher.submit_rows(p, n)) for p, n in sizes.items()]
        await settle()
        assert batcher.queued_points == 23 and batcher.queued_requests == 4
        recorder.release(4)
        await busy
        answers = await asyncio.gather(*tasks)
        assert batcher.in_flight_points == 0 and batcher.queued_points == 0
        return answers

    results = run(main())
    assert [(s.points, s.requests) for s in stats] == [(1, 1), (10, 2), (10, 3), (3, 1)]
    assert recorder.calls == [
        [(0, 0, 1)],
        [(1, 0, 4), (2, 0, 6)],
        [(2, 6, 7), (3, 0, 3), (4, 0, 6)],
        [(4, 6, 9)],
    ]
    for (payload, size), answer in zip(sizes.items(), results):
        assert list(answer) == ["row"]
        np.testing.assert_array_equal(answer["row"], rows_of(payload, size))


def test_a_request_split_into_single_rows_is_reassembled(workers):
    recorder = RowRecorder()

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_batch_points=1), workers.executor("cpu"))
        answer = await batcher.submit_rows(3, 2)
        await batcher.drain()
        return answer

    np.testing.assert_array_equal(run(main())["row"], [3000, 3001])
    assert recorder.calls == [[(3, 0, 1)], [(3, 1, 2)]]


def test_a_part_answered_with_an_exception_fails_only_its_own_request(workers):
    recorder = RowRecorder(gated=True, fail={2})

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cpu"))
        busy = asyncio.create_task(batcher.submit_rows(0, 1))
        await recorder.wait_calls(1)
        tasks = [asyncio.create_task(batcher.submit_rows(p, 3)) for p in (1, 2, 3)]
        await settle()
        recorder.release(2)
        await busy
        return await asyncio.gather(*tasks, return_exceptions=True)

    ok1, bad, ok3 = run(main())
    assert recorder.calls[1] == [(1, 0, 3), (2, 0, 3), (3, 0, 3)]  # one batch
    assert isinstance(bad, ValueError) and str(bad) == "bad request 2"
    np.testing.assert_array_equal(ok1["row"], rows_of(1, 3))
    np.testing.assert_array_equal(ok3["row"], rows_of(3, 3))


def test_a_split_request_that_fails_leaves_the_queue_and_the_batcher_keeps_serving(workers):
    recorder = RowRecorder(fail={5})

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_batch_points=10), workers.executor("cpu"))
        with pytest.raises(ValueError, match="bad request 5"):
            await batcher.submit_rows(5, 25)
        assert batcher.queued_points == 0 and batcher.queued_requests == 0
        answer = await batcher.submit_rows(6, 3)
        await batcher.drain()
        return answer

    np.testing.assert_array_equal(run(main())["row"], rows_of(6, 3))
    # The failure of rows [0, 10) reaches the caller while rows [10, 20) are computed; rows
    # [20, 25) never are. The second failed piece is discarded without harming the loop.
    assert recorder.calls == [[(5, 0, 10)], [(5, 10, 20)], [(6, 0, 3)]]


def test_a_cancelled_split_request_gives_back_its_untaken_rows(workers):
    recorder = RowRecorder(gated=True)

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_batch_points=10), workers.executor("cpu"))
        gone = asyncio.create_task(batcher.submit_rows(1, 25))
        await recorder.wait_calls(1)  # rows [0, 10) are being computed
        assert (batcher.in_flight_points, batcher.queued_points) == (10, 15)
        gone.cancel()
        await settle()
        assert batcher.queued_points == 0 and batcher.queued_requests == 0
        stays = asyncio.create_task(batcher.submit_rows(2, 3))
        recorder.release(2)
        answer = await stays
        await batcher.drain()
        return gone, answer

    gone, answer = run(main())
    assert gone.cancelled()
    np.testing.assert_array_equal(answer["row"], rows_of(2, 3))
    assert recorder.calls == [[(1, 0, 10)], [(2, 0, 3)]]


def test_a_cancelled_request_in_flight_leaves_the_queue_counts_alone(workers):
    recorder = RowRecorder(gated=True)

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cpu"))
        gone = asyncio.create_task(batcher.submit_rows(1, 5))
        await recorder.wait_calls(1)
        stays = asyncio.create_task(batcher.submit_rows(2, 4))
        await settle()
        gone.cancel()
        await settle()
        assert (batcher.in_flight_points, batcher.queued_points) == (5, 4)
        recorder.release(2)
        answer = await stays
        await batcher.drain()
        return answer

    np.testing.assert_array_equal(run(main())["row"], rows_of(2, 4))
    assert recorder.calls == [[(1, 0, 5)], [(2, 0, 4)]]


def test_deadline_exceeded_says_how_much_was_computed_and_the_rows_are_never_computed(workers):
    recorder = RowRecorder(gated=True)

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cpu"))
        busy = asyncio.create_task(batcher.submit_rows(0, 10))
        await recorder.wait_calls(1)
        deadline = time.monotonic() + 0.02
        with pytest.raises(DeadlineExceeded) as info:
            await batcher.submit_rows(1, 40, deadline=deadline)
        assert batcher.queued_points == 0 and batcher.queued_requests == 0
        recorder.release()
        await busy
        await batcher.drain()
        return info.value

    assert str(run(main())) == "the deadline passed with 0 of 40 points computed"
    assert recorder.calls == [[(0, 0, 10)]]


def test_a_deadline_at_or_before_now_is_refused_before_queueing(workers):
    clock = Clock(5.0)
    recorder = RowRecorder()

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cpu"), clock=clock)
        for deadline in (5.0, 4.0):
            with pytest.raises(DeadlineExceeded) as info:
                await batcher.submit_rows(1, 3, deadline=deadline)
            assert str(info.value) == "the deadline passed before the request was queued"
            assert batcher.queued_points == 0
        answer = await batcher.submit_rows(2, 3, deadline=5.5)  # still ahead: answered
        await batcher.drain()
        return answer

    np.testing.assert_array_equal(run(main())["row"], rows_of(2, 3))
    assert recorder.calls == [[(2, 0, 3)]]


def test_batch_stats_report_points_requests_queue_waits_and_compute_time(workers):
    clock = Clock()
    recorder = RowRecorder(gated=True, clock=clock, advance=[2.0, 0.5])
    stats = []

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cpu"), clock=clock,
                             on_batch=stats.append)
        busy = asyncio.create_task(batcher.submit_rows(0, 3))  # queued at 0 s, starts at 0 s
        await recorder.wait_calls(1)
        clock.now = 1.0
        first = asyncio.create_task(batcher.submit_rows(1, 4))  # queued at 1 s
        await settle()
        clock.now = 3.0
        second = asyncio.create_task(batcher.submit_rows(2, 5))  # queued at 3 s
        await settle()
        clock.now = 5.0
        recorder.release(2)  # the first batch ends at 7 s, the second starts then, ends at 7.5 s
        await asyncio.gather(busy, first, second)
        await batcher.drain()

    run(main())
    assert stats == [
        BatchStats(points=3, requests=1, queue_wait_s=(0.0,), compute_s=7.0),
        BatchStats(points=9, requests=2, queue_wait_s=(6.0, 4.0), compute_s=0.5),
    ]


def test_a_failing_on_batch_hook_does_not_stop_the_batcher(workers, caplog):
    recorder = RowRecorder()
    seen = []

    def hook(stats):
        seen.append(stats.points)
        raise RuntimeError("metrics are down")

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cpu"), on_batch=hook)
        answers = [await batcher.submit_rows(p, p) for p in (1, 2)]
        await batcher.drain()
        return answers

    answers = run(main())
    assert seen == [1, 2]
    assert [r.getMessage() for r in caplog.records] == ["on_batch hook failed"] * 2
    assert "metrics are down" in caplog.text  # with the hook's traceback
    for payload, answer in zip((1, 2), answers):
        np.testing.assert_array_equal(answer["row"], rows_of(payload, payload))


def test_the_batch_function_runs_in_the_devices_worker_thread(workers):
    recorder = RowRecorder()

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cuda:1"))
        await batcher.submit_rows(1, 2)
        await batcher.drain()

    run(main())
    assert recorder.threads[0].startswith("collider-cuda:1")


def test_an_empty_request_is_answered_on_the_event_loop_without_queueing(workers):
    recorder = RowRecorder(fail={9})

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_queue_points=1), workers.executor("cpu"))
        answer = await batcher.submit_rows(4, 0)
        assert batcher.queued_points == 0 and batcher.in_flight_points == 0
        with pytest.raises(ValueError, match="bad request 9"):
            await batcher.submit_rows(9, 0)
        await batcher.drain()
        return answer

    answer = run(main())
    assert answer["row"].shape == (0,)
    assert recorder.calls == [[(4, 0, 0)], [(9, 0, 0)]]
    assert recorder.threads == [threading.current_thread().name] * 2


@pytest.mark.parametrize("rows, answers, message", [
    (3, [], "the batch function returned 0 answers for 1 parts"),
    (3, {"row": np.zeros(3)}, "the batch function returned dict answers for 1 parts"),
    (3, [{"row": np.zeros(4)}], ("the batch function returned row of shape (4,) for a part of 3 "
                                "rows")),
    (3, [{"row": [0, 0, 0]}], "the batch function returned row of shape list for a part of 3 rows"),
    (0, [{"row": np.zeros(0)}, {}], "the batch function returned 2 answers for 1 parts"),
    (0, [{"row": np.zeros(1)}], ("the batch function returned row of shape (1,) for a part of 0 "
                                "rows")),
])
def test_batch_contract_violations_are_typed_errors_saying_what_was_wrong(workers, rows, answers,
                                                                          message):
    def batch(parts):  # request 1 gets the wrong answers, the others the right ones
        if parts[0].payload == 1:
            return answers
        return tuple({"row": np.full(p.rows, p.payload)} for p in parts)  # a tuple is fine

    async def main():
        batcher = RowBatcher(batch, BatchSettings(), workers.executor("cpu"))
        with pytest.raises(BatchContractError) as info:
            await batcher.submit_rows(1, rows)
        after = await batcher.submit_rows(2, 2)
        await batcher.drain()
        return info.value, after

    error, after = run(main())
    assert str(error) == message
    np.testing.assert_array_equal(after["row"], [2, 2])


def test_a_batch_waits_max_wait_ms_from_its_oldest_request_on_the_batchers_clock(workers):
    clock = Clock()
    recorder = RowRecorder()

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_wait_ms=5), workers.executor("cpu"),
                             clock=clock)
        first = asyncio.create_task(batcher.submit_rows(1, 3))  # queued at 0 s
        await settle()
        clock.now = 0.004
        second = asyncio.create_task(batcher.submit_rows(2, 4))  # queued at 0.004 s
        clock.now = 0.004999
        # However long the loop waits in real time, the batch is 1 us short of its 5 ms on the
        # batcher's clock: nothing may start. (The sleep only gives a wrong loop time to start.)
        await asyncio.sleep(0.02)
        assert recorder.calls == [] and batcher.queued_points == 7
        clock.now = 0.005  # 5 ms after the oldest request (only 1 ms after the newest)
        answers = await asyncio.gather(first, second)
        await batcher.drain()
        return answers

    answers = run(main())
    assert recorder.calls == [[(1, 0, 3), (2, 0, 4)]]
    np.testing.assert_array_equal(answers[1]["row"], rows_of(2, 4))


def test_a_request_that_queued_while_the_worker_was_busy_has_already_waited(workers):
    """max_wait_ms counts from the oldest request's queueing, not from when the loop is free to
    look at it (issue 21, item 12): a request that waited its max_wait_ms behind a busy worker
    goes as soon as the worker is free, without a second wait."""
    clock = Clock()
    recorder = RowRecorder(gated=True)

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_wait_ms=5), workers.executor("cpu"),
                             clock=clock)
        first = asyncio.create_task(batcher.submit_rows(1, 3))  # queued at 0 s
        await settle()
        clock.now = 0.005
        await recorder.wait_calls(1)  # the worker is busy with the first batch
        clock.now = 0.006
        second = asyncio.create_task(batcher.submit_rows(2, 4))  # queued at 6 ms, while busy
        await settle()
        clock.now = 0.012  # it has waited 6 ms > 5 ms; the clock stands still from here on
        recorder.release(2)
        await first
        # A batch that waited for more points from now would wait forever on this clock.
        answer = await asyncio.wait_for(second, 5)
        await batcher.drain()
        return answer

    answer = run(main())
    assert recorder.calls == [[(1, 0, 3)], [(2, 0, 4)]]
    np.testing.assert_array_equal(answer["row"], rows_of(2, 4))


def test_a_request_cancelled_while_its_batch_waits_is_never_computed(workers):
    recorder = RowRecorder()
    stats = []

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_wait_ms=60_000), workers.executor("cpu"),
                             clock=Clock(), on_batch=stats.append)
        gone = asyncio.create_task(batcher.submit_rows(1, 3))
        await settle()
        gone.cancel()
        await settle()
        assert batcher.queued_points == 0
        await batcher.drain()  # wakes the waiting loop, which finds nothing to compute

    run(main())
    assert recorder.calls == [] and stats == []


def test_drain_dispatches_a_waiting_batch_at_once(workers):
    recorder = RowRecorder()

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(max_wait_ms=60_000), workers.executor("cpu"),
                             clock=Clock())  # the batch would wait a minute on a frozen clock
        waiting = asyncio.create_task(batcher.submit_rows(1, 3))
        await settle()
        assert recorder.calls == []
        await batcher.drain()
        assert batcher.closed
        return await waiting

    np.testing.assert_array_equal(run(main())["row"], rows_of(1, 3))
    assert recorder.calls == [[(1, 0, 3)]]


def test_a_closed_batcher_refuses_requests_with_a_message(workers):
    recorder = RowRecorder()

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cpu"))
        assert batcher.closed is False
        batcher.close()
        assert batcher.closed
        with pytest.raises(BatcherClosed) as info:
            await batcher.submit_rows(1, 3)
        await batcher.drain()
        return info.value

    assert str(run(main())) == "the model is shutting down or being unloaded"
    assert recorder.calls == []


def test_a_dead_loop_says_so_to_every_waiting_request_and_empties_the_queue(workers, caplog):
    recorder = RowRecorder(gated=True)

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cpu"))
        busy = asyncio.create_task(batcher.submit_rows(1, 3))
        await recorder.wait_calls(1)
        queued = [asyncio.create_task(batcher.submit_rows(p, 2)) for p in (2, 3)]
        await settle()
        batcher._task.cancel()  # stands for a bug that kills the loop
        results = await asyncio.gather(busy, *queued, return_exceptions=True)
        state = (batcher.closed, batcher.queued_points, batcher.queued_requests)
        recorder.release()
        await batcher.drain()
        return results, state

    results, state = run(main())
    assert [type(r) for r in results] == [BatcherClosed] * 3
    assert [str(r) for r in results] == ["the batching loop ended (cancelled)"] * 3
    assert state == (True, 0, 0)
    assert [r.getMessage() for r in caplog.records if r.levelname == "ERROR"] == [
        "batching loop ended: cancelled"]
    assert recorder.calls == [[(1, 0, 3)]]


def test_device_workers_shutdown_waits_for_the_running_batch():
    workers = DeviceWorkers()
    started, release, finished = threading.Event(), threading.Event(), []

    def batch():
        started.set()
        assert release.wait(10)
        time.sleep(0.05)  # the rest of the batch's work, still running when shutdown is called
        finished.append("batch")

    workers.executor("cpu").submit(batch)
    assert started.wait(10)
    release.set()
    workers.shutdown()
    assert finished == ["batch"]
    # A device used after shutdown gets a fresh worker.
    assert workers.executor("cpu").submit(lambda: 42).result(10) == 42
    workers.shutdown()


def test_device_workers_run_one_batch_at_a_time_per_device():
    workers = DeviceWorkers()
    second_started = threading.Event()
    try:
        executor = workers.executor("cpu")
        # The first batch waits a little for the second to start: it never can, on one thread.
        first = executor.submit(second_started.wait, 0.1)
        second = executor.submit(second_started.set)
        assert first.result(10) is False
        second.result(10)
    finally:
        workers.shutdown()


def test_device_workers_one_thread_per_device_each_initialised():
    initialised = []
    workers = DeviceWorkers(initializer=lambda: initialised.append(
        threading.current_thread().name))
    try:
        cpu, gpu = workers.executor("cpu"), workers.executor("cuda:0")
        assert workers.executor("cpu") is cpu and gpu is not cpu
        names = {cpu.submit(lambda: threading.current_thread().name).result(10) for _ in range(3)}
        gpu_name = gpu.submit(lambda: threading.current_thread().name).result(10)
    finally:
        workers.shutdown()
    assert len(names) == 1
    cpu_name = names.pop()
    assert cpu_name.startswith("collider-cpu") and gpu_name.startswith("collider-cuda:0")
    assert sorted(initialised) == sorted([cpu_name, gpu_name])  # once per thread


def test_batch_part_rows():
    assert BatchPart("payload", 3, 7).rows == 4 and BatchPart(None, 0, 0).rows == 0


@pytest.mark.parametrize("kwargs, message", [
    ({"max_batch_points": True}, "max_batch_points must be a positive integer, got True"),
    ({"max_batch_points": 1.5}, "max_batch_points must be a positive integer, got 1.5"),
    ({"max_queue_points": 0}, "max_queue_points must be a positive integer, got 0"),
    ({"max_wait_ms": "5"}, "max_wait_ms must be a finite number >= 0, got '5'"),
    ({"max_wait_ms": float("inf")}, "max_wait_ms must be a finite number >= 0, got inf"),
    ({"max_wait_ms": -0.5}, "max_wait_ms must be a finite number >= 0, got -0.5"),
])
def test_settings_refusals_name_the_setting_and_value(kwargs, message):
    with pytest.raises(ValueError) as info:
        BatchSettings(**kwargs)
    assert str(info.value) == message


def test_settings_accept_their_smallest_values():
    settings = BatchSettings(max_batch_points=1, max_queue_points=1, max_wait_ms=0)
    assert (settings.max_batch_points, settings.max_queue_points, settings.max_wait_ms) == (1, 1, 0)
    assert BatchSettings(max_wait_ms=2.5).max_wait_ms == 2.5


def test_point_batcher_asks_for_normals_only_when_a_request_wants_them(workers):
    calls = []

    def compute(local, want_gradient):
        calls.append((len(local), want_gradient))
        return local[:, 0].copy(), (2.0 * local if want_gradient else None)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(max_batch_points=5), workers.executor("cpu"))
        plain = await batcher.submit(points(5, 1), False)
        empty = await batcher.submit(np.empty((0, 3)), False)
        mixed = await asyncio.gather(batcher.submit(points(2, 2), False),
                                     batcher.submit(points(3, 3), True))
        await batcher.drain()
        return plain, empty, mixed

    plain, empty, (no_normal, with_normal) = run(main())
    assert calls == [(5, False), (5, True)]  # the empty request computes nothing
    assert plain[1] is None and no_normal[1] is None
    assert empty[0].shape == (0,) and empty[1] is None
    np.testing.assert_array_equal(no_normal[0], points(2, 2)[:, 0])
    np.testing.assert_array_equal(with_normal[0], points(3, 3)[:, 0])
    np.testing.assert_array_equal(with_normal[1], 2.0 * points(3, 3))


def test_a_lone_request_is_computed_on_the_callers_array_without_a_copy(workers):
    seen = []

    def compute(local, want_gradient):
        seen.append(local)
        return local[:, 0].copy(), None

    local = points(4, 0)

    async def main():
        batcher = PointBatcher(compute, BatchSettings(), workers.executor("cpu"))
        await batcher.submit(local, False)
        await batcher.drain()

    run(main())
    assert np.shares_memory(seen[0], local)


def test_a_wrong_answer_after_a_failed_part_still_fails_the_whole_batch(workers):
    gate = threading.Event()

    def batch(parts):
        if parts[0].payload == 0:  # the first request holds the worker while the others queue
            assert gate.wait(10)
            return [{"row": np.zeros(p.rows)} for p in parts]
        return [ValueError("bad request"), {"row": np.zeros(parts[1].rows + 1)}]

    async def main():
        batcher = RowBatcher(batch, BatchSettings(), workers.executor("cpu"))
        busy = asyncio.create_task(batcher.submit_rows(0, 1))
        await settle()
        tasks = [asyncio.create_task(batcher.submit_rows(p, 2)) for p in (1, 2)]
        await settle()
        gate.set()
        await busy
        results = await asyncio.gather(*tasks, return_exceptions=True)
        await batcher.drain()
        return results

    for error in run(main()):
        assert isinstance(error, BatchContractError)
        assert str(error) == "the batch function returned row of shape (3,) for a part of 2 rows"


def test_a_waiting_batch_goes_as_soon_as_it_is_exactly_full(workers):
    recorder = RowRecorder()

    async def main():
        settings = BatchSettings(max_batch_points=100, max_wait_ms=60_000)
        batcher = RowBatcher(recorder, settings, workers.executor("cpu"), clock=Clock())
        first = asyncio.create_task(batcher.submit_rows(1, 50))
        await settle()  # the loop now waits (a minute, on a frozen clock) for more points
        assert recorder.calls == []
        second = asyncio.create_task(batcher.submit_rows(2, 50))  # 100 points: the batch is full
        answers = await asyncio.gather(first, second)
        await batcher.drain()
        return answers

    answers = run(main())  # waiting out the minute would time the test out
    assert recorder.calls == [[(1, 0, 50), (2, 0, 50)]]
    np.testing.assert_array_equal(answers[1]["row"], rows_of(2, 50))


class TickingClock(Clock):
    """A clock that moves ``tick`` seconds every time it is read: time passes while a request is
    being queued."""

    def __init__(self, tick: float):
        super().__init__(0.0)
        self.tick = tick

    def __call__(self) -> float:
        now = self.now
        self.now += self.tick
        return now


def test_time_spent_queueing_counts_against_the_deadline(workers):
    recorder = RowRecorder()

    async def main():
        batcher = RowBatcher(recorder, BatchSettings(), workers.executor("cpu"),
                             clock=TickingClock(0.5))
        # Still ahead when the request is queued (at 0 s), already behind once it is (0.5 s): it
        # expires at once, however fast the batch would have answered it.
        with pytest.raises(DeadlineExceeded) as info:
            await batcher.submit_rows(1, 3, deadline=0.25)
        assert batcher.queued_points == 0
        await batcher.drain()
        return info.value

    assert str(run(main())) == "the deadline passed with 0 of 3 points computed"


def test_point_batcher_reports_on_the_injected_clock_from_the_devices_thread(workers, caplog):
    clock = Clock(10.0)
    stats, threads = [], []

    def compute(local, want_gradient):
        threads.append(threading.current_thread().name)
        clock.now += 0.25
        return local[:, 0].copy(), None

    async def main():
        batcher = PointBatcher(compute, BatchSettings(), workers.executor("cpu"), clock=clock,
                               on_batch=stats.append)
        with pytest.raises(DeadlineExceeded):  # the deadline is on the injected clock
            await batcher.submit(points(2, 0), False, deadline=9.5)
        distance, _ = await batcher.submit(points(4, 1), False, deadline=11.0)
        await batcher.drain()
        return distance

    np.testing.assert_array_equal(run(main()), points(4, 1)[:, 0])
    assert stats == [BatchStats(points=4, requests=1, queue_wait_s=(0.0,), compute_s=0.25)]
    assert len(threads) == 1 and threads[0].startswith("collider-cpu")
    assert "batching loop ended" not in caplog.text  # a normal drain is no error
