"""Scene files: the shipped ones load; bad ones fail before the run with the key and the file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from collider_client.sim.command import SCENES_DIR, resolve_scene, shipped_scenes
from collider_client.sim.scene import SceneError, load_scene

BASE = """
[scene]
duration_s = 0.01
dt_s = 1e-4

[cloth]
width = 10
height = 8
spacing_m = 0.01

[effects.gravity]
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


def test_shipped_scenes_load():
    names = shipped_scenes()
    assert {"drape_bunny", "drape_dragon", "moving_bunny", "flag_in_wind",
            "drape_bunny_all_effects"} <= set(names)
    for name in names:
        scene = load_scene(resolve_scene(name))
        assert scene.steps >= 1
    paper = load_scene(SCENES_DIR / "drape_bunny.toml")
    assert (paper.cloth.width, paper.cloth.height, paper.cloth.spacing_m) == (200, 200, 1.25e-3)
    assert (paper.dt_s, paper.duration_s, paper.steps) == (1e-4, 5.0, 50_000)
    assert paper.effects["pins"]["corners"] == ["top-left", "top-right"]
    assert [c.model for c in paper.colliders] == ["bunny"]
    assert not load_scene(SCENES_DIR / "flag_in_wind.toml").colliders


def test_minimal_scene(tmp_path):
    scene = load_scene(write(tmp_path, BASE))
    assert list(scene.effects) == ["gravity"]
    assert scene.effects["gravity"]["acceleration_m_s2"].tolist() == [0.0, 0.0, -9.81]


@pytest.mark.parametrize("change, message", [
    (("[cloth]", "[cloth]\ncolour = 'red'"), "unknown key(s) ['cloth.colour']"),
    (("[effects.gravity]", "[effects.gravity]\nstrength = 3"), "effects.gravity.strength"),
    (("[effects.gravity]", "[effects.magnetism]"), "effects.magnetism"),
    (("dt_s = 1e-4", "dt_s = 0"), "scene.dt_s: must be > 0, got 0"),
    (("dt_s = 1e-4", "dt_s = -1e-4"), "scene.dt_s: must be > 0"),
    (("dt_s = 1e-4", "dt_s = 'fast'"), "scene.dt_s: must be a number, got str"),
    (("width = 10", "width = 2.5"), "cloth.width: must be an integer"),
    (("width = 10", "width = 1"), "cloth.width: must be >= 2"),
    (("spacing_m = 0.01", "spacing_m = 0.01\ndensity_kg_m2 = -0.2"), "cloth.density_kg_m2: must be > 0"),
    (("spacing_m = 0.01", "spacing_m = 0.01\norigin_m = [0, 0]"), "cloth.origin_m: must be a list of 3"),
    (("duration_s = 0.01\n", ""), "scene.duration_s: missing"),
    (("[effects.gravity]", "[effects.stretch]\nstiffness_n_m = 1e9"), "unstable"),
    (("[effects.gravity]", "[effects.pins]\nvertices = [[10, 0]]"), "outside the 10 x 8 cloth"),
    (("[effects.gravity]", "[effects.friction]\ncoefficient = 0.3"), "needs effects.collisions"),
    (("[effects.gravity]", "[effects.collisions]"), "needs at least one [[colliders]]"),
    (("[effects.gravity]", "[effects.gravity]\n[[colliders]]\nmodel = 'sphere'"),
     "[effects.collisions] is absent"),
    (("[effects.gravity]", "[effects.collisions]\n[[colliders]]\nmodel = 'sphere'\n"
                           "motion = { kind = 'teleport' }"), "colliders[0].motion.kind"),
    (("[effects.gravity]", "[effects.collisions]\n[[colliders]]\nmodel = 'sphere'\n"
                           "motion = { kind = 'keyframes', times_s = [1, 0] }"), "increase strictly"),
    (("[effects.gravity]", "[effects.friction]\ncoefficient = -1"), "effects.friction.coefficient"),
])
def test_validation_names_the_key_and_the_file(tmp_path, change, message):
    old, new = change
    assert old in BASE
    path = write(tmp_path, BASE.replace(old, new, 1))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert message in str(info.value)
    assert str(path) in str(info.value)


def test_not_toml(tmp_path):
    with pytest.raises(SceneError, match="not valid TOML"):
        load_scene(write(tmp_path, "[scene\n"))


def test_cli_rejects_bad_scene_in_one_line(tmp_path):
    path = write(tmp_path, BASE.replace("dt_s = 1e-4", "dt_s = 0"))
    out = subprocess.run([sys.executable, "-m", "collider_server.cli", "simulate", str(path),
                          "--output", str(tmp_path / "out")], capture_output=True, text=True)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    assert out.stderr.strip().count("\n") == 0
    assert "scene.dt_s: must be > 0" in out.stderr and str(path) in out.stderr


def test_cli_rejects_a_missing_model_before_the_run(tmp_path, models_dir):
    path = write(tmp_path, BASE + "[effects.collisions]\n[[colliders]]\nmodel = 'teapot'\n")
    out = subprocess.run([sys.executable, "-m", "collider_server.cli", "simulate", str(path),
                          "--models", str(models_dir), "--output", str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert out.returncode == 2, out.stderr
    assert "colliders[].model ['teapot'] not found" in out.stderr
    assert "box" in out.stderr and "sphere" in out.stderr
    assert not (tmp_path / "out" / "scene.pc2").exists()  # rejected before anything ran


def test_cli_runs_a_shipped_scene_without_colliders(tmp_path):
    # No colliders: runs with no model repository and no server at all.
    out = subprocess.run([sys.executable, "-m", "collider_server.cli", "simulate", "flag_in_wind",
                          "--steps", "250", "--quiet", "--models", str(tmp_path / "absent"),
                          "--output", str(tmp_path / "out")], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "fields asked     none (no collisions)" in out.stdout
    assert "points sent      0 of 0" in out.stdout
    for suffix in (".obj", ".pc2", ".png", ".report.json"):
        assert (tmp_path / "out" / f"flag_in_wind{suffix}").is_file()


def test_cli_unreachable_server_is_one_line(tmp_path):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    path = write(tmp_path, BASE + "[effects.collisions]\n[[colliders]]\nmodel = 'sphere'\n")
    out = subprocess.run([sys.executable, "-m", "collider_server.cli", "simulate", str(path),
                          "--server", f"http://127.0.0.1:{port}", "--output", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr and "cannot connect" in out.stderr


def test_collider_poses_from_motion():
    import numpy as np

    from collider_client.sim.scene import ColliderSpec, Motion, euler_matrix, pose_function

    # +90 deg about x turns a Y-up model Z-up: x stays, y -> z, z -> -y.
    np.testing.assert_allclose(euler_matrix(np.array([90.0, 0, 0])),
                               [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-15)
    static = pose_function(ColliderSpec("m", np.array([1.0, 2, 3]), np.zeros(3), Motion()))
    np.testing.assert_allclose(static(7.0)[:3, 3], [1, 2, 3])
    moving = pose_function(ColliderSpec("m", np.zeros(3), np.zeros(3), Motion(
        kind="velocity", velocity_m_s=np.array([0.0, 0, 0.1]),
        angular_velocity_deg_s=np.array([0.0, 0, 90.0]))))
    pose = moving(1.0)
    np.testing.assert_allclose(pose[:3, 3], [0, 0, 0.1])
    np.testing.assert_allclose(pose[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # 90 deg about z
    keyed = pose_function(ColliderSpec("m", np.array([0.0, 0, 1]), np.zeros(3), Motion(
        kind="keyframes", times_s=np.array([0.0, 2.0]),
        positions_m=np.array([[0.0, 0, 0], [2.0, 0, 0]]),
        rotations_deg=np.array([[0.0, 0, 0], [0.0, 0, 180]]))))
    np.testing.assert_allclose(keyed(1.0)[:3, 3], [1, 0, 1])
    np.testing.assert_allclose(keyed(1.0)[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(keyed(5.0)[:3, 3], [2, 0, 1])  # held after the last key
