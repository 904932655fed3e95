"""The point batcher alone: no server, no torch; compute is gated with events, not timing."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest

from collider_server.batching import (
    BatchContractError,
    BatcherClosed,
    BatchSettings,
    DeadlineExceeded,
    DeviceWorkers,
    PointBatcher,
    QueueFull,
)


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


def test_contract_violation_is_a_typed_error(workers):
    async def main():
        batcher = PointBatcher(lambda local, g: (np.zeros(len(local) + 1), None), BatchSettings(),
                               workers.executor("cpu"))
        with pytest.raises(BatchContractError, match="shape"):
            await batcher.submit(points(3, 0), False)
        await batcher.drain()

    run(main())


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
