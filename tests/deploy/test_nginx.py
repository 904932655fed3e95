"""The compose topology without Docker: a real nginx, configured with the very file compose mounts
(docker/nginx/collider.conf.template), in front of two real ``collider serve`` processes on
loopback. Queries are routed by model (consistent hash of the model name), and killing a replica
loses no query: nginx resends it to the other one (``proxy_next_upstream ... non_idempotent``)."""

from __future__ import annotations

import shutil
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import pytest

from .conftest import NGINX_TEMPLATE, SPHERE_RADIUS_M, Nginx, Replica, bake_sphere, nginx_binary

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(nginx_binary() is None,
                       reason="nginx is not installed (Debian: apt-get install nginx; .ci/run does)"),
]

# 16 models: with two replicas, the chance that consistent hashing puts all of them on one replica
# is 2 * 2**-16, so "both replicas serve some models" is a property of the setup, not luck.
MODELS = [f"m{i:02d}" for i in range(16)]


@pytest.fixture(scope="module")
def repo(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("replica-models")
    sphere = bake_sphere(tmp_path_factory.mktemp("baked") / "sphere.safetensors")
    for name in MODELS:
        shutil.copy(sphere, root / f"{name}.safetensors")
    return root


def start(repo: Path, root: Path) -> tuple[list[Replica], Nginx]:
    replicas = [Replica(repo), Replica(repo)]  # both start loading at once
    try:
        for replica in replicas:
            replica.wait_ready()
        return replicas, Nginx(root, [r.address for r in replicas])
    except BaseException:
        for replica in replicas:
            replica.kill()
        raise


def stop(replicas: list[Replica], nginx: Nginx) -> None:
    nginx.stop()
    for replica in replicas:
        replica.kill()


def points_for(i: int, n: int = 64) -> np.ndarray:
    """n points (metres, world frame) at known distances from the sphere centred at the origin."""
    rng = np.random.default_rng(i)
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return directions * rng.uniform(0.05, 0.15, size=(n, 1))


def query(client: httpx.Client, url: str, model: str, i: int) -> None:
    """One query through nginx; asserts 200 and distances close to the analytic sphere's."""
    points = points_for(i)
    response = client.post(f"{url}/v1/models/{model}/query",
                           json={"points": points.tolist(), "fields": ["distance"]})
    assert response.status_code == 200, (model, i, response.status_code, response.text)
    distance = np.asarray(response.json()["distance"])
    want = np.linalg.norm(points, axis=1) - SPHERE_RADIUS_M
    np.testing.assert_allclose(distance, want, atol=0.01)  # a 24^3 voxel grid of a 0.2 m sphere


def test_queries_are_spread_by_model(repo, tmp_path):
    replicas, nginx = start(repo, tmp_path)
    try:
        with httpx.Client(timeout=60) as client:
            for k, model in enumerate(MODELS):
                for round_ in range(3):  # in a row: round-robin would split them over both
                    query(client, nginx.url, model, 100 * round_ + k)
        served = [r.points_by_model() for r in replicas]
    finally:
        stop(replicas, nginx)

    owners = {}
    for model in MODELS:
        holders = [i for i, counts in enumerate(served) if counts.get(model, 0) > 0]
        assert len(holders) == 1, f"{model}'s queries went to replicas {holders}, not to one"
        owners[model] = holders[0]
        assert served[holders[0]][model] == 3 * 64  # every point of its 3 queries, on one replica
    assert set(owners.values()) == {0, 1}, "one replica got every model"
    # The access log agrees: one replica per model route, no retries while both are up.
    for uri, status, tried in nginx.log():
        assert status == 200 and len(tried) == 1
        model = uri.split("/")[3]
        assert tried[0] == replicas[owners[model]].address


def test_killing_a_replica_loses_no_query(repo, tmp_path):
    """Four callers keep querying every model; after 48 answers one replica is SIGKILLed (no
    drain: a crash). Every query still gets a correct 200: those the dead replica held or would
    have got are resent by nginx to the survivor. The one case nginx cannot resend is a response
    the replica had begun (headers sent, body cut by the kill): the caller sees a dropped
    response and resends the query itself (queries are idempotent). That can happen only to a
    query in flight at the kill, so at most one per caller."""
    replicas, nginx = start(repo, tmp_path)
    total, kill_after = 192, 48
    answered = 0
    cut_by_the_kill = 0
    lock = threading.Lock()
    killed = threading.Event()
    victim = replicas[0]

    def caller(worker: int) -> None:
        nonlocal answered, cut_by_the_kill
        with httpx.Client(timeout=60) as client:
            for j in range(worker, total, 4):
                try:
                    query(client, nginx.url, MODELS[j % len(MODELS)], j)
                except httpx.RemoteProtocolError:  # a response begun by the killed replica
                    with lock:
                        cut_by_the_kill += 1
                    query(client, nginx.url, MODELS[j % len(MODELS)], j)
                with lock:
                    answered += 1
                    if answered == kill_after:
                        victim.kill()  # from the caller that got answer 48: others are mid-query
                        killed.set()

    try:
        with ThreadPoolExecutor(4) as pool:
            for future in [pool.submit(caller, w) for w in range(4)]:
                future.result()  # re-raises any failed query
        assert killed.is_set()
        survivor = replicas[1].points_by_model()
        log = nginx.log()
    finally:
        stop(replicas, nginx)

    assert answered == total
    assert cut_by_the_kill <= 4, f"{cut_by_the_kill} responses cut: more than the queries in flight"
    # A cut response is logged once with whatever status nginx recorded for it, on the victim
    # alone; the caller's resend is a row of its own. Every other row is a 200.
    assert len(log) == total + cut_by_the_kill
    others = [(status, tried) for _, status, tried in log if status != 200]
    assert len(others) <= cut_by_the_kill and all(t == [victim.address] for _, t in others), others
    # nginx met the dead replica and resent to the survivor (a row naming both, dead one first) ...
    resent = [tried for _, _, tried in log if len(tried) == 2]
    assert resent and all(t == [victim.address, replicas[1].address] for t in resent)
    # ... and the survivor now serves every model, the dead replica's included.
    assert set(survivor) == set(MODELS)


def test_routing_benchmark_runs_both_policies(repo, tmp_path):
    """benchmarks/routing.py end to end, briefly: both policies answered every query, and by model
    each model's batches were all on one replica."""
    import json
    import subprocess
    import sys

    from .conftest import REPO

    output = tmp_path / "routing.json"
    result = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "routing.py"), "--collider",
         str(repo / "m00.safetensors"), "--models", "2", "--simulators", "2", "--cloth", "8",
         "--duration", "1", "--output", str(output)],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads(output.read_text())
    policies = {r["policy"]: r for r in report["results"]}
    assert set(policies) == {"round-robin", "by-model"}
    for r in policies.values():
        assert r["queries"] > 0 and set(r["status"]) == {"200"} and r["mean_batch_points"] >= 64
    assert all(len(replicas) == 1 for replicas in policies["by-model"]["replicas_of_model"].values())
    assert "| by-model |" in result.stdout


def test_slow_clients_are_closed_by_nginx_and_never_reach_a_replica(repo, tmp_path):
    """The deployment's nginx holds slow connections itself: 30 that send half a request line, or
    nothing, are closed by nginx within its client_header_timeout (10 s, as the service's own
    header_timeout_s) although the replica behind would wait 120 s; the replica never has more
    than nginx's few keep-alive connections open, and a normal query meanwhile is answered."""
    import re
    import socket
    import time

    replica = Replica(repo, "--header-timeout-s", "120").wait_ready()
    front = Nginx(tmp_path, [replica.address])
    try:
        timeout_s = float(re.search(r"client_header_timeout (\d+)s;", NGINX_TEMPLATE.read_text()).group(1))
        assert timeout_s == 10
        slow = []
        for i in range(30):
            sock = socket.create_connection(("127.0.0.1", front.port), timeout=timeout_s + 5)
            if i % 2:
                sock.sendall(b"POST /v1/models/m00/query HTTP/1.1\r\nHost: x\r\nContent-Le")
            slow.append(sock)
        opened = time.monotonic()
        with httpx.Client(timeout=30) as client:
            query(client, front.url, "m00", 0)
        metrics = httpx.get(f"{replica.url}/metrics", timeout=10).text
        open_now = float(re.search(r"^collider_connections_open (\S+)$", metrics, re.MULTILINE).group(1))
        assert open_now <= 3  # nginx's upstream keep-alive and this scrape, not the 30
        lifetimes = []
        for sock in slow:
            assert sock.recv(4096) == b""  # closed without an answer (nginx's header timeout)
            lifetimes.append(time.monotonic() - opened)
            sock.close()
        assert timeout_s - 0.5 < min(lifetimes) and max(lifetimes) < timeout_s + 3, lifetimes
    finally:
        front.stop()
        replica.kill()
