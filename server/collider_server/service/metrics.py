"""Prometheus metrics of one service instance (prometheus-client, a registry per app).

The two an autoscaler and an operator read first: ``collider_queue_points{model}`` (points
waiting for a batch, read from the batcher when scraped) and ``collider_request_seconds{route}``
(end-to-end latency of each answered request, from the app receiving it to its last byte sent).
``collider_requests_in_flight`` counts requests received and not yet answered: a body still
arriving, a query waiting for its batch. ``collider_connections_open`` and
``collider_connections_closed_total{reason}`` show the connection limits at work
(:mod:`.connections`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

from .batching import BatchStats, RowBatcher
from .problems import Problem

log = logging.getLogger("collider_server.service")

SECONDS_BUCKETS = (0.0001, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5)
REQUEST_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10, 30)
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
        self.queue_points = Gauge("collider_queue_points",
                                  "points waiting in the model's queue for a batch", ["model"],
                                  registry=r)
        self.requests_in_flight = Gauge("collider_requests_in_flight",
                                        "HTTP requests received and not yet answered (a scrape "
                                        "counts itself)", registry=r)
        self.connections_open = Gauge("collider_connections_open",
                                      "HTTP connections open (the scrape's own included)",
                                      registry=r)
        self.connections_closed = Counter("collider_connections_closed",
                                          "connections closed by a limit, by reason: "
                                          "header-timeout, too-many-connections, shutting-down",
                                          ["reason"], registry=r)
        self.request_seconds = Histogram("collider_request_seconds",
                                         "end-to-end latency of answered requests, seconds",
                                         ["route"], buckets=REQUEST_BUCKETS, registry=r)

    def watch_queue(self, model: str, batcher: RowBatcher) -> None:
        """Report ``batcher``'s waiting points as ``collider_queue_points{model}`` (read at
        scrape time: no cost per request). A reload points the series at the new batcher."""
        self.queue_points.labels(model).set_function(lambda: batcher.queued_points)

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
                       self.points_per_second, self.queue_points):
            try:
                metric.remove(model)
            except KeyError:
                pass

    def render(self) -> tuple[bytes, str]:
        return generate_latest(self.registry), CONTENT_TYPE_LATEST


class RequestObserver:
    """ASGI middleware around the app: counts answered HTTP requests by method, route template
    and status, times them (``collider_request_seconds``), and answers an unhandled error with a
    500 problem (``Connection: close``) instead of a dropped connection."""

    def __init__(self, app, metrics: ServiceMetrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = time.perf_counter()
        status = [0]

        async def send_and_record(message):
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        self.metrics.requests_in_flight.inc()
        try:
            await self.app(scope, receive, send_and_record)
        except Exception as exc:
            log.exception("unhandled error on %s %s", scope["method"], scope["path"])
            if status[0]:  # the answer had begun: all that can be done is to end the connection
                raise
            problem = Problem(500, "internal-error", f"{type(exc).__name__}: {exc}",
                              {"Connection": "close"})
            await problem.response()(scope, receive, send_and_record)
        finally:
            self.metrics.requests_in_flight.dec()
            route = getattr(scope.get("route"), "path_format", None) or "unmatched"
            self.metrics.requests.labels(scope["method"], route, str(status[0] or 500)).inc()
            self.metrics.request_seconds.labels(route).observe(time.perf_counter() - started)
