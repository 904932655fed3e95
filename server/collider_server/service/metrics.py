"""Prometheus metrics of one service instance (prometheus-client, a registry per app)."""

from __future__ import annotations

from typing import Callable

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

from ..batching import BatchStats

SECONDS_BUCKETS = (0.0001, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5)
POINTS_BUCKETS = tuple(float(2 ** k) for k in range(4, 23, 2))


class ServiceMetrics:
    """Request counts by route and status, and per model: queue time, batch size in points,
    compute time, points computed (``rate()`` of it is points per second), models loaded."""

    def __init__(self):
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter("collider_requests", "HTTP requests answered",
                                ["method", "route", "status"], registry=r)
        self.queue_seconds = Histogram("collider_queue_seconds",
                                       "time from queueing to the start of its batch, seconds",
                                       ["model"], buckets=SECONDS_BUCKETS, registry=r)
        self.batch_points = Histogram("collider_batch_points", "points per compute call",
                                      ["model"], buckets=POINTS_BUCKETS, registry=r)
        self.compute_seconds = Histogram("collider_compute_seconds",
                                         "time of one compute call, seconds",
                                         ["model"], buckets=SECONDS_BUCKETS, registry=r)
        self.points = Counter("collider_points", "points computed", ["model"], registry=r)
        self.points_per_second = Gauge("collider_points_per_second",
                                       "compute throughput of the latest batch, points/s",
                                       ["model"], registry=r)
        self.models_loaded = Gauge("collider_models_loaded", "models loaded and serving",
                                   registry=r)

    def batch_observer(self, model: str) -> Callable[[BatchStats], None]:
        """The ``on_batch`` hook of ``model``'s batcher."""
        queue = self.queue_seconds.labels(model)
        size = self.batch_points.labels(model)
        compute = self.compute_seconds.labels(model)
        points = self.points.labels(model)
        rate = self.points_per_second.labels(model)

        def observe(stats: BatchStats) -> None:
            for wait in stats.queue_wait_s:
                queue.observe(wait)
            size.observe(stats.points)
            compute.observe(stats.compute_s)
            points.inc(stats.points)
            rate.set(stats.points / stats.compute_s)

        return observe

    def forget(self, model: str) -> None:
        """Drop an unloaded model's series."""
        for metric in (self.queue_seconds, self.batch_points, self.compute_seconds, self.points,
                       self.points_per_second):
            try:
                metric.remove(model)
            except KeyError:
                pass

    def render(self) -> tuple[bytes, str]:
        return generate_latest(self.registry), CONTENT_TYPE_LATEST


class RequestCounter:
    """ASGI middleware counting answered HTTP requests by method, route template and status."""

    def __init__(self, app, metrics: ServiceMetrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        status = [500]

        async def send_and_record(message):
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_and_record)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            self.metrics.requests.labels(scope["method"], template, str(status[0])).inc()
