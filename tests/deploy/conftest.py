"""Real processes for the topology tests: ``collider serve`` replicas on loopback ports and a real
nginx (Debian's package) configured with docker/nginx/collider.conf.template, the file the compose
setup mounts into the official nginx image."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
NGINX_TEMPLATE = REPO / "docker" / "nginx" / "collider.conf.template"
SPHERE_RADIUS_M = 0.1


# One home for starting servers: collider_cli.launch.
from collider_cli.launch import free_port, wait_ready


def render_template(text: str, values: dict[str, str]) -> str:
    """What the nginx image's envsubst step does: replace ``${NAME}`` for the given names only,
    leaving nginx's own ``$variables`` alone."""
    return re.sub(r"\$\{(\w+)\}", lambda m: values.get(m.group(1), m.group(0)), text)


def nginx_binary() -> str | None:
    return shutil.which("nginx") or next(
        (p for p in ("/usr/sbin/nginx", "/usr/local/sbin/nginx") if os.access(p, os.X_OK)), None)


class Replica:
    """One ``collider serve`` process on a loopback port."""

    def __init__(self, models: Path, *flags: str):
        self.port = free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.url = f"http://{self.address}"
        self.process = subprocess.Popen(
            [sys.executable, "-m", "collider_cli", "serve", "--models", str(models),
             "--port", str(self.port), "--device", "cpu", "--compute-threads", "1",
             "--log-level", "warning", *flags],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def wait_ready(self) -> Replica:
        wait_ready(self.url, self.process)
        return self

    def points_by_model(self) -> dict[str, float]:
        """``collider_points_total`` of each model, from this replica's ``/metrics``."""
        text = httpx.get(f"{self.url}/metrics", timeout=10).text
        return {m: float(v) for m, v in
                re.findall(r'^collider_points_total\{model="([^"]+)"\} ([0-9.e+]+)$', text, re.MULTILINE)}

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
        self.process.communicate(timeout=30)


class Nginx:
    """nginx in the foreground with the shared template rendered into its ``http`` block; the
    access log records, per request, the model route, status and every replica tried."""

    LOG_FORMAT = "$uri $status \"$upstream_addr\""

    def __init__(self, root: Path, upstreams: list[str]):
        binary = nginx_binary()
        if binary is None:
            pytest.skip("nginx is not installed (Debian: apt-get install nginx; .ci/run does)")
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.root = root
        self.access_log = root / "access.log"
        servers = " ".join(f"server {a} max_fails=1 fail_timeout=30s;" for a in upstreams)
        (root / "collider.conf").write_text(render_template(
            NGINX_TEMPLATE.read_text(),
            {"NGINX_LISTEN": f"127.0.0.1:{self.port}", "COLLIDER_UPSTREAMS": servers}))
        # As root, nginx's workers would run as 'nobody', who cannot enter pytest's 0700 folders.
        user = "user root root;" if os.geteuid() == 0 else ""
        (root / "nginx.conf").write_text(f"""
{user}
worker_processes 1;
daemon off;
pid {root}/nginx.pid;
error_log {root}/error.log warn;
events {{ worker_connections 512; }}
http {{
    client_body_temp_path {root}/client_body;
    proxy_temp_path {root}/proxy;
    fastcgi_temp_path {root}/fastcgi;
    uwsgi_temp_path {root}/uwsgi;
    scgi_temp_path {root}/scgi;
    log_format routed '{self.LOG_FORMAT}';
    access_log {self.access_log} routed;
    include {root}/collider.conf;
}}
""")
        subprocess.run([binary, "-t", "-q", "-p", str(root), "-e", str(root / "error.log"),
                        "-c", str(root / "nginx.conf")], check=True, capture_output=True)
        self.process = subprocess.Popen(
            [binary, "-p", str(root), "-e", str(root / "error.log"), "-c", str(root / "nginx.conf")],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        end = time.monotonic() + 30
        while True:  # start-up only: until nginx accepts connections
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                break
            except OSError:
                if self.process.poll() is not None or time.monotonic() > end:
                    raise AssertionError(f"nginx did not start: {(root / 'error.log').read_text()}")
                time.sleep(0.05)

    def log(self) -> list[tuple[str, int, list[str]]]:
        """(uri, status, replicas tried in order) per answered request."""
        rows = []
        for line in self.access_log.read_text().splitlines():
            uri, status, upstreams = re.fullmatch(r'(\S+) (\d+) "(.*)"', line).groups()
            rows.append((uri, int(status), [u.strip() for u in upstreams.split(",") if u.strip()]))
        return rows

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGQUIT)  # graceful: finish open requests
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
        self.process.communicate()


def bake_sphere(path: Path, radius: float = SPHERE_RADIUS_M, resolution: int = 24) -> Path:
    """A small voxel sphere collider (metres, centred at the origin of its frame)."""
    import trimesh

    from collider_server.engine.meshes import Mesh
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider

    tri = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    collider = bake_collider(Mesh(np.asarray(tri.vertices), np.asarray(tri.faces), path.stem),
                             "voxel", path.stem, resolution=resolution, show_progress=False,
                             device="cpu")
    return save_collider(collider, path)
