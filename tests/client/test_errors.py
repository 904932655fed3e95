"""Every server error status maps to its typed exception; 429/503 are retried honouring
``Retry-After``. The server here is a real HTTP server on loopback (stdlib ``http.server``) that
answers a scripted sequence of statuses, so each code can be produced on demand."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

import collider_client as cc
from collider_contract import wire

EXPECTED = {
    400: cc.BadRequestError, 401: cc.UnauthorizedError, 404: cc.ModelNotFoundError,
    413: cc.PayloadTooLargeError, 415: cc.UnsupportedMediaTypeError, 422: cc.InvalidValueError,
    429: cc.QueueFullError, 503: cc.ServiceUnavailableError, 504: cc.DeadlineExceededError,
    500: cc.ServerError,
}


class ScriptedServer:
    """Answers each request with the next (status, headers) of ``script``; then 200 + a valid
    query answer. Records every request's headers."""

    def __init__(self):
        self.script: list[tuple[int, dict]] = []
        self.requests: list[dict] = []
        self.times: list[float] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def _answer(self):
                length = int(self.headers.get("content-length") or 0)
                body = self.rfile.read(length) if length else b""
                outer.requests.append({"path": self.path, "headers": dict(self.headers),
                                       "body": body})
                outer.times.append(time.monotonic())
                if outer.script:
                    status, headers = outer.script.pop(0)
                    problem = json.dumps({"type": f"https://example.test/{status}",
                                          "title": f"title {status}", "status": status,
                                          "detail": f"detail for {status}"}).encode()
                    self.send_response(status)
                    self.send_header("content-type", "application/problem+json")
                    for k, v in headers.items():
                        self.send_header(k, v)
                    self.send_header("content-length", str(len(problem)))
                    self.end_headers()
                    self.wfile.write(problem)
                    return
                if self.path == "/v1/models":
                    payload = wire.dumps({"models": [{"name": "m", "kind": "voxel",
                                                      "domain_min": [0, 0, 0],
                                                      "domain_max": [1, 1, 1]}]})
                else:
                    request = wire.loads(body)
                    n = len(wire.decode_array(request["points"], "points"))
                    payload = wire.dumps({"distance": np.full(n, 0.5, np.float32), "model": "m"})
                self.send_response(200)
                self.send_header("content-type", wire.MSGPACK)
                self.send_header("content-length", str(len(payload)))
                self.end_headers()
                self.wfile.write(payload)

            do_GET = do_POST = _answer

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def scripted():
    server = ScriptedServer()
    yield server
    server.close()


NO_RETRY = cc.RetryPolicy(max_retries=0)


@pytest.mark.parametrize("status", sorted(EXPECTED))
def test_every_status_maps_to_its_exception(scripted, status):
    scripted.script.append((status, {}))
    with cc.Client(scripted.url, retry=NO_RETRY) as client, pytest.raises(EXPECTED[status]) as info:
        client.query("m", np.zeros((2, 3)))
    error = info.value
    assert type(error) is EXPECTED[status]
    assert error.status == status
    assert error.detail == f"detail for {status}"
    assert error.title == f"title {status}"
    assert error.type == f"https://example.test/{status}"
    assert f"detail for {status}" in str(error)


def test_error_for_status_covers_the_contract():
    for status, cls in EXPECTED.items():
        assert type(cc.error_for_status(status, "x")) is cls
    assert type(cc.error_for_status(418, "x")) is cc.ServerError


def test_retries_503_then_429_honouring_retry_after(scripted):
    scripted.script += [(503, {"Retry-After": "0.3"}), (429, {"Retry-After": "0"})]
    retry = cc.RetryPolicy(max_retries=3, backoff_s=0.01)
    with cc.Client(scripted.url, retry=retry) as client:
        result = client.query("m", np.zeros((4, 3)))
    assert result.distance.tolist() == [0.5] * 4
    assert len(scripted.requests) == 3
    assert scripted.times[1] - scripted.times[0] >= 0.3  # waited as the server asked


def test_gives_up_after_max_retries_with_the_servers_retry_after(scripted):
    scripted.script += [(429, {"Retry-After": "0"})] * 3
    with cc.Client(scripted.url, retry=cc.RetryPolicy(max_retries=2, backoff_s=0.0)) as client:
        with pytest.raises(cc.QueueFullError) as info:
            client.query("m", np.zeros((1, 3)))
    assert info.value.retry_after_s == 0.0
    assert len(scripted.requests) == 3


def test_other_errors_are_not_retried(scripted):
    scripted.script += [(422, {}), (422, {})]
    with cc.Client(scripted.url, retry=cc.RetryPolicy(max_retries=3, backoff_s=0.0)) as client:
        with pytest.raises(cc.InvalidValueError):
            client.query("m", np.zeros((1, 3)))
    assert len(scripted.requests) == 1


def test_async_client_maps_and_retries_the_same(scripted):
    scripted.script += [(503, {"Retry-After": "0"}), (404, {})]

    async def main():
        async with cc.AsyncClient(scripted.url, retry=cc.RetryPolicy(backoff_s=0.0)) as client:
            with pytest.raises(cc.ModelNotFoundError):
                await client.query("m", np.zeros((1, 3)))
            return await client.query("m", np.zeros((3, 3)))

    result = asyncio.run(main())
    assert result.distance.shape == (3,)
    assert len(scripted.requests) == 3


def test_token_is_sent_as_bearer(scripted):
    with cc.Client(scripted.url, token="s3cret") as client:
        client.list_models()
    assert scripted.requests[0]["headers"]["Authorization"] == "Bearer s3cret"


def test_refused_connection_is_a_connect_error():
    import socket

    with socket.socket() as s:  # a port nobody listens on once this socket closes
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with cc.Client(f"http://127.0.0.1:{port}",
                   retry=cc.RetryPolicy(max_retries=1, backoff_s=0.0)) as client:
        with pytest.raises(cc.ConnectError):
            client.query("m", np.zeros((1, 3)))
        assert client.ready() is False


def test_a_server_that_never_answers_is_a_request_timeout():
    """A listening server that accepts the request and says nothing: after ``timeout_s`` the
    client raises its own RequestTimeoutError (not Python's builtin TimeoutError)."""
    import socket

    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        with cc.Client(f"http://127.0.0.1:{port}", timeout_s=0.3) as client:
            started = time.monotonic()
            with pytest.raises(cc.RequestTimeoutError, match="timed out") as raised:
                client.query("m", np.zeros((1, 3)))
            assert time.monotonic() - started < 5.0
    assert isinstance(raised.value, cc.TransportError)
    assert not isinstance(raised.value, TimeoutError)


def test_retry_policy_backoff_and_retry_after():
    policy = cc.RetryPolicy(max_retries=5, backoff_s=0.1, max_backoff_s=1.0)
    assert policy.delay_s(0, None) == pytest.approx(0.1)
    assert policy.delay_s(2, None) == pytest.approx(0.4)
    assert policy.delay_s(0, 0.7) == pytest.approx(0.7)
    assert policy.delay_s(5, None) == pytest.approx(1.0)  # capped
    # a longer Retry-After is cut to max_backoff_s too, as docs/client.md says
    assert policy.delay_s(0, 14.0) == pytest.approx(1.0)
    assert cc.RetryPolicy().delay_s(0, 60.0) == pytest.approx(5.0)
    with pytest.raises(ValueError):
        cc.RetryPolicy(max_retries=-1)
