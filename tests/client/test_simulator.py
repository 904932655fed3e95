"""The Verlet simulator: a small cloth dropped on a real (voxel) sphere stays outside it, the step
runs only the declared effects, outputs load back, and both backends give the same run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import collider_client as cc
from collider_client.sim.output import read_pc2
from collider_client.sim.run import run_scene
from collider_client.sim.scene import load_scene
from collider_client.sim.simulator import Simulator

from .conftest import SPHERE_RADIUS_M

DROP = """
[scene]
name = "drop on a sphere"
duration_s = 0.12
dt_s = 2e-4
frame_every_steps = 50
preview_frames = [0, -1]

[cloth]
width = 16
height = 16
spacing_m = 0.01
origin_m = [-0.075, -0.075, 0.104]
density_kg_m2 = 0.3

[[colliders]]
model = "sphere"
{motion}

[effects.gravity]
[effects.stretch]
stiffness_n_m = 40.0
[effects.shear]
stiffness_n_m = 10.0
[effects.damping]
coefficient_1_s = 1.0
[effects.collisions]
eps_m = 1e-3
{friction}
"""


class CountingClient(cc.Client):
    """A real embedded client that counts the queries it answers and the fields asked."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.calls, self.fields, self.only_colliding = 0, set(), set()

    def query(self, model, points, fields=cc.USE_CLIENT_DEFAULT, **kwargs):
        self.calls += 1
        self.fields |= set(fields)
        self.only_colliding.add(kwargs.get("only_colliding", False))
        return super().query(model, points, fields=fields, **kwargs)


def scene_file(tmp_path: Path, motion: str = "", friction: str = "", name="drop.toml") -> Path:
    path = tmp_path / name
    path.write_text(DROP.format(motion=motion, friction=friction))
    return path


def sphere_depth(frames, centre_at=lambda t: np.zeros(3)) -> float:
    """Deepest penetration (m, >= 0) of any vertex of any frame into the exact sphere."""
    return max(float(-(np.linalg.norm(v - centre_at(t), axis=1) - SPHERE_RADIUS_M).min())
               for t, v in frames)


def test_drop_on_sphere_stays_outside(tmp_path, models_dir):
    scene = load_scene(scene_file(tmp_path))
    with CountingClient(models=models_dir, device="cpu") as client:
        report, frames = run_scene(scene, client, tmp_path / "out", show_progress=False)
    assert report.steps == 600 and len(frames) == 13
    assert report.colliding_max > 20            # the cloth reached the sphere
    assert sphere_depth(frames) < 1e-3          # and never went 1 mm inside it
    assert frames[-1][1][:, 2].min() < 0.09     # its edges fell past the top, draping
    assert client.fields == {"distance", "contact", "collides"}  # no friction: no normals asked for
    assert client.only_colliding == {True}  # contacts of the colliding points only
    assert client.calls == report.queries > 0
    # The same check through the exact mesh SDF that `--check-mesh` uses.
    import trimesh

    from collider_client.sim.exact import exact_penetration

    mesh_path = tmp_path / "sphere.obj"
    trimesh.creation.icosphere(subdivisions=5, radius=SPHERE_RADIUS_M).export(mesh_path)
    check = exact_penetration(scene, frames, {"sphere": mesh_path})
    assert check["max_depth_m"] < 1e-3 and check["frames"] == 13
    assert check["min_distance_m"] < 2.5e-3  # it rests on the sphere, about eps away
    # Outputs: OBJ (quads), PC2 (every frame), PNG, report.
    obj = (tmp_path / "out" / "drop.obj").read_text().splitlines()
    assert sum(line.startswith("v ") for line in obj) == 256
    assert sum(line.startswith("f ") for line in obj) == 225
    cache = read_pc2(tmp_path / "out" / "drop.pc2")
    assert cache.shape == (13, 256, 3)
    np.testing.assert_allclose(cache[-1], frames[-1][1])
    assert (tmp_path / "out" / "drop.png").read_bytes()[:4] == b"\x89PNG"
    saved = json.loads((tmp_path / "out" / "drop.report.json").read_text())
    assert saved["steps"] == 600 and set(saved["time_per_step_ms"]) == {
        "total", "integration", "collision", "query"}


def test_absent_effects_are_not_executed(tmp_path, models_dir):
    # No colliders: no client at all, so no query can happen; only gravity: no springs ran,
    # every vertex moved by exactly the same free-fall displacement.
    path = tmp_path / "fall.toml"
    path.write_text("[scene]\nduration_s = 0.01\ndt_s = 1e-3\n[cloth]\nwidth = 5\nheight = 4\n"
                    "spacing_m = 0.01\n[effects.gravity]\n")
    sim = Simulator(load_scene(path), client=None)
    assert sim.effects == ["gravity"] and sim.hook is None and not sim.springs
    assert sim.wind is None and sim.pinned is None and sim.damping == 0.0
    for _ in range(10):
        sim.step()
    shift = sim.x - sim.rest
    np.testing.assert_allclose(shift, np.broadcast_to(shift[0, 0], shift.shape), atol=1e-15)
    # Verlet from rest: z_n = -g dt^2 n (n + 1) / 2.
    assert shift[0, 0, 2] == pytest.approx(-9.81 * 1e-6 * 55)
    # Colliders far away: the hook runs but sends nothing (outside the inflated box).
    far = load_scene(scene_file(tmp_path, name="far.toml"))
    far.cloth.origin_m = np.array([5.0, 5.0, 5.0])
    with CountingClient(models=models_dir, device="cpu") as client:
        infos = {m.name: m for m in client.list_models()}
        sim = Simulator(far, client, infos)
        for _ in range(20):
            sim.step()
        assert client.calls == 0 and sim.hook.stats.points_sent == 0
        assert sim.hook.stats.points_total == 20 * 256


def test_friction_asks_for_normals(tmp_path, models_dir):
    scene = load_scene(scene_file(tmp_path, friction="[effects.friction]\ncoefficient = 0.5"))
    with CountingClient(models=models_dir, device="cpu") as client:
        report, frames = run_scene(scene, client, tmp_path / "out", show_progress=False,
                                   steps=300, preview=False)
    assert client.fields == {"distance", "contact", "collides", "normal"}
    assert client.only_colliding == {True}
    assert "friction" in report.effects
    assert sphere_depth(frames) < 1e-3


def test_moving_sphere_pushes_the_cloth(tmp_path, models_dir):
    # The sphere starts 5 cm lower and rises at 0.5 m/s into the falling cloth.
    motion = ("position_m = [0.0, 0.0, -0.05]\n"
              "motion = { kind = 'velocity', velocity_m_s = [0.0, 0.0, 0.5] }")
    scene = load_scene(scene_file(tmp_path, motion=motion,
                                  friction="[effects.friction]\ncoefficient = 0.8"))
    with cc.Client(models=models_dir, device="cpu") as client:
        report, frames = run_scene(scene, client, tmp_path / "out", show_progress=False,
                                   preview=False)
    centre = lambda t: np.array([0.0, 0.0, -0.05 + 0.5 * t])  # noqa: E731
    assert sphere_depth(frames, centre) < 1e-3
    assert report.colliding_max > 20
    top = frames[-1][1][:, 2].max()
    assert top > 0.104  # lifted above where it started by the rising sphere


def test_remote_and_embedded_runs_agree(tmp_path, models_dir, server_url):
    out = {}
    for backend in ("embedded", "remote"):
        args = ["--server", server_url] if backend == "remote" else ["--models", str(models_dir)]
        result = subprocess.run(
            [sys.executable, "-m", "collider_server.cli", "simulate",
             str(scene_file(tmp_path)), "--steps", "300", "--quiet", "--no-preview",
             "--output", str(tmp_path / backend), *args],
            capture_output=True, text=True, timeout=300)
        assert result.returncode == 0, result.stderr
        assert f"({backend} backend)" in result.stdout
        out[backend] = read_pc2(tmp_path / backend / "drop.pc2")
    np.testing.assert_allclose(out["embedded"], out["remote"], atol=1e-5)


def test_check_mesh_places_the_mesh_as_the_model_was_made(tmp_path):
    """A model baked from a 1 m sphere file with --fit-size 0.2 is a 0.1 m sphere: the exact
    check must measure against the file placed the same way, not the raw 1 m sphere."""
    pytest.importorskip("collider_server", reason="the engine (server extras) is not installed")
    import trimesh

    from collider_server.cli import main

    big = tmp_path / "big.obj"
    trimesh.creation.icosphere(subdivisions=4, radius=1.0).export(big)
    models = tmp_path / "models"
    assert main(["bake", str(big), "--kind", "voxel", "--resolution", "48", "--name", "sphere",
                 "--fit-size", "0.2", "--models", str(models), "--quiet"]) == 0
    out = tmp_path / "out"
    code = main(["simulate", str(scene_file(tmp_path)), "--models", str(models), "--steps", "300",
                 "--no-preview", "--quiet", "--output", str(out), "--check-mesh", f"sphere={big}"])
    assert code == 0
    check = json.loads((out / "drop.report.json").read_text())["exact_check"]
    assert check["max_depth_m"] < 1e-3  # the raw 1 m file would put every vertex ~0.9 m inside
    assert check["min_distance_m"] < 3e-3  # and the cloth did reach the sphere
