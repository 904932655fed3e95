"""Starting a server for tests, benchmarks and ``collider bench``: a free loopback port, the
service in a thread or a ``collider serve`` subprocess, and waiting until it is ready. The one
home of these helpers (tests and benchmarks import them from here).

Waiting polls ``/readyz``: start-up has nothing else to wait on but an open port. Nothing here
listens anywhere but loopback.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from typing_extensions import Self

LOOPBACK = "127.0.0.1"
#: Tokens a test or benchmark server must not inherit from the caller's environment.
TOKEN_VARIABLES = ("COLLIDER_TOKEN", "COLLIDER_ADMIN_TOKEN")


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port nobody listens on at the moment (the OS's choice)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def wait_ready(url: str, process: subprocess.Popen | None = None, timeout_s: float = 120.0,
               headers: dict | None = None) -> None:
    """Poll ``url/readyz`` until it answers 200. Raises RuntimeError (with the process's output
    when it was captured) if ``process`` exits first, TimeoutError after ``timeout_s``."""
    import httpx

    end = time.monotonic() + timeout_s
    # One client for every poll: a new one (httpx.get) builds its SSL context each time, ~0.1 s
    # of CPU per poll taken from the server starting beside it.
    with httpx.Client(timeout=2, headers=headers) as client:
        while time.monotonic() < end:
            if process is not None and process.poll() is not None:
                raise RuntimeError(f"collider serve exited with {process.returncode}"
                                   f"{_output_tail(process)}")
            try:
                if client.get(f"{url}/readyz").status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.05)
    raise TimeoutError(f"{url} did not become ready in {timeout_s} s")


def _output_tail(process: subprocess.Popen) -> str:
    if process.stdout is None:
        return ""
    with contextlib.suppress(Exception):
        out = process.stdout.read()
        out = out.decode(errors="replace") if isinstance(out, bytes) else out
        return ":\n" + out[-3000:]
    return ""


class ServerProcess:
    """``collider serve --models MODELS FLAGS`` on a free loopback port (or ``port``).

    env : extra environment variables; the caller's COLLIDER_TOKEN / COLLIDER_ADMIN_TOKEN are
        not inherited unless given here
    capture : collect stdout + stderr (text) in ``process.stdout`` instead of inheriting them
    """

    def __init__(self, models: Path, *flags: str, port: int | None = None,
                 env: dict | None = None, capture: bool = False):
        self.port = port or free_port()
        self.url = f"http://{LOOPBACK}:{self.port}"
        base = {k: v for k, v in os.environ.items() if k not in TOKEN_VARIABLES}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "collider_cli", "serve", "--host", LOOPBACK,
             "--port", str(self.port), "--models", str(models), *flags],
            env={**base, **(env or {})},
            stdout=subprocess.PIPE if capture else None,
            stderr=subprocess.STDOUT if capture else None, text=capture)

    def wait_ready(self, timeout_s: float = 120.0) -> ServerProcess:
        try:
            wait_ready(self.url, self.process, timeout_s)
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self, timeout_s: float = 30.0) -> int:
        """SIGTERM, then SIGKILL after ``timeout_s``; the exit status. A captured output's pipe is
        closed."""
        if self.process.poll() is None:
            self.process.terminate()
        try:
            return self.process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            return self.process.wait()
        finally:
            if self.process.stdout is not None:
                self.process.stdout.close()


@contextlib.contextmanager
def serve_process(models: Path, *flags: str, ready_timeout_s: float = 120.0,
                  **options) -> Iterator[ServerProcess]:
    """A :class:`ServerProcess`, ready, until the block ends (then stopped)."""
    server = ServerProcess(models, *flags, **options).wait_ready(ready_timeout_s)
    try:
        yield server
    finally:
        server.stop()


class ServerThread:
    """The service under a real uvicorn in a background thread of this process, on a free
    loopback port; a context manager (ready on entry, stopped on exit).

    settings : :class:`~collider_server.service.ServiceSettings` fields; ``compute_threads``
        defaults to this process's torch thread count (the server sets it process-wide)
    ready_timeout_s : how long entry waits for ``/readyz`` (every model loaded and warmed up)
    """

    def __init__(self, ready_timeout_s: float = 120.0, **settings):
        import torch
        import uvicorn

        from collider_server.service import ServiceSettings, create_app, uvicorn_config

        self.port = free_port()
        self.url = f"http://{LOOPBACK}:{self.port}"
        self.ready_timeout_s = ready_timeout_s
        settings.setdefault("compute_threads", torch.get_num_threads())
        self.settings = ServiceSettings(host=LOOPBACK, port=self.port, **settings)
        self.app = create_app(self.settings)
        config = uvicorn_config(self.app, LOOPBACK, self.port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> Self:
        self.thread.start()
        wait_ready(self.url, timeout_s=self.ready_timeout_s)
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(30)
        if self.thread.is_alive():
            raise RuntimeError("server thread did not stop")
