"""A ``collider serve`` subprocess for the served half of a bench: the product's own command,
on a free loopback port, until the block ends."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator


from ..service.launch import free_port  # noqa: E402,F401  (one home for it)


@contextlib.contextmanager
def serve_process(models: Path, *flags: str, ready_timeout_s: float = 300.0) -> Iterator[str]:
    """Run ``collider serve --models MODELS FLAGS`` on 127.0.0.1; yields its URL once
    ``/readyz`` answers 200 (every model loaded and warmed up). Its output goes to a temporary
    log that is shown when it fails to start."""
    from collider_client import Client

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {k: v for k, v in os.environ.items() if k not in ("COLLIDER_TOKEN", "COLLIDER_ADMIN_TOKEN")}
    with tempfile.TemporaryFile() as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "collider_server.cli", "serve", "--host", "127.0.0.1",
             "--port", str(port), "--models", str(models), "--log-level", "warning", *flags],
            stdout=log, stderr=subprocess.STDOUT, env=env)
        try:
            with Client(url, timeout_s=5.0) as probe:
                end = time.monotonic() + ready_timeout_s
                while not _ready(probe):
                    if process.poll() is not None or time.monotonic() > end:
                        log.seek(0)
                        tail = log.read().decode(errors="replace")[-2000:]
                        raise RuntimeError(f"collider serve did not become ready (exit code "
                                           f"{process.poll()}):\n{tail}")
                    time.sleep(0.2)  # start-up only: nothing to wait on but the port
            yield url
        finally:
            process.terminate()
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def _ready(client) -> bool:
    try:
        return client.ready()
    except Exception:  # connection refused while the server starts
        return False
