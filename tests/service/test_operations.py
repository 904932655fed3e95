"""The service under load and change, against real servers: coalescing and splitting, 429 when
the queue is full, 504 at the deadline, disconnected callers leaving the queue, auth, admin
load/unload while others query, metrics, and a graceful shutdown on SIGTERM."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest
from tests.conftest import run_collider

from collider_contract import wire

from .conftest import ADMIN_TOKEN, ServerThread, make_repo
from .test_queries import decode, post, sample_points


def metric(url: str, name: str, headers=None) -> float:
    text = httpx.get(f"{url}/metrics", headers=headers).text
    found = re.search(rf"^{re.escape(name)} ([0-9.e+-]+)$", text, re.MULTILINE)
    return float(found.group(1)) if found else 0.0


def wait_until(condition, what: str, timeout_s: float = 30.0) -> None:
    """Poll ``condition`` until it holds; fail naming ``what`` after ``timeout_s`` (a bound on a
    hung server, not a guess at how fast this machine is)."""
    end = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < end, f"timed out waiting until {what}"
        time.sleep(0.01)


def wait_for_a_pending_request(url: str) -> None:
    """Until the server holds one request besides the scrape asking (``in_flight`` counts it)."""
    wait_until(lambda: metric(url, "collider_requests_in_flight") >= 2,
               "the server has received the request")


def test_concurrent_callers_are_coalesced_and_each_gets_its_own_answers(repo, engine):
    with ServerThread(models=repo, device="cpu", max_wait_ms=50) as server:
        inputs = [sample_points(100 + i, 100 + i) for i in range(24)]
        barrier = threading.Barrier(len(inputs))

        def call(i):
            barrier.wait()
            return decode(post(f"{server.url}/v1/models/sphere/query",
                               {"points": inputs[i], "fields": ["distance", "normal"]}))

        with ThreadPoolExecutor(len(inputs)) as pool:
            results = list(pool.map(call, range(len(inputs))))
        for points, got in zip(inputs, results):
            want = engine["sphere"].query(points, ["distance", "normal"])
            np.testing.assert_array_equal(got["distance"], want.distance)
            np.testing.assert_array_equal(got["normal"], want.normal)
        batches = metric(server.url, 'collider_batch_points_count{model="sphere"}')
        points = metric(server.url, 'collider_batch_points_sum{model="sphere"}')
        assert points == sum(len(p) for p in inputs) + 0  # every point computed exactly once
        assert batches < len(inputs) / 2, f"{batches} batches for {len(inputs)} requests"


def test_coalesced_requests_that_differ_only_in_eps_get_their_own_contacts(repo, engine):
    """Same points, pose and fields, different eps, in one batch (issue 21, item 11): each gets
    the contacts and collisions of its own eps, not those of the first request of its group."""
    fields = ["distance", "contact", "collides"]
    points = sample_points(400, 21)
    eps_values = [0.001, 0.01, 0.03, 0.06]
    # A batch waits up to 2 s for more points: the four concurrent requests share one.
    with ServerThread(models=repo, device="cpu", max_wait_ms=2000) as server:
        barrier = threading.Barrier(len(eps_values))

        def call(eps):
            barrier.wait()
            return decode(post(f"{server.url}/v1/models/sphere/query",
                               {"points": points, "fields": fields, "eps": eps}))

        with ThreadPoolExecutor(len(eps_values)) as pool:
            results = list(pool.map(call, eps_values))
        assert metric(server.url, 'collider_batch_points_count{model="sphere"}') == 1
    counts = []
    for eps, got in zip(eps_values, results):
        want = engine["sphere"].query(points, fields, eps=eps)
        np.testing.assert_array_equal(got["contact"], want.contact)
        np.testing.assert_array_equal(got["collides"], want.collides)
        counts.append(int(got["collides"].sum()))
    assert counts == sorted(counts) and len(set(counts)) == len(counts)  # the eps mattered


def test_large_request_is_split_across_batches(repo, engine):
    with ServerThread(models=repo, device="cpu", max_batch_points=256) as server:
        points = sample_points(2000, 7)
        got = decode(post(f"{server.url}/v1/models/sphere/query",
                          {"points": points, "fields": ["distance", "contact"]}))
        want = engine["sphere"].query(points, ["distance", "contact"])
        np.testing.assert_array_equal(got["distance"], want.distance)
        np.testing.assert_array_equal(got["contact"], want.contact)
        assert metric(server.url, 'collider_batch_points_count{model="sphere"}') == 8


@pytest.fixture(scope="module")
def slow_server(repo):
    """A batch waits 10 s for more points and the queue holds 1,000 points: a request of 800
    sits in the queue, deterministically, until its deadline or its client goes."""
    with ServerThread(models=repo, device="cpu", max_wait_ms=10_000, max_queue_points=1000,
                      max_request_points=1000) as server:
        yield server


def background_post(url: str, body: dict, timeout: float = 30):
    pool = ThreadPoolExecutor(1)
    future = pool.submit(lambda: httpx.post(url, content=wire.dumps(body),
                                            headers={"content-type": wire.MSGPACK}, timeout=timeout))
    pool.shutdown(wait=False)
    return future


def wait_for_queue(url: str, model: str, points: int) -> None:
    """Return once the queue gauge of ``model`` reads ``points`` (an event the server reports,
    not a guess at how long it takes); fails after 30 s."""
    end = time.monotonic() + 30
    while metric(url, f'collider_queue_points{{model="{model}"}}') != points:
        assert time.monotonic() < end, f"the queue of {model} never held {points} points"


def test_queue_full_answers_429_at_once_and_deadlines_504(slow_server):
    url = f"{slow_server.url}/v1/models/sphere/query"
    first = background_post(url, {"points": sample_points(800, 1), "deadline_ms": 3000})
    wait_for_queue(slow_server.url, "sphere", 800)
    full = post(url, {"points": sample_points(800, 2), "deadline_ms": 1000})
    # Refused at once: answered while the first request still holds the queue (not after
    # waiting for room), whatever the speed of the machine.
    assert not first.done()
    assert full.status_code == 429 and full.json()["type"] == "queue-full"
    assert int(full.headers["retry-after"]) >= 1
    assert "max_queue_points=1000" in full.json()["detail"]
    timed_out = first.result(10)
    assert timed_out.status_code == 504 and timed_out.json()["type"] == "deadline-exceeded"
    # The expired request left the queue: a new one fits again (and expires too).
    header = post(url, {"points": sample_points(900, 3)}, headers={"X-Deadline-Ms": "200"})
    assert header.status_code == 504


def test_disconnected_client_leaves_the_queue(slow_server):
    url = f"{slow_server.url}/v1/models/small/query"
    with pytest.raises(httpx.ReadTimeout):
        httpx.post(url, content=wire.dumps({"points": sample_points(900, 4)}),
                   headers={"content-type": wire.MSGPACK}, timeout=0.5)
    wait_for_queue(slow_server.url, "small", 0)  # the server saw the disconnect
    # Were the 900 points still queued, 900 more would be refused with 429.
    again = post(url, {"points": sample_points(900, 5), "deadline_ms": 300})
    assert again.status_code == 504, again.text


def test_auth_on(repo, engine):
    with ServerThread(models=repo, device="cpu", token="s3cret", admin_token=ADMIN_TOKEN) as server:
        url = f"{server.url}/v1/models/sphere/query"
        body = {"points": sample_points(10, 8)}
        missing = post(url, body)
        assert missing.status_code == 401 and missing.headers["www-authenticate"].startswith("Bearer")
        assert missing.headers["content-type"] == "application/problem+json"
        wrong = post(url, body, headers={"Authorization": "Bearer nope"})
        assert wrong.status_code == 401 and "not valid" in wrong.json()["detail"]
        ok = decode(post(url, body, headers={"Authorization": "Bearer s3cret"}))
        np.testing.assert_array_equal(ok["distance"], engine["sphere"].query(body["points"]).distance)
        for path in ("/v1/models", "/v1/models/sphere", "/metrics"):
            assert httpx.get(server.url + path).status_code == 401
            assert httpx.get(server.url + path, headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert post(f"{server.url}/v1/scene/query", {**body, "colliders": [{"model": "sphere"}]}).status_code == 401
        for path in ("/livez", "/readyz"):
            assert httpx.get(server.url + path).status_code == 200
        # Admin routes take the admin token, not the service token.
        user = httpx.delete(f"{server.url}/v1/admin/models/small", headers={"Authorization": "Bearer s3cret"})
        assert user.status_code == 401


def test_auth_off_by_default_and_admin_disabled(server):
    assert httpx.get(f"{server.url}/v1/models").status_code == 200
    response = httpx.delete(f"{server.url}/v1/admin/models/sphere",
                            headers={"Authorization": f"Bearer {ADMIN_TOKEN}"})
    assert response.status_code == 403 and "COLLIDER_ADMIN_TOKEN" in response.json()["detail"]
    assert httpx.get(f"{server.url}/v1/models/sphere").status_code == 200


def test_admin_load_and_unload_while_others_query(tmp_path, model_files, engine):
    repo = make_repo(tmp_path / "models", model_files, names=["sphere"])
    admin = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    with ServerThread(models=repo, device="cpu", admin_token=ADMIN_TOKEN) as server:
        stop = threading.Event()
        statuses: list[int] = []
        wrong: list[int] = []  # an assert in this thread would only be a warning: collect here
        points = sample_points(500, 9)
        want = engine["sphere"].query(points).distance

        def keep_querying():
            with httpx.Client(timeout=30) as client:
                while not stop.is_set():
                    r = client.post(f"{server.url}/v1/models/sphere/query",
                                    content=wire.dumps({"points": points}),
                                    headers={"content-type": wire.MSGPACK})
                    statuses.append(r.status_code)
                    if r.status_code != 200 or not np.array_equal(decode(r)["distance"], want):
                        wrong.append(len(statuses))

        thread = threading.Thread(target=keep_querying)
        thread.start()
        try:
            assert post(f"{server.url}/v1/models/late/query", {"points": points}).status_code == 404
            shutil.copy(model_files["small"], repo / "late.safetensors")
            loaded = httpx.put(f"{server.url}/v1/admin/models/late", headers=admin, timeout=60)
            assert loaded.status_code == 200 and loaded.json()["info"]["name"] == "late"
            got = decode(post(f"{server.url}/v1/models/late/query", {"points": points}))
            np.testing.assert_array_equal(got["distance"], engine["small"].query(points).distance)
            assert metric(server.url, "collider_models_loaded") == 2
            reloaded = httpx.put(f"{server.url}/v1/admin/models/sphere", headers=admin, timeout=60)
            assert reloaded.status_code == 200
            assert httpx.delete(f"{server.url}/v1/admin/models/late", headers=admin).status_code == 200
            assert post(f"{server.url}/v1/models/late/query", {"points": points}).status_code == 404
            assert httpx.delete(f"{server.url}/v1/admin/models/late", headers=admin).status_code == 404
            missing = httpx.put(f"{server.url}/v1/admin/models/ghost", headers=admin)
            assert missing.status_code == 404 and "ghost" in missing.json()["detail"]
            (repo / "broken.safetensors").write_bytes(b"not a model")
            broken = httpx.put(f"{server.url}/v1/admin/models/broken", headers=admin)
            assert broken.status_code == 422 and broken.json()["type"] == "bad-model-file"
            answered = len(statuses)  # and the queries go on after every admin change
            wait_until(lambda: len(statuses) >= answered + 3, "three more queries were answered")
        finally:
            stop.set()
            thread.join(30)
        assert statuses and set(statuses) == {200}, set(statuses)
        assert not wrong, f"answers {wrong} of {len(statuses)} differ from the engine's"


def test_metrics_count_requests_by_status(server):
    post(f"{server.url}/v1/models/sphere/query", {"points": sample_points(10, 1)})
    httpx.post(f"{server.url}/v1/models/sphere/query", content=b"x", headers={"content-type": "text/csv"})
    text = httpx.get(f"{server.url}/metrics").text
    assert re.search(r'collider_requests_total\{method="POST",route="/v1/models/\{name\}/query",'
                     r'status="415"\} [1-9]', text)
    for name in ("collider_queue_seconds_bucket", "collider_compute_seconds_sum",
                 "collider_points_total", "collider_points_per_second", "collider_models_loaded"):
        assert name in text
    assert metric(server.url, "collider_requests_in_flight") == 1  # only the scrape asking


def test_client_gone_mid_body_is_a_499_not_a_500(server):
    def count(status: str) -> float:
        text = httpx.get(f"{server.url}/metrics").text
        found = re.search(r'collider_requests_total\{method="POST",route="/v1/models/\{name\}/query",'
                          rf'status="{status}"\}} (\S+)', text)
        return float(found.group(1)) if found else 0.0

    before_499, before_500 = count("499"), count("500")
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(b"POST /v1/models/sphere/query HTTP/1.1\r\nHost: x\r\n"
                     b"Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n"
                     b'{"points": [[0, 0, 0], ')
        wait_for_a_pending_request(server.url)  # it reads the body; now the client goes
    wait_until(lambda: count("499") != before_499, "the server counted the client gone")
    assert count("499") == before_499 + 1
    assert count("500") == before_500


def test_a_reload_while_a_body_arrives_does_not_fail_that_request(tmp_path, model_files, engine):
    repo = make_repo(tmp_path / "models", model_files, names=["sphere"])
    body = json.dumps({"points": [[0.0, 0.0, 0.0]]}).encode()
    with ServerThread(models=repo, device="cpu", admin_token=ADMIN_TOKEN) as server:
        with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
            sock.sendall(b"POST /v1/models/sphere/query HTTP/1.1\r\nHost: x\r\nConnection: close\r\n"
                         b"Content-Type: application/json\r\nAccept: application/json\r\n"
                         b"Content-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body[:5])
            # The handler has looked the model up and waits for the rest of the body (nothing
            # between receiving the request and reading its body awaits anything else).
            wait_for_a_pending_request(server.url)
            reloaded = httpx.put(f"{server.url}/v1/admin/models/sphere",
                                 headers={"Authorization": f"Bearer {ADMIN_TOKEN}"}, timeout=60)
            assert reloaded.status_code == 200
            sock.sendall(body[5:])
            answer = b""
            while chunk := sock.recv(65536):
                answer += chunk
    head, _, payload = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 200"), answer[:300]
    want = engine["sphere"].query([[0.0, 0.0, 0.0]]).distance
    np.testing.assert_allclose(json.loads(payload)["distance"], want)


def serve_subprocess(repo, *args, env=None):
    """A ready ``collider serve`` over ``repo`` (output captured); ``(process, url)``."""
    from collider_cli.launch import ServerProcess

    server = ServerProcess(repo, "--device", "cpu", *args, env=env, capture=True)
    try:
        server.wait_ready(60)
    except (RuntimeError, TimeoutError) as exc:
        raise AssertionError(str(exc)) from None
    return server.process, server.url


def test_graceful_shutdown_answers_every_accepted_request(repo, engine):
    # Batches wait 5 s for more points, so the requests are still queued when SIGTERM arrives;
    # uvicorn then waits for them (graceful_shutdown_s is 30 s).
    process, url = serve_subprocess(repo, "--max-wait-ms", "5000")
    try:
        inputs = [sample_points(50 + i, 200 + i) for i in range(8)]
        with ThreadPoolExecutor(len(inputs)) as pool:
            futures = [pool.submit(post, f"{url}/v1/models/sphere/query", {"points": p})
                       for p in inputs]
            # SIGTERM once every request is accepted and queued (the queue gauge says so; a
            # fixed sleep was too short on a loaded machine).
            queued = sum(len(p) for p in inputs)
            end = time.monotonic() + 30
            while metric(url, 'collider_queue_points{model="sphere"}') != queued:
                assert time.monotonic() < end, "the requests never all reached the queue"
            process.send_signal(signal.SIGTERM)
            results = [f.result(30) for f in futures]
        for points, response in zip(inputs, results):
            np.testing.assert_array_equal(decode(response)["distance"],
                                          engine["sphere"].query(points).distance)
        # uvicorn re-raises the signal after its clean shutdown: the process ends by SIGTERM
        # (status 143 in a shell), as docs/service.md says.
        assert process.wait(30) == -signal.SIGTERM
        with pytest.raises(httpx.ConnectError):
            httpx.get(f"{url}/livez")
    finally:
        if process.poll() is None:
            process.kill()
        output = process.communicate()[0]
    assert "Application shutdown complete" in output


def test_settings_from_config_file_env_and_flags(tmp_path, monkeypatch):
    from collider_server.service import load_settings

    config = tmp_path / "serve.toml"
    config.write_text("[serve]\nmax_wait_ms = 5.0\nmax_batch_points = 1000\nport = 9001\n")
    monkeypatch.setenv("COLLIDER_MAX_BATCH_POINTS", "2000")
    settings = load_settings(config, port=9002, max_wait_ms=None)
    assert (settings.max_wait_ms, settings.max_batch_points, settings.port) == (5.0, 2000, 9002)
    (tmp_path / "bad.json").write_text(json.dumps({"max_wait_mss": 1}))
    with pytest.raises(ValueError, match="max_wait_mss"):
        load_settings(tmp_path / "bad.json")
    (tmp_path / "flat.json").write_text(json.dumps({"max_wait_ms": 3, "port": 9003}))
    assert load_settings(tmp_path / "flat.json", port=None).max_wait_ms == 3.0
    (tmp_path / "broken.toml").write_text("port = [")
    with pytest.raises(ValueError, match="broken.toml: malformed config file"):
        load_settings(tmp_path / "broken.toml")
    with pytest.raises(ValueError, match="missing.toml: cannot read"):
        load_settings(tmp_path / "missing.toml")
    # uvicorn knows lower-case level names only: upper case is accepted, unknown names named.
    monkeypatch.setenv("COLLIDER_LOG_LEVEL", "DEBUG")
    assert load_settings().log_level == "debug"
    monkeypatch.setenv("COLLIDER_LOG_LEVEL", "verbose")
    with pytest.raises(ValueError, match="log_level: .*'verbose'"):
        load_settings()


# A refusal that broke would start the server in this process and block it: a deadline of one
# minute, not the suite's ten. The thread method: the signal method's exception is lost in uvicorn's loop.
@pytest.mark.timeout(60, method="thread")
def test_serve_cli_user_errors_are_one_line(tmp_path):
    # In this process (a traceback would be an exception here); the installed entry point's own
    # process is tests/cli/test_cli_models.py's.
    result = run_collider("serve", "--models", tmp_path / "none")
    assert result.returncode == 2 and "is not a folder" in result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1
    result = run_collider("serve", "--max-wait-ms", "-1")
    assert result.returncode == 2 and "max_wait_ms" in result.stderr


@pytest.mark.timeout(60, method="thread")  # as above: a placeholder let through would serve in this process
@pytest.mark.parametrize("variable, value", [("COLLIDER_TOKEN", "change-me"),
                                             ("COLLIDER_ADMIN_TOKEN", "change-me-too"),
                                             ("COLLIDER_TOKEN", " CHANGEME ")])
def test_a_placeholder_token_is_refused(tmp_path, monkeypatch, variable, value):
    """The examples' placeholders are public: a server holding one would be open to anyone."""
    from collider_server.service import load_settings

    monkeypatch.setenv(variable, value)
    setting = variable.removeprefix("COLLIDER_").lower()
    with pytest.raises(ValueError, match=f"{setting}: .*placeholder"):
        load_settings()
    for other in [k for k in os.environ if k.startswith("COLLIDER_") and k != variable]:
        monkeypatch.delenv(other)
    result = run_collider("serve", "--models", tmp_path)
    assert result.returncode == 2 and "placeholder" in result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1
    monkeypatch.setenv(variable, "a-real-secret-of-ours")
    assert getattr(load_settings(), setting) == "a-real-secret-of-ours"


def test_cors_is_off_by_default_and_on_when_configured(server, repo):
    preflight = {"Origin": "http://sim.example", "Access-Control-Request-Method": "POST"}
    closed = httpx.options(f"{server.url}/v1/models/sphere/query", headers=preflight)
    assert "access-control-allow-origin" not in closed.headers
    with ServerThread(models=repo, device="cpu", cors_origins=["http://sim.example"]) as open_server:
        allowed = httpx.options(f"{open_server.url}/v1/models/sphere/query", headers=preflight)
        assert allowed.headers["access-control-allow-origin"] == "http://sim.example"


def test_server_keeps_answering_while_a_batch_computes(tmp_path, tiny_neural_collider):
    from collider_server.engine.modelfile import save_collider

    collider = tiny_neural_collider([-0.2] * 3, [0.2] * 3, name="net")
    save_collider(collider, tmp_path / "models" / "net.safetensors")
    with ServerThread(models=tmp_path / "models", device="cpu") as server:
        # Hold the batch inside its compute call until the other routes have answered: events,
        # not a guess that 60,000 points take longer than some sleep on this machine.
        engine = server.app.state.collider.registry.get("net").collider
        computing, release = threading.Event(), threading.Event()
        real_query_local = engine.query_local

        def gated_query_local(*args, **kwargs):
            computing.set()
            release.wait(60)
            return real_query_local(*args, **kwargs)

        engine.query_local = gated_query_local
        points = sample_points(2000, 11).astype(np.float32)
        big = background_post(f"{server.url}/v1/models/net/query",
                              {"points": points, "fields": ["distance", "normal"]})
        try:
            assert computing.wait(60), "the query never reached its compute call"
            assert httpx.get(f"{server.url}/livez").status_code == 200
            assert httpx.get(f"{server.url}/v1/models").status_code == 200
            assert not big.done()  # still computing while the others were answered
        finally:
            release.set()
        response = big.result(120)
        assert response.status_code == 200
        np.testing.assert_array_equal(decode(response)["distance"],
                                      collider.query(points, ["distance"]).distance)


def test_shutdown_closes_stalled_uploads_and_still_answers_the_query_in_compute(repo, engine):
    """Issue 35, item 3: five connections that sent half a body held SIGTERM for the whole body
    timeout (29.6 s). Now they are answered 503 shutting-down and closed at once, while a query
    whose body had arrived (held 2 s by max_wait_ms) is still answered."""
    process, url = serve_subprocess(repo, "--max-wait-ms", "2000", "--body-timeout-s", "60")
    port = int(url.rsplit(":", 1)[1])
    stalled = []
    try:
        for _ in range(5):
            sock = socket.create_connection(("127.0.0.1", port), timeout=30)
            sock.sendall(b"POST /v1/models/sphere/query HTTP/1.1\r\nHost: x\r\n"
                         b"Content-Type: application/json\r\nContent-Length: 1000\r\n\r\n"
                         b'{"points": [[0, 0, ')
            stalled.append(sock)
        points = sample_points(300, 7)
        with ThreadPoolExecutor(1) as pool:
            answer = pool.submit(post, f"{url}/v1/models/sphere/query", {"points": points})
            end = time.monotonic() + 30
            while metric(url, 'collider_queue_points{model="sphere"}') != len(points):
                assert time.monotonic() < end, "the query never reached the queue"
            process.send_signal(signal.SIGTERM)
            signalled = time.monotonic()
            assert process.wait(30) == -signal.SIGTERM
            stopped_s = time.monotonic() - signalled
            response = answer.result(30)
        np.testing.assert_array_equal(decode(response)["distance"],
                                      engine["sphere"].query(points).distance)
        assert stopped_s < 10, f"SIGTERM took {stopped_s:.1f} s"  # the body timeout is 60 s
        for sock in stalled:
            answered = b""
            while chunk := sock.recv(65536):  # ends when the server closes the connection
                answered += chunk
            head, _, body = answered.partition(b"\r\n\r\n")
            assert head.startswith(b"HTTP/1.1 503 Service Unavailable\r\n"), answered[:200]
            assert json.loads(body)["type"] == "shutting-down"
    finally:
        for sock in stalled:
            sock.close()
        if process.poll() is None:
            process.kill()
        process.communicate()
