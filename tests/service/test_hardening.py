"""Regressions from probing the service from outside (issue 10): hostile array shapes, answers that
would not be finite, booleans among numbers, empty error details, stalled bodies, crashes, and the
metrics an autoscaler reads. Real servers on loopback; raw sockets where HTTP clients would hide
what the server did with the connection."""

from __future__ import annotations

import http.client
import json
import re
import socket
import time

import httpx
import msgpack
import numpy as np
import pytest

from collider_contract import wire

from .conftest import ServerThread
from .test_operations import background_post, metric
from .test_queries import decode, post, sample_points

QUERY = "/v1/models/sphere/query"


def strict_json(text: str):
    """JSON as JSON.parse reads it: NaN and Infinity are errors."""
    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


def array_map(dtype: str, shape: list, data: bytes = b"") -> dict:
    return {"dtype": dtype, "shape": shape, "data": data}


# Shapes whose product overflows int64, or huge dimensions with zero size (issue 10, point 1).
HOSTILE_SHAPES = {
    "points-2^62x4-empty": ({"points": array_map("<f4", [2**62, 4])}, "bad-points"),
    "points-2^63x0": ({"points": array_map("<f4", [2**63, 0])}, "bad-points"),
    "points-2^31x2^31x0": ({"points": array_map("<f4", [2**31, 2**31, 0])}, "bad-points"),
    "points-2^62x5-short": ({"points": array_map("<f8", [2**62, 5], b"\0" * 12)}, "bad-points"),
    "points-2^62x3-short": ({"points": array_map("<f4", [2**62, 3], b"\0" * 12)}, "bad-points"),
    "pose-2^61x8": ({"points": wire.encode_array(np.zeros((2, 3))),
                     "pose": array_map("<f8", [2**61, 8])}, "bad-pose"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_SHAPES))
def test_hostile_shapes_are_422_and_the_connection_stays_usable(server, engine, case):
    body, code = HOSTILE_SHAPES[case]
    connection = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    try:
        connection.request("POST", QUERY, msgpack.packb(body, use_bin_type=True),
                           {"Content-Type": wire.MSGPACK})
        response = connection.getresponse()
        problem = strict_json(response.read())
        assert response.status == 422, problem
        assert problem["type"] == code
        assert not re.search(r"-\d", problem["detail"]), problem["detail"]  # no negative sizes
        # The next request on the same keep-alive connection is answered.
        points = sample_points(5, 1)
        connection.request("POST", QUERY, wire.dumps({"points": points}),
                           {"Content-Type": wire.MSGPACK})
        again = connection.getresponse()
        assert again.status == 200
        got = wire.decode_array(wire.loads(again.read())["distance"], "distance")
        np.testing.assert_array_equal(got, engine["sphere"].query(points).distance)
    finally:
        connection.close()


FAR = {
    "points-1e300-json": (wire.JSON, (b'{"points": [[0, 0, 0], [1e300, 0, 0]], "fields": '
                                     b'["distance", "normal", "contact", "collides"]}')),
    "points-1e39-json": (wire.JSON, b'{"points": [[1e39, 0, 0]], "fields": ["distance"]}'),
    "pose-1e300-msgpack": (wire.MSGPACK, wire.dumps({
        "points": np.zeros((3, 3)), "fields": ["distance", "normal", "contact"],
        "pose": np.array([[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])})),
}


@pytest.mark.parametrize("case", sorted(FAR))
def test_finite_input_never_gets_a_non_finite_answer(server, case):
    media, raw = FAR[case]
    for path in (QUERY, "/v1/scene/query"):
        if path != QUERY:
            body = wire.loads(raw, media)
            pose = body.pop("pose", None)
            body["colliders"] = [{"model": "sphere"} if pose is None
                                 else {"model": "sphere", "pose": pose}]
            raw_body = wire.dumps(body, media)
        else:
            raw_body = raw
        response = httpx.post(server.url + path, content=raw_body,
                              headers={"content-type": media, "accept": wire.JSON})
        problem = strict_json(response.text)  # whatever the answer, it is valid JSON
        assert response.status_code == 422, problem
        assert problem["type"] in ("out-of-range", "bad-points", "bad-pose"), problem
        assert "row" in problem["detail"] or "pose" in problem["detail"]


def test_a_far_request_in_a_batch_fails_alone(repo, engine):
    """Coalesced with good requests, a request without a finite answer gets its 422; the others
    in the same batch get their answers (assembled in the compute thread, batch-wide)."""
    from collider_contract import ModelQuery, QueryError, as_pose
    from collider_server.service.batching import BatchPart
    from collider_server.service.query_jobs import QueryJob, answer_batch

    collider = engine["sphere"]
    fields = ("distance", "normal", "contact", "collides")
    good = [sample_points(7, 1), sample_points(5, 2).astype(np.float32)]
    far = np.array([[0.0, 0.0, 0.0], [0.0, 1e300, 0.0]])
    shifted = np.eye(4)
    shifted[:3, 3] = [0.05, 0.0, 0.0]
    jobs = [QueryJob(ModelQuery(good[0], fields, as_pose(None), 0.001)),
            QueryJob(ModelQuery(far, fields, as_pose(None), 0.001)),
            QueryJob(ModelQuery(good[1], fields, as_pose(None), 0.001)),
            QueryJob(ModelQuery(good[0], ("distance", "contact"), as_pose(shifted), 0.002))]
    answers = answer_batch(collider, "sphere", [BatchPart(j, 0, len(j.query.points)) for j in jobs])
    assert isinstance(answers[1], QueryError) and answers[1].status == 422
    assert "row 1" in answers[1].detail
    for job, answer in zip([jobs[0], jobs[2], jobs[3]], [answers[0], answers[2], answers[3]]):
        q = job.query
        want = collider.query(q.points, q.fields, q.pose, q.eps)
        assert set(answer) == set(q.fields)
        for name in q.fields:
            np.testing.assert_array_equal(answer[name], getattr(want, name))
            assert answer[name].dtype == getattr(want, name).dtype


def test_malformed_bodies_name_what_is_wrong(server):
    for raw in (b"\xc1", b"", b"\x92\x01", b"\x81\xa1a"):
        response = httpx.post(server.url + QUERY, content=raw,
                              headers={"content-type": wire.MSGPACK})
        assert response.status_code == 400
        detail = response.json()["detail"]
        reason = detail.split("body:", 1)[1].strip()
        assert len(reason) > 3, detail


def test_a_boolean_among_json_numbers_is_refused(server):
    for points in ("[[0, true, 0]]", "[[0.5, 0, false]]", "[[true, true, true]]"):
        response = httpx.post(server.url + QUERY, content=f'{{"points": {points}}}',
                              headers={"content-type": wire.JSON})
        assert response.status_code == 422, points
        assert response.json()["type"] == "bad-points"


@pytest.fixture(scope="module")
def timeout_server(repo):
    with ServerThread(models=repo, device="cpu", body_timeout_s=0.3) as server:
        yield server


def test_stalled_body_gets_408_and_the_connection_closes(timeout_server):
    with socket.create_connection(("127.0.0.1", timeout_server.port), timeout=10) as sock:
        sock.sendall(f"POST {QUERY} HTTP/1.1\r\nHost: x\r\nContent-Type: {wire.JSON}\r\n"
                     "Content-Length: 100\r\n\r\n{\"points\":".encode())
        answer = b""
        while chunk := sock.recv(65536):  # ends when the server closes the connection
            answer += chunk
    head, _, payload = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 408 Request Timeout\r\n"), answer[:300]
    assert b"connection: close" in head.lower()
    problem = strict_json(payload)
    assert problem["type"] == "body-timeout" and "body_timeout_s=0.3" in problem["detail"]
    assert metric(timeout_server.url, 'collider_requests_total{method="POST",'
                  'route="/v1/models/{name}/query",status="408"}') >= 1
    # A body that arrives in slow parts, each within the timeout, is read whole.
    points = sample_points(20, 3)
    body = wire.dumps({"points": points})
    with socket.create_connection(("127.0.0.1", timeout_server.port), timeout=10) as sock:
        sock.sendall(f"POST {QUERY} HTTP/1.1\r\nHost: x\r\nContent-Type: {wire.MSGPACK}\r\n"
                     f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode())
        for i in range(0, len(body), 200):
            sock.sendall(body[i:i + 200])
            time.sleep(0.05)
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 200"), answer[:300]


def test_an_unhandled_error_is_a_500_problem_that_closes_the_connection(repo):
    server = ServerThread(models=repo, device="cpu")

    async def boom():
        raise RuntimeError("deliberate")

    server.app.add_api_route("/boom", boom)
    with server:
        connection = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
        connection.request("GET", "/boom")
        response = connection.getresponse()
        problem = strict_json(response.read())
        assert response.status == 500 and problem["type"] == "internal-error"
        assert "deliberate" in problem["detail"]
        assert response.getheader("connection") == "close"
        connection.close()
        assert metric(server.url, 'collider_requests_total{method="GET",route="/boom",'
                      'status="500"}') == 1


@pytest.fixture(scope="module")
def waiting_server(repo):
    """Batches wait 10 s for more points: what is queued stays queued, deterministically."""
    with ServerThread(models=repo, device="cpu", max_wait_ms=10_000) as server:
        yield server


def test_metrics_show_the_queue_depth_and_request_latency(waiting_server, engine):
    url = waiting_server.url
    assert metric(url, 'collider_queue_points{model="sphere"}') == 0
    waiting = background_post(f"{url}{QUERY}", {"points": sample_points(321, 4),
                                                 "deadline_ms": 20_000})
    end = time.monotonic() + 10
    while metric(url, 'collider_queue_points{model="sphere"}') != 321:
        assert time.monotonic() < end, "the queued points never showed"
    assert metric(url, 'collider_queue_points{model="small"}') == 0
    # A request that fills a batch (65,536 points) sends the queue off at once.
    points = sample_points(65_536 - 321, 5)
    got = decode(post(f"{url}{QUERY}", {"points": points}))
    np.testing.assert_array_equal(got["distance"], engine["sphere"].query(points).distance)
    assert waiting.result(10).status_code == 200
    assert metric(url, 'collider_queue_points{model="sphere"}') == 0
    count = metric(url, 'collider_request_seconds_count{route="/v1/models/{name}/query"}')
    total = metric(url, 'collider_request_seconds_sum{route="/v1/models/{name}/query"}')
    assert count == 2 and total > 0


# -- the hot route's fast path answers exactly as the FastAPI route (issue 10, point 10) --------


def fast_path_requests() -> list[tuple[str, dict, bytes]]:
    """(path, headers, body) of good and bad query requests: every bad body of test_queries, the
    hostile shapes above, auth missing and wrong, an unknown model, JSON and msgpack answers."""
    from .test_queries import BAD_BODIES

    token = {"Authorization": "Bearer tok"}
    points = sample_points(50, 9)
    requests = [
        (QUERY, {**token, "content-type": wire.MSGPACK},
         wire.dumps({"points": points, "fields": ["distance", "normal", "contact", "collides"]})),
        (QUERY, {**token, "content-type": wire.JSON, "X-Deadline-Ms": "60000"},
         wire.dumps({"points": points, "fields": ["contact"], "eps": 0.01}, wire.JSON)),
        (QUERY, {"content-type": wire.MSGPACK}, wire.dumps({"points": points})),
        (QUERY, {"Authorization": "Bearer nope", "content-type": wire.MSGPACK},
         wire.dumps({"points": points})),
        ("/v1/models/nope/query", {**token, "content-type": wire.MSGPACK},
         wire.dumps({"points": points})),
    ]
    for media, raw, *_ in BAD_BODIES.values():
        requests.append((QUERY, {**token, "content-type": media}, raw))
    for body, _ in HOSTILE_SHAPES.values():
        requests.append((QUERY, {**token, "content-type": wire.MSGPACK},
                         msgpack.packb(body, use_bin_type=True)))
    return requests


def test_the_fast_path_answers_as_the_fastapi_route(repo):
    with ServerThread(models=repo, device="cpu", token="tok") as fast, \
            ServerThread(models=repo, device="cpu", token="tok", query_fast_path=False) as slow:
        for path, headers, body in fast_path_requests():
            a = httpx.post(fast.url + path, content=body, headers=headers)
            b = httpx.post(slow.url + path, content=body, headers=headers)
            assert (a.status_code, a.headers["content-type"]) == \
                   (b.status_code, b.headers["content-type"]), (path, headers, a.text, b.text)
            for name in ("www-authenticate", "retry-after", "connection"):
                assert a.headers.get(name) == b.headers.get(name), name
            assert a.content == b.content, (a.text[:300], b.text[:300])
        # Both counted under the route template.
        for server in (fast, slow):
            assert metric(server.url, 'collider_requests_total{method="POST",'
                          'route="/v1/models/{name}/query",status="200"}',
                          {"Authorization": "Bearer tok"}) == 2


def test_the_app_refuses_a_router_dependency_the_fast_path_would_skip(monkeypatch):
    from fastapi import Depends

    from collider_server.service import ServiceSettings, create_app
    from collider_server.service.routers import models

    async def audit():
        pass

    route = next(r for r in models.router.routes if r.path.endswith("/query"))
    monkeypatch.setattr(route, "dependencies", [*route.dependencies, Depends(audit)])
    with pytest.raises(RuntimeError, match="audit"):
        create_app(ServiceSettings())


# -- the body limit itself, and what follows a refused body (issue 21, items 3 and 13) ----------


@pytest.fixture(scope="module")
def small_body_server(repo):
    with ServerThread(models=repo, device="cpu", max_body_bytes=2048) as server:
        yield server


def padded_json(size: int) -> bytes:
    """A valid JSON query of exactly ``size`` bytes (spaces before the closing brace)."""
    body = b'{"points": [[0.1, 0, 0], [0, 0.2, 0]]'
    return body + b" " * (size - len(body) - 1) + b"}"


def raw_exchange(port: int, request: bytes) -> bytes:
    """Send ``request`` on a fresh connection; everything answered until the server closes it
    (or stops sending for 5 s)."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
        sock.sendall(request)
        answer = b""
        try:
            while chunk := sock.recv(65536):
                answer += chunk
        except TimeoutError:
            answer += b"<still open>"
    return answer


@pytest.mark.parametrize("chunked", [False, True], ids=["content-length", "chunked"])
def test_a_body_of_exactly_max_body_bytes_is_accepted_and_one_more_byte_refused(
        small_body_server, engine, chunked):
    for size, status in ((2048, 200), (2049, 413)):
        body = padded_json(size)
        assert len(body) == size
        if chunked:  # no declared length: the limit is met while reading
            framing = b"Transfer-Encoding: chunked\r\n\r\n"
            payload = b"".join(f"{len(part):x}\r\n".encode() + part + b"\r\n"
                               for part in (body[:1000], body[1000:])) + b"0\r\n\r\n"
        else:
            framing = f"Content-Length: {size}\r\n\r\n".encode()
            payload = body
        answer = raw_exchange(small_body_server.port,
                              f"POST {QUERY} HTTP/1.1\r\nHost: x\r\nContent-Type: {wire.JSON}\r\n"
                              "Connection: close\r\n".encode() + framing + payload)
        head, _, content = answer.partition(b"\r\n\r\n")
        assert head.startswith(f"HTTP/1.1 {status}".encode()), (size, answer[:300])
        if status == 200:
            got = json.loads(content)["distance"]
            want = engine["sphere"].query(np.array([[0.1, 0, 0], [0, 0.2, 0]])).distance
            np.testing.assert_allclose(got, want, rtol=1e-6)
        else:
            assert strict_json(content)["type"] == "body-too-large"


def test_a_declared_oversized_body_is_refused_and_its_connection_closed(small_body_server):
    """The 413 comes before the body is read: the connection must close, or a client that sends
    its next request instead of the refused body would have it read as that body."""
    with socket.create_connection(("127.0.0.1", small_body_server.port), timeout=5) as sock:
        sock.sendall(f"POST {QUERY} HTTP/1.1\r\nHost: x\r\nContent-Type: {wire.JSON}\r\n"
                     "Content-Length: 4096\r\n\r\n".encode())
        answer = b""
        while b"}" not in answer:
            answer += sock.recv(65536)
        head, _, problem = answer.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 413") and b"connection: close" in head.lower(), answer
        assert strict_json(problem)["type"] == "body-too-large"
        try:
            sock.sendall(b"GET /v1/models HTTP/1.1\r\nHost: x\r\n\r\n")
            rest = sock.recv(65536)
        except (ConnectionResetError, BrokenPipeError):
            rest = b""
        assert rest == b"", rest[:300]  # closed: nothing taken as a body, nothing answered


# -- null is not a value of any key; huge pose entries warn nothing (issue 21, item 5) ----------


@pytest.mark.parametrize("key", ["fields", "pose", "eps", "deadline_ms", "only_colliding"])
def test_a_null_value_is_422_naming_the_key(server, key):
    points = [[0.1, 0, 0]]
    for path, body in ((QUERY, {"points": points, key: None}),
                       ("/v1/scene/query", {"points": points, "colliders": [{"model": "sphere"}],
                                            key: None})):
        if path != QUERY and key == "pose":  # a scene's poses are per collider
            body = {"points": points, "colliders": [{"model": "sphere", "pose": None}]}
        response = httpx.post(server.url + path, content=json.dumps(body),
                              headers={"content-type": wire.JSON})
        problem = strict_json(response.text)
        assert response.status_code == 422, (path, key, problem)
        assert problem["type"] == f"bad-{key.replace('_', '-')}", problem


def test_a_pose_with_huge_entries_is_refused_without_a_numpy_warning(server, recwarn):
    import warnings

    from collider_contract import PoseError, as_pose

    for value, message in ((1e300, "pose scale is outside .* entry of 1e\\+300"),
                           (-1e200, "pose scale is outside .* entry of 1e\\+200"),
                           (2e6, "not rigid")):
        pose = np.eye(4)
        pose[0, 1] = value
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # an overflow RuntimeWarning fails the test
            with pytest.raises(PoseError, match=message):
                as_pose(pose)
        response = httpx.post(server.url + QUERY, headers={"content-type": wire.MSGPACK},
                              content=wire.dumps({"points": np.zeros((1, 3)), "pose": pose}))
        assert response.status_code == 422 and response.json()["type"] == "bad-pose"
    scaled = np.diag([1e6, 1e6, 1e6, 1.0])  # the largest scale allowed is still accepted
    assert as_pose(scaled).scale == 1e6


def test_an_array_map_with_a_key_besides_dtype_shape_and_data_is_refused_naming_it(server):
    """Issue 35, item 4: the schema's ``additionalProperties: false``, answered as the embedded
    backend would (the contract's reader refuses it)."""
    points = {**wire.encode_array(np.zeros((2, 3), np.float32)), "x": 1}
    for url, body in ((server.url + QUERY, {"points": points}),
                      (server.url + "/v1/scene/query", {"points": points, "colliders": [{"model": "sphere"}]})):
        response = httpx.post(url, content=msgpack.packb(body, use_bin_type=True),
                              headers={"content-type": wire.MSGPACK})
        assert response.status_code == 422, response.text
        assert response.json()["type"] == "bad-points"
        assert response.json()["detail"] == ("points: array map has unknown key(s) ['x']; it holds "
                                             "exactly ['dtype', 'shape', 'data']")
