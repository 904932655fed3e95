"""Shared by the service benchmarks: a lean keep-alive HTTP/1.1 client on asyncio streams, a
``collider serve`` subprocess, the benchmark models, and latency percentiles.

Why a hand-written client: on a 2-core machine the client shares the CPU with the server, and a
general-purpose async client (httpx) spends ~1 ms of Python per request, which would measure the
client instead of the server. This one writes the request bytes and reads ``Content-Length``
bytes back, nothing more (loopback only, no TLS, no chunked responses: the server sends none).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MESHES = REPO.parent / "shared" / "data" / "meshes"
sys.path.insert(0, str(REPO / "client"))

from collider_cli.launch import free_port  # noqa: F401  (one home for it)
from collider_contract import wire


class HTTPError(Exception):
    def __init__(self, status: int, body: bytes):
        super().__init__(f"HTTP {status}: {body[:300]!r}")
        self.status = status
        self.body = body


class LeanConnection:
    """One keep-alive HTTP/1.1 connection; one request at a time."""

    def __init__(self, host: str, port: int, token: str | None = None):
        self.host, self.port = host, port
        self.auth = f"Authorization: Bearer {token}\r\n" if token else ""
        self.reader = self.writer = None

    async def post(self, path: str, body: bytes, media: str = wire.MSGPACK,
                   headers: str = "") -> tuple[int, bytes]:
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
            sock = self.writer.get_extra_info("socket")
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        head = (f"POST {path} HTTP/1.1\r\nHost: {self.host}\r\nContent-Type: {media}\r\n"
                f"Content-Length: {len(body)}\r\n{self.auth}{headers}\r\n").encode()
        self.writer.write(head + body)
        status_line = await self.reader.readline()
        if not status_line:
            raise ConnectionError("server closed the connection")
        status = int(status_line.split()[1])
        length, closing = 0, False
        while True:
            line = await self.reader.readline()
            if line in (b"\r\n", b""):
                break
            name, _, value = line.partition(b":")
            if name.strip().lower() == b"content-length":
                length = int(value)
            elif name.strip().lower() == b"connection":
                closing = value.strip().lower() == b"close"
        data = await self.reader.readexactly(length)
        if closing:  # e.g. nginx after keepalive_requests (1,000) on one connection: the next opens anew
            await self.close()
            self.reader = self.writer = None
        return status, data

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            with contextlib.suppress(Exception):
                await self.writer.wait_closed()


def query_body(points: np.ndarray, fields, **extra) -> bytes:
    return wire.dumps({"points": points, "fields": list(fields), **extra}, wire.MSGPACK)


def decode_response(data: bytes) -> dict:
    body = wire.loads(data, wire.MSGPACK)
    return {k: wire.decode_array(v, k) for k, v in body.items() if k != "model"}


@contextlib.contextmanager
def serve(models: Path, *flags: str, env: dict | None = None):
    """``collider serve`` on a free loopback port until the block ends; yields its port.
    ``flags`` may hold ``--device``; the server's default is ``auto`` (CUDA when present)."""
    from collider_cli.launch import serve_process

    with serve_process(models, "--log-level", "warning", *flags, env=env) as server:
        SERVER_PIDS[server.port] = server.process.pid
        yield server.port


#: The process id of each running ``serve`` by port (for :func:`cpu_seconds`).
SERVER_PIDS: dict[int, int] = {}


def cpu_seconds(port: int) -> float:
    """CPU seconds (user + system, all threads) the server on ``port`` has used so far: a cost
    measure that other processes' load on a shared machine disturbs much less than wall time."""
    fields = Path(f"/proc/{SERVER_PIDS[port]}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def prepare_models(root: Path, resolution: int = 128) -> dict[str, str]:
    """The benchmark models in ``root``: ``bunny-voxel`` (the Stanford bunny baked at
    ``resolution``^3) and ``bunny-neural`` (``models/bunny.safetensors`` when it exists, else an
    untrained network of the paper's bunny architecture: the same compute per point).
    Returns ``{name: description}``."""
    from collider_server.engine.modelfile import load_collider, save_collider
    from collider_server.making.bake import bake_collider
    from collider_server.making.mesh_files import load_mesh

    root.mkdir(parents=True, exist_ok=True)
    notes = {}
    voxel = root / "bunny-voxel.safetensors"
    if not voxel.is_file():
        mesh = load_mesh(MESHES / "stanford-bunny.obj")
        save_collider(bake_collider(mesh, "voxel", "bunny-voxel", resolution=resolution,
                                    device="cpu"), voxel)
    notes["bunny-voxel"] = f"voxel, stanford-bunny.obj baked at {resolution}^3"
    neural = root / "bunny-neural.safetensors"
    trained = REPO / "models" / "bunny.safetensors"
    if trained.is_file():
        shutil.copy(trained, neural)
        notes["bunny-neural"] = "neural, the trained models/bunny.safetensors"
    elif not neural.is_file():
        save_collider(untrained_paper_bunny(load_collider(voxel, "cpu")), neural)
    if "bunny-neural" not in notes:
        notes["bunny-neural"] = ("neural, UNTRAINED network of the paper-bunny architecture "
                                 "(K=128, 3x256; same compute per point as the trained one)")
    return notes


def untrained_paper_bunny(voxel):
    import torch

    from collider_server.engine.collider import ColliderInfo
    from collider_server.engine.kinds.neural import PRESETS, NeuralCollider, build_network

    arch = PRESETS["paper-bunny"]
    lo, hi = voxel.domain_min, voxel.domain_max
    info = ColliderInfo("bunny-neural", "neural", lo.tolist(), hi.tolist(),
                        settings={"architecture": dataclasses.asdict(arch)},
                        source={"note": "untrained; benchmark stand-in"})
    torch.manual_seed(0)
    network = build_network(arch, 0.5 * (lo + hi), 0.5 * float((hi - lo).max()))
    return NeuralCollider(info, network, "cpu")


def percentiles_ms(latencies_s: list[float]) -> dict[str, float]:
    if not latencies_s:
        return {"p50_ms": float("nan"), "p90_ms": float("nan"), "p99_ms": float("nan")}
    a = np.asarray(latencies_s) * 1e3
    return {"p50_ms": float(np.percentile(a, 50)), "p90_ms": float(np.percentile(a, 90)),
            "p99_ms": float(np.percentile(a, 99))}


def bunny_points(collider, n: int, seed: int) -> np.ndarray:
    """(n, 3) float32 points in the collider's domain box (collider frame = world frame here)."""
    rng = np.random.default_rng(seed)
    return rng.uniform(collider.domain_min, collider.domain_max, (n, 3)).astype(np.float32)


def machine_note() -> str:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{os.cpu_count()} CPU cores, load average {load:.1f} at start"


NGINX_TEMPLATE = REPO / "docker" / "nginx" / "collider.conf.template"


def nginx_config(policy: str, listen_port: int, replicas: list[int], root: Path,
                 worker_connections: int = 1024) -> Path:
    """docker/nginx/collider.conf.template rendered as the nginx image renders it, inside a
    minimal nginx.conf of one worker (``worker_connections``: the image's default is 1024).
    policy: "by-model" (the template) or "round-robin" (its ``hash`` line removed)."""
    text = NGINX_TEMPLATE.read_text()
    if policy == "round-robin":
        text, removed = re.subn(r"^\s*hash \$collider_model consistent;\n", "", text, flags=re.MULTILINE)
        assert removed == 1, "the template's hash line moved: update benchmarks/service_common.py"
    servers = " ".join(f"server 127.0.0.1:{p} max_fails=1 fail_timeout=10s;" for p in replicas)
    values = {"NGINX_LISTEN": f"127.0.0.1:{listen_port}", "COLLIDER_UPSTREAMS": servers}
    text = re.sub(r"\$\{(\w+)\}", lambda m: values.get(m.group(1), m.group(0)), text)
    (root / "collider.conf").write_text(text)
    user = "user root root;" if os.geteuid() == 0 else ""
    temp = "\n".join(f"    {kind}_temp_path {root}/{kind};"
                     for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"))
    conf = root / "nginx.conf"
    conf.write_text(f"{user}\nworker_processes 1;\nworker_rlimit_nofile {4 * worker_connections};\n"
                    f"daemon off;\npid {root}/nginx.pid;\n"
                    f"events {{ worker_connections {worker_connections}; }}\n"
                    f"http {{\n{temp}\n    access_log off;\n    include {root}/collider.conf;\n}}\n")
    return conf


@contextlib.contextmanager
def nginx(conf: Path, port: int):
    """Run nginx with ``conf`` until the block ends (then a graceful stop); yields its PID."""
    binary = shutil.which("nginx") or "/usr/sbin/nginx"
    error_log = conf.parent / "error.log"
    process = subprocess.Popen([binary, "-p", str(conf.parent), "-e", str(error_log), "-c", str(conf)])
    try:
        end = time.monotonic() + 30
        while True:  # until it accepts connections
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if process.poll() is not None or time.monotonic() > end:
                    raise RuntimeError(f"nginx did not start: {error_log.read_text()}")
                time.sleep(0.05)
        yield process.pid
    finally:
        process.send_signal(signal.SIGQUIT)
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            process.kill()
