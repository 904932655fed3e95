"""Real servers for the service tests: uvicorn on a free loopback port, in a background thread
(or a ``collider serve`` subprocess for the signal tests), over a tiny voxel repository."""

from __future__ import annotations

import shutil
import socket
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

SPHERE_RADIUS = 0.1  # metres; the "sphere" model
SMALL_RADIUS = 0.05  # metres; the "small" model
ADMIN_TOKEN = "admin-secret"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(url: str, timeout_s: float = 60.0, headers=None) -> None:
    """Poll ``/readyz`` until 200 (start-up only; the tests themselves never poll)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.05)
    raise TimeoutError(f"{url} did not become ready in {timeout_s} s")


class ServerThread:
    """``collider_server.service`` under a real uvicorn in a background thread."""

    def __init__(self, **settings):
        import uvicorn

        from collider_server.service import ServiceSettings, create_app

        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        import torch

        # Keep the test process's torch thread count as it is (the server sets it process-wide).
        settings.setdefault("compute_threads", torch.get_num_threads())
        self.settings = ServiceSettings(host="127.0.0.1", port=self.port, **settings)
        self.app = create_app(self.settings)
        config = uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> "ServerThread":
        self.thread.start()
        wait_ready(self.url)
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(30)
        assert not self.thread.is_alive(), "server did not stop"


def bake_sphere(path: Path, radius: float, resolution: int = 32) -> Path:
    import trimesh

    from collider_server.bake import bake_collider
    from collider_server.meshes import Mesh
    from collider_server.modelfile import save_collider

    tri = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    collider = bake_collider(Mesh(np.asarray(tri.vertices), np.asarray(tri.faces), path.stem),
                             "voxel", path.stem, resolution=resolution, show_progress=False,
                             device="cpu")
    return save_collider(collider, path)


@pytest.fixture(scope="session")
def model_files(tmp_path_factory) -> dict[str, Path]:
    """Voxel spheres baked once per session: ``sphere`` (r 0.1 m) and ``small`` (r 0.05 m)."""
    root = tmp_path_factory.mktemp("model-files")
    return {"sphere": bake_sphere(root / "sphere.safetensors", SPHERE_RADIUS),
            "small": bake_sphere(root / "small.safetensors", SMALL_RADIUS, 24)}


def make_repo(root: Path, model_files: dict[str, Path], names=("sphere", "small")) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copy(model_files[name], root / f"{name}.safetensors")
    return root


@pytest.fixture(scope="session")
def repo(tmp_path_factory, model_files) -> Path:
    return make_repo(tmp_path_factory.mktemp("repo"), model_files)


@pytest.fixture(scope="session")
def engine(repo):
    """The same models in process, for comparing numbers."""
    from collider_server.repository import ModelRepository

    repository = ModelRepository(repo)
    return {name: repository.load(name, "cpu") for name in repository.names()}


@pytest.fixture(scope="module")
def server(repo):
    """Default settings (coalescing on), no auth, admin disabled."""
    with ServerThread(models=repo, device="cpu") as s:
        yield s
