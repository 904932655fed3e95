"""Client test fixtures: a small model repository and a real ``collider serve`` on loopback.

Colliders are baked into a temporary folder (a voxel sphere of radius 0.1 m and a voxel box), so
these tests need no shared meshes and no trained models. Units: metres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

SPHERE_RADIUS_M = 0.1


def _bake(kind_shape: str, root: Path) -> None:
    import trimesh

    from collider_server.engine.meshes import Mesh
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider

    if kind_shape == "sphere":
        shape = trimesh.creation.icosphere(subdivisions=4, radius=SPHERE_RADIUS_M)
    else:
        shape = trimesh.creation.box(extents=(0.2, 0.1, 0.05))
    collider = bake_collider(Mesh(np.asarray(shape.vertices), np.asarray(shape.faces), kind_shape),
                             "voxel", kind_shape, resolution=32, show_progress=False)
    save_collider(collider, root / f"{kind_shape}.safetensors")


def _bake_pulse(root: Path) -> None:
    """The project's pulsing sphere (radius 0.1 m +-20 %, centre moving +-0.1 m along x, 13
    frames at 12 fps, looping) as ``pulse`` (exact, animated) and ``pulse-voxel`` (5 keyframe
    grids of 24^3)."""
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.animations import pulsing_sphere
    from collider_server.making.bake import bake_animated_collider

    animation, _ = pulsing_sphere()
    save_collider(bake_animated_collider(animation, "mesh", "pulse"), root / "pulse.safetensors")
    save_collider(bake_animated_collider(animation, "voxel", "pulse-voxel", resolution=24, keyframes=5,
                                         show_progress=False), root / "pulse-voxel.safetensors")


def _save_arm(root: Path) -> None:
    """The project's generated skinned arm (3 joints, clips "wave" and "reach") as ``arm``
    (kind ``skinned``, exact)."""
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.skinned import skinned_arm, skinned_collider

    save_collider(skinned_collider(skinned_arm(), "arm"), root / "arm.safetensors")


def _save_arm_neural(root: Path) -> None:
    """The arm's articulated network (kind ``neural-skinned``) as ``arm-neural``: a small one
    trained for a few steps (the answers are the network's, whatever its accuracy: the same
    embedded and served)."""
    from collider_server.engine.kinds.neural_skinned import ArticulatedGridArchitecture
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.skinned import skinned_arm
    from collider_server.making.training import TrainConfig
    from collider_server.making.training.articulated import train_articulated

    arch = ArticulatedGridArchitecture(levels=4, max_resolution=64, table_log2=12, label_resolution=32,
                                       weight_resolution=24)
    config = TrainConfig(samples=8000, steps=20, batch_size=1024, validation_points=500, threads=1)
    result = train_articulated(skinned_arm(), "arm-neural", config, arch=arch, show_progress=False)
    save_collider(result.collider, root / "arm-neural.safetensors")


@pytest.fixture(scope="session")
def models_dir(built_once) -> Path:
    """A model repository with ``sphere`` (radius 0.1 m at the origin) and ``box``
    (0.2 x 0.1 x 0.05 m at the origin), voxel colliders, and the animated ``pulse`` (exact) and
    ``pulse-voxel`` (keyframe grids) of the pulsing sphere, the skinned ``arm`` and its
    articulated network ``arm-neural``; metres."""
    pytest.importorskip("collider_server", reason="the engine (server extras) is not installed")

    def make(root: Path) -> None:
        _bake("sphere", root)
        _bake("box", root)
        _bake_pulse(root)
        _save_arm(root)
        _save_arm_neural(root)

    return built_once("client-models", make)  # one for every worker: the arm's network trains once


@pytest.fixture(scope="session")
def server_url(models_dir):
    """URL of a real ``collider serve`` subprocess over ``models_dir`` on a free loopback port."""
    try:
        import collider_server.service  # noqa: F401
    except ImportError as exc:
        pytest.skip(f"collider_server.service is missing ({exc}); the remote backend cannot be "
                    "tested against a real server")
    from collider_cli.launch import ServerProcess

    server = ServerProcess(models_dir, "--device", "cpu", "--log-level", "warning",
                           env={"PYTHONUNBUFFERED": "1"})
    try:
        server.wait_ready(90)
    except (RuntimeError, TimeoutError) as exc:
        pytest.fail(f"collider serve did not become ready: {exc}")
    try:
        yield server.url
    finally:
        server.stop()
