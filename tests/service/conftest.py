"""Real servers for the service tests: uvicorn on a free loopback port, in a background thread
(or a ``collider serve`` subprocess for the signal tests), over a tiny voxel repository."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

SPHERE_RADIUS = 0.1  # metres; the "sphere" model
SMALL_RADIUS = 0.05  # metres; the "small" model
ADMIN_TOKEN = "admin-secret"


# One home for starting servers (tests, benchmarks, collider bench): collider_cli.launch.
from collider_cli.launch import ServerThread, free_port, wait_ready  # noqa: F401


def bake_sphere(path: Path, radius: float, resolution: int = 32) -> Path:
    import trimesh

    from collider_server.engine.meshes import Mesh
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider

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
    from collider_server.engine.repository import ModelRepository

    repository = ModelRepository(repo)
    return {name: repository.load(name, "cpu") for name in repository.names()}


@pytest.fixture(scope="module")
def server(repo):
    """Default settings (coalescing on), no auth, admin disabled."""
    with ServerThread(models=repo, device="cpu") as s:
        yield s
