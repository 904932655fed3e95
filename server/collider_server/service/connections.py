"""Connection limits uvicorn lacks: a header read timeout, a bound on open connections, and
stalled uploads closed on shutdown.

uvicorn times out an idle keep-alive connection (5 s) but not a connection that sends nothing, or
half a request line, or headers a byte at a time: each holds a file descriptor for as long as the
client likes, and a few thousand of them exhaust the process's descriptors. Here, as nginx's
``client_header_timeout`` and ``worker_connections`` do:

- **header timeout**: a connection must finish its request headers within ``header_timeout_s``
  of opening, or of the end of its previous response. Otherwise it is answered 408
  ``header-timeout`` (when part of a request came) and closed; one that sent nothing is just
  closed, as an idle keep-alive connection is. (The body has its own timeout, ``body_timeout_s``,
  in :func:`~collider_server.service.bodies.read_body`.)
- **connection bound**: beyond ``max_connections`` open connections a new one is answered 503
  ``too-many-connections`` (``Retry-After: 1``) and closed at once.
- **shutdown**: on SIGTERM a connection whose request body is still arriving (nothing of it in
  compute) is answered 503 ``shutting-down`` and closed at once, instead of holding the shutdown
  for up to ``body_timeout_s``; requests whose bodies came are answered first, as uvicorn does.

All three are counted in ``/metrics`` (``collider_connections_closed_total{reason}``, with the
problem's type as the reason; ``collider_connections_open``). Malformed requests that the HTTP
parser itself refuses (bad request line, bad chunked encoding) are answered 400
``malformed-request`` as a problem document instead of uvicorn's plain text.

:func:`uvicorn_config` is the one place a uvicorn server of the service is configured
(``collider serve`` and the test and benchmark servers of :mod:`collider_cli.launch`).
"""

from __future__ import annotations

import asyncio
import http
import logging
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from .metrics import ServiceMetrics
from .problems import Problem

log = logging.getLogger("collider_server.service")

HEADER_TIMEOUT = "header-timeout"
TOO_MANY_CONNECTIONS = "too-many-connections"
MALFORMED_REQUEST = "malformed-request"
SHUTTING_DOWN = "shutting-down"


class ConnectionGuard:
    """The limits and counts shared by every connection of one server.

    max_connections : most connections open at once; beyond it new ones are refused
    header_timeout_s : longest wait, seconds, for a request's headers (see the module's doc)
    """

    def __init__(self, max_connections: int, header_timeout_s: float, metrics: ServiceMetrics):
        self.max_connections = max_connections
        self.header_timeout_s = header_timeout_s
        self.open = 0
        self._closed = {reason: metrics.connections_closed.labels(reason)
                        for reason in (HEADER_TIMEOUT, TOO_MANY_CONNECTIONS, SHUTTING_DOWN)}
        metrics.connections_open.set_function(lambda: self.open)
        # The answers are made once: thousands of connections refused or timed out together
        # should each cost the event loop as little as possible.
        self.refusal = raw_problem(Problem(
            503, TOO_MANY_CONNECTIONS, f"the server has max_connections={max_connections} "
            "connections open; retry shortly", {"Retry-After": "1"}))
        self.shutting_down = raw_problem(Problem(
            503, SHUTTING_DOWN, "the server is shutting down; the request body had not arrived "
            "whole", {"Retry-After": "5"}))
        self.late_headers = raw_problem(Problem(
            408, HEADER_TIMEOUT, f"the request headers did not arrive within "
            f"header_timeout_s={header_timeout_s:g} s"))

    def admit(self) -> bool:
        """Count a new connection in, unless the bound is reached."""
        if self.open >= self.max_connections:
            return False
        self.open += 1
        return True

    def release(self) -> None:
        self.open -= 1

    def count(self, reason: str) -> None:
        """One connection closed by a limit (``reason``: the problem's type)."""
        self._closed[reason].inc()


def raw_problem(problem: Problem) -> bytes:
    """``problem`` as a whole HTTP/1.1 response that closes the connection (written straight to
    the socket: these answers come before, or instead of, a request the app could see)."""
    body = problem.document()
    headers = {"content-type": "application/problem+json", "content-length": str(len(body)),
               **{k.lower(): v for k, v in problem.headers.items()}, "connection": "close"}
    # The status line's reason phrase is the standard one, as uvicorn writes it for every other
    # answer (the problem's title is the body's own).
    head = f"HTTP/1.1 {problem.status} {http.HTTPStatus(problem.status).phrase}\r\n" + "".join(
        f"{name}: {value}\r\n" for name, value in headers.items())
    return head.encode("latin-1") + b"\r\n" + body


class GuardedProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with the :class:`ConnectionGuard`'s limits. ``guard`` is
    set on the subclass that :func:`protocol_class` makes for one server."""

    guard: ConnectionGuard

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._admitted = False
        self._header_timer: asyncio.TimerHandle | None = None
        self._partial = False  # part of the request whose headers the timer waits for came

    # -- the connection's life ---------------------------------------------------------------

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        if not self.guard.admit():
            self.guard.count(TOO_MANY_CONNECTIONS)
            transport.write(self.guard.refusal)
            transport.close()
            return
        self._admitted = True
        super().connection_made(transport)
        self._wait_for_headers()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self._admitted:
            return  # refused: uvicorn never knew it
        self._admitted = False
        self._stop_waiting()
        self.guard.release()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if not self._admitted:
            return
        self._partial = True
        super().data_received(data)

    # -- the header timer --------------------------------------------------------------------

    def _wait_for_headers(self) -> None:
        self._stop_waiting()
        self._partial = False
        self._header_timer = self.loop.call_later(self.guard.header_timeout_s, self._headers_late)

    def _stop_waiting(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def on_headers_complete(self) -> None:
        self._stop_waiting()
        super().on_headers_complete()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        # The next request's headers are waited for, unless one is already queued (pipelined:
        # its headers came) or the connection is closing.
        if not self.transport.is_closing() and not self.pipeline and (
                self.cycle is None or self.cycle.response_complete):
            self._wait_for_headers()

    def _headers_late(self) -> None:
        self._header_timer = None
        if self.transport.is_closing():
            return
        self.guard.count(HEADER_TIMEOUT)
        if self._partial:  # part of a request came: say why it was not answered
            self.transport.write(self.guard.late_headers)
        self.transport.close()

    # -- shutdown ------------------------------------------------------------------------------

    def shutdown(self) -> None:
        """On SIGTERM: a request whose body is still arriving has nothing in compute, so it is
        answered 503 ``shutting-down`` and closed now (its reader sees a disconnect) instead of
        holding the shutdown until its body timeout; uvicorn's own rule then covers the rest
        (idle connections close, a request in compute is answered first)."""
        cycle = self.cycle
        if cycle is not None and not cycle.response_complete and cycle.more_body:
            self.guard.count(SHUTTING_DOWN)
            if not cycle.response_started:
                self.transport.write(self.guard.shutting_down)
            self.transport.close()
            return
        super().shutdown()

    # -- the HTTP parser's own refusals --------------------------------------------------------

    def send_400_response(self, msg: str) -> None:
        self.transport.write(raw_problem(Problem(
            400, MALFORMED_REQUEST, f"the HTTP request cannot be parsed ({msg.rstrip('.')})")))
        self.transport.close()


def protocol_class(guard: ConnectionGuard) -> type[GuardedProtocol]:
    """The uvicorn protocol class of one server, bound to its ``guard``."""
    return type("GuardedProtocol", (GuardedProtocol,), {"guard": guard})


def uvicorn_config(app, host: str, port: int, **options: Any):
    """The ``uvicorn.Config`` serving ``app`` (made by :func:`~collider_server.service.create_app`,
    which holds the :class:`ConnectionGuard` in ``app.state.connections``) with its limits;
    ``options`` are further ``uvicorn.Config`` arguments (log level, graceful shutdown, ...)."""
    import uvicorn

    return uvicorn.Config(app, host=host, port=port, http=protocol_class(app.state.connections),
                          **options)
