"""Scene files: the shipped ones load; bad ones fail before the run with the key and the file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from collider_client.sim.scene import SCENES_DIR, load_scene, resolve_scene, shipped_scenes
from collider_client.sim.tables import SceneError

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
    (("[effects.gravity]", ("[effects.collisions]\n[[colliders]]\nmodel = 'sphere'\n"
                           "motion = { kind = 'teleport' }")), "colliders[0].motion.kind"),
    (("[effects.gravity]", ("[effects.collisions]\n[[colliders]]\nmodel = 'sphere'\n"
                           "motion = { kind = 'keyframes', times_s = [1, 0] }")), "increase strictly"),
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
    out = subprocess.run([sys.executable, "-m", "collider_cli", "simulate", str(path),
                          "--output", str(tmp_path / "out")], capture_output=True, text=True)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    assert out.stderr.strip().count("\n") == 0
    assert "scene.dt_s: must be > 0" in out.stderr and str(path) in out.stderr


def test_cli_rejects_a_missing_model_before_the_run(tmp_path, models_dir):
    path = write(tmp_path, BASE + "[effects.collisions]\n[[colliders]]\nmodel = 'teapot'\n")
    out = subprocess.run([sys.executable, "-m", "collider_cli", "simulate", str(path),
                          "--models", str(models_dir), "--output", str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert out.returncode == 2, out.stderr
    assert "colliders[0].model: no model named 'teapot'" in out.stderr
    assert "box" in out.stderr and "sphere" in out.stderr
    assert not (tmp_path / "out" / "scene.pc2").exists()  # rejected before anything ran


def test_cli_runs_a_shipped_scene_without_colliders(tmp_path):
    # No colliders: runs with no model repository and no server at all.
    out = subprocess.run([sys.executable, "-m", "collider_cli", "simulate", "flag_in_wind",
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
    out = subprocess.run([sys.executable, "-m", "collider_cli", "simulate", str(path),
                          "--server", f"http://127.0.0.1:{port}", "--output", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr and "cannot connect" in out.stderr


def test_collider_poses_from_motion():
    import numpy as np

    from collider_client.sim.motion import ColliderSpec, Motion, euler_matrix, pose_function

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


# -- every default, every error message in full, every boundary (mutation testing, issue #9) ----

def scene_error(tmp_path: Path, text: str) -> str:
    """The message of the SceneError that loading ``text`` raises, after its ``FILE: `` prefix."""
    path = write(tmp_path, text)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert message.startswith(f"{path}: "), message
    return message[len(f"{path}: "):]


ALL_EFFECTS = """
[effects.gravity]
[effects.wind]
velocity_m_s = [1, 0, 0]
[effects.damping]
coefficient_1_s = 0
[effects.stretch]
stiffness_n_m = 1
[effects.shear]
stiffness_n_m = 2
[effects.bend]
stiffness_n_m = 3
[effects.pins]
corners = ["top-left"]
[effects.collisions]
[effects.friction]
coefficient = 0
[[colliders]]
model = "sphere"
"""


def test_minimal_scene_takes_the_documented_defaults(tmp_path):
    scene = load_scene(write(tmp_path, BASE))
    assert scene.path == tmp_path / "scene.toml"
    assert scene.name == "scene"  # the file's stem
    assert (scene.duration_s, scene.dt_s, scene.steps) == (0.01, 1e-4, 100)
    assert scene.frame_every == 100
    assert scene.preview_frames == [0, -1]
    cloth = scene.cloth
    assert (cloth.width, cloth.height, cloth.spacing_m) == (10, 8, 0.01)
    assert (cloth.axes, cloth.density_kg_m2) == ("xy", 0.5)
    assert cloth.origin_m.dtype == np.float64 and cloth.origin_m.tolist() == [0.0, 0.0, 0.0]
    assert scene.colliders == []
    assert scene.has("gravity") and not scene.has("wind") and not scene.has("collisions")


def test_declared_values_replace_the_defaults(tmp_path):
    scene = load_scene(write(tmp_path, BASE.replace("[cloth]", "[cloth]\naxes = 'yz'\n"
                                                    "origin_m = [1, 2, -3]\ndensity_kg_m2 = 0.3")
                             .replace("dt_s = 1e-4", "dt_s = 0.1\nname = 'drape'\n"
                                      "frame_every_steps = 1\npreview_frames = []")
                             .replace("duration_s = 0.01", "duration_s = 0.3")))
    assert (scene.name, scene.frame_every, scene.preview_frames) == ("drape", 1, [])
    assert scene.steps == 3  # 0.3 / 0.1 = 2.9999999999999996 in floating point: rounded
    assert (scene.cloth.axes, scene.cloth.density_kg_m2) == ("yz", 0.3)
    # integers in the file still give float64 vectors (the simulator updates them in place)
    assert scene.cloth.origin_m.dtype == np.float64
    assert scene.cloth.origin_m.tolist() == [1.0, 2.0, -3.0]


def test_each_effect_takes_its_documented_defaults(tmp_path):
    from collider_client.sim.scene import EFFECTS

    scene = load_scene(write(tmp_path, BASE.replace("[effects.gravity]\n", ALL_EFFECTS)))
    assert list(scene.effects) == list(EFFECTS)  # all declared, in the simulator's order
    fx = scene.effects
    assert fx["gravity"]["acceleration_m_s2"].tolist() == [0.0, 0.0, -9.81]
    assert fx["wind"]["velocity_m_s"].tolist() == [1.0, 0.0, 0.0]
    assert fx["wind"]["drag_1_s"] == 1.0
    assert fx["damping"] == {"coefficient_1_s": 0}  # 0 is allowed (>= 0)
    assert [fx[s]["stiffness_n_m"] for s in ("stretch", "shear", "bend")] == [1, 2, 3]
    assert fx["pins"] == {"corners": ["top-left"], "vertices": []}
    assert fx["collisions"] == {"eps_m": 1e-3}
    assert fx["friction"] == {"coefficient": 0, "restitution": 0.0}  # coefficient 0 is allowed
    (collider,) = scene.colliders
    assert collider.model == "sphere"
    assert collider.position_m.tolist() == [0.0, 0.0, 0.0]
    assert collider.rotation_deg.tolist() == [0.0, 0.0, 0.0]
    assert collider.motion.kind == "static"


def test_motion_defaults_are_still(tmp_path):
    base = BASE.replace("[effects.gravity]", "[effects.collisions]\n[[colliders]]\nmodel = 'sphere'\n")
    velocity = load_scene(write(tmp_path, base + "motion = { kind = 'velocity' }\n")).colliders[0]
    assert velocity.motion.kind == "velocity"
    assert velocity.motion.velocity_m_s.tolist() == [0.0, 0.0, 0.0]
    assert velocity.motion.angular_velocity_deg_s.tolist() == [0.0, 0.0, 0.0]
    keyed = load_scene(write(tmp_path, base + "motion = { kind = 'keyframes', times_s = [0, 1, 3] }\n"))
    motion = keyed.colliders[0].motion
    assert motion.times_s.tolist() == [0.0, 1.0, 3.0]
    assert motion.positions_m.tolist() == [[0.0, 0.0, 0.0]] * 3
    assert motion.rotations_deg.tolist() == [[0.0, 0.0, 0.0]] * 3
    keyed = load_scene(write(tmp_path, base + "motion = { kind = 'keyframes', times_s = [0, 2], "
                             "positions_m = [[0, 0, 0], [1, 2, 3]], rotations_deg = [[0, 0, 0], [0, 0, 90]] }\n"))
    motion = keyed.colliders[0].motion
    assert motion.positions_m.tolist() == [[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]
    assert motion.rotations_deg.tolist() == [[0.0, 0.0, 0.0], [0.0, 0.0, 90.0]]
    for motion in ("{ kind = 'static' }", "{}"):  # kind defaults to static
        static = load_scene(write(tmp_path, base + f"motion = {motion}\n")).colliders[0]
        assert static.motion.kind == "static"


COLLIDER = "[effects.collisions]\n[[colliders]]\nmodel = 'sphere'\n"
KNOWN_EFFECTS = sorted(["gravity", "wind", "damping", "stretch", "shear", "bend", "pins",
                        "collisions", "friction"])


@pytest.mark.parametrize("old, new, message", [
    # [scene]
    ("[scene]\nduration_s = 0.01\ndt_s = 1e-4\n", "", "scene: missing (required)"),
    ("[scene]", "scene = 3\n[other]", "[scene] must be a table, got int"),
    ("dt_s = 1e-4", "dt_s = inf", "scene.dt_s: must be finite, got inf"),
    ("dt_s = 1e-4", "dt_s = nan", "scene.dt_s: must be finite, got nan"),
    ("dt_s = 1e-4", "dt_s = true", "scene.dt_s: must be a number, got bool True"),
    ("dt_s = 1e-4", "dt_s = [1e-4]", "scene.dt_s: must be a number, got list [0.0001]"),
    ("dt_s = 1e-4", "dt_s = 0.02", "scene.dt_s: is longer than duration_s (0.02 > 0.01)"),
    ("dt_s = 1e-4", "", "scene.dt_s: missing (required)"),
    ("duration_s = 0.01", "duration_s = 0", "scene.duration_s: must be > 0, got 0"),
    ("duration_s = 0.01", "duration_s = -1.0", "scene.duration_s: must be > 0, got -1.0"),
    ("[scene]", "speed = 3\n[scene]", ("unknown key(s) ['speed']; "
     "known here: ['cloth', 'colliders', 'effects', 'scene']")),
    ("dt_s = 1e-4", "dt_s = 1e-4\nframe_every_steps = 0",
     "scene.frame_every_steps: must be >= 1, got 0"),
    ("dt_s = 1e-4", "dt_s = 1e-4\nframe_every_steps = 2.0",
     "scene.frame_every_steps: must be an integer, got float 2.0"),
    ("dt_s = 1e-4", "dt_s = 1e-4\npreview_frames = 'last'",
     "scene.preview_frames: must be a list of frame indices (negative from the end), got 'last'"),
    ("dt_s = 1e-4", "dt_s = 1e-4\npreview_frames = ''",
     "scene.preview_frames: must be a list of frame indices (negative from the end), got ''"),
    ("dt_s = 1e-4", "dt_s = 1e-4\npreview_frames = [0, true]",
     "scene.preview_frames: must be a list of frame indices (negative from the end), got [0, True]"),
    ("dt_s = 1e-4", "dt_s = 1e-4\npreview_frames = [0, 1.5]",
     "scene.preview_frames: must be a list of frame indices (negative from the end), got [0, 1.5]"),
    ("dt_s = 1e-4", "dt_s = 1e-4\nname = 3", "scene.name: must be a string, got int 3"),
    ("dt_s = 1e-4", "dt_s = 1e-4\nspeed = 3", ("unknown key(s) ['scene.speed']; known here: "
     "['dt_s', 'duration_s', 'frame_every_steps', 'name', 'preview_frames']")),
    # [cloth]
    ("[cloth]\nwidth = 10\nheight = 8\nspacing_m = 0.01\n", "", "cloth: missing (required)"),
    ("width = 10\n", "", "cloth.width: missing (required)"),
    ("height = 8\n", "", "cloth.height: missing (required)"),
    ("width = 10", "width = 4097", "cloth.width: must be <= 4096, got 4097"),
    ("height = 8", "height = 4097", "cloth.height: must be <= 4096, got 4097"),
    ("height = 8", "height = 1", "cloth.height: must be >= 2, got 1"),
    ("height = 8", "height = 8.0", "cloth.height: must be an integer, got float 8.0"),
    ("spacing_m = 0.01", "spacing = 0.01", "cloth.spacing_m: missing (required)"),
    ("spacing_m = 0.01", "spacing_m = 0", "cloth.spacing_m: must be > 0, got 0"),
    ("spacing_m = 0.01", "spacing_m = 0.01\naxes = 'zx'",
     "cloth.axes: must be one of ['xy', 'xz', 'yz'], got 'zx'"),
    ("spacing_m = 0.01", "spacing_m = 0.01\naxes = 1", "cloth.axes: must be a string, got int 1"),
    ("spacing_m = 0.01", "spacing_m = 0.01\norigin_m = [0, 0, true]",
     "cloth.origin_m: must be a list of 3 numbers, got [0, 0, True]"),
    ("spacing_m = 0.01", "spacing_m = 0.01\norigin_m = [0, 0, 'up']",
     "cloth.origin_m: must be a list of 3 numbers, got [0, 0, 'up']"),
    ("spacing_m = 0.01", "spacing_m = 0.01\norigin_m = 'up'",
     "cloth.origin_m: must be a list of 3 numbers, got 'up'"),
    ("spacing_m = 0.01", "spacing_m = 0.01\norigin_m = [0, 0, 0, 0]",
     "cloth.origin_m: must be a list of 3 numbers, got [0, 0, 0, 0]"),
    ("spacing_m = 0.01", "spacing_m = 0.01\norigin_m = [0, 0, inf]",
     "cloth.origin_m: must be finite, got [0, 0, inf]"),
    ("spacing_m = 0.01", "spacing_m = 0.01\ndensity_kg_m2 = 0",
     "cloth.density_kg_m2: must be > 0, got 0"),
    # [[colliders]] and their motion
    ("[scene]", "colliders = 3\n[scene]",
     "colliders: must be an array of tables ([[colliders]])"),
    ("[scene]", "colliders = [1]\n[scene]", "[colliders[0]] must be a table, got int"),
    ("[effects.gravity]", "[effects.collisions]\n[[colliders]]\nposition_m = [0, 0, 0]",
     "colliders[0].model: missing (required)"),
    ("[effects.gravity]", COLLIDER + "[[colliders]]\nmodel = 'box'\nposition_m = [0, 0]",
     "colliders[1].position_m: must be a list of 3 numbers, got [0, 0]"),
    ("[effects.gravity]", COLLIDER + "rotation_deg = [0, 0]",
     "colliders[0].rotation_deg: must be a list of 3 numbers, got [0, 0]"),
    ("[effects.gravity]", COLLIDER + "colour = 'red'", ("unknown key(s) ['colliders[0].colour']; "
     "known here: ['clip', 'loop', 'make', 'model', 'motion', 'position_m', 'rotation_deg', "
     "'time_offset_s']")),
    ("[effects.gravity]", COLLIDER + "clip = 3", "colliders[0].clip: must be a string, got int 3"),
    ("[effects.gravity]", COLLIDER + "time_offset_s = 'soon'",
     "colliders[0].time_offset_s: must be a number, got str 'soon'"),
    ("[effects.gravity]", COLLIDER + "time_offset_s = nan",
     "colliders[0].time_offset_s: must be finite, got nan"),
    ("[effects.gravity]", COLLIDER + "loop = 1", "colliders[0].loop: must be true or false, got int 1"),
    ("[effects.gravity]", COLLIDER + "make = 3", "colliders[0].make: must be a string, got int 3"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'teleport' }",
     "colliders[0].motion.kind: must be one of ['static', 'velocity', 'keyframes'], got 'teleport'"),
    ("[effects.gravity]", COLLIDER + "motion = { velocity_m_s = [0, 0, 1] }",
     "unknown key(s) ['colliders[0].motion.velocity_m_s']; known here: ['kind']"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'velocity', velocity_m_s = [0, 1] }",
     "colliders[0].motion.velocity_m_s: must be a list of 3 numbers, got [0, 1]"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'velocity', angular_velocity_deg_s = [0, 1] }",
     "colliders[0].motion.angular_velocity_deg_s: must be a list of 3 numbers, got [0, 1]"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'velocity', times_s = [0, 1] }",
     ("unknown key(s) ['colliders[0].motion.times_s']; "
     "known here: ['angular_velocity_deg_s', 'kind', 'velocity_m_s']")),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes' }",
     "colliders[0].motion.times_s: missing (required)"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0] }",
     "colliders[0].motion.times_s: must be a list of at least 2 numbers, got [0]"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0, true] }",
     "colliders[0].motion.times_s: must be a list of at least 2 numbers, got [0, True]"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0, '1'] }",
     "colliders[0].motion.times_s: must be a list of at least 2 numbers, got [0, '1']"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = '0 1' }",
     "colliders[0].motion.times_s: must be a list of at least 2 numbers, got '0 1'"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0, 1, 1] }",
     "colliders[0].motion.times_s: must increase strictly, got [0.0, 1.0, 1.0]"),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0, 1], "
                                     "positions_m = [[0, 0, 0]] }",
     ("colliders[0].motion.positions_m: must hold 2 finite [x, y, z] rows (one per time), "
     "got shape (1, 3)")),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0, 1], "
                                     "positions_m = [[0, 0], [0, 0]] }",
     ("colliders[0].motion.positions_m: must hold 2 finite [x, y, z] rows (one per time), "
     "got shape (2, 2)")),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0, 1], "
                                     "positions_m = [[0, 0, 0], [0, 0, inf]] }",
     ("colliders[0].motion.positions_m: must hold 2 finite [x, y, z] rows (one per time), "
     "got shape (2, 3)")),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0, 1], "
                                     "rotations_deg = [[0, 0, 'a'], [0, 0, 0]] }",
     ("colliders[0].motion.rotations_deg: must be a list of [x, y, z] lists, "
     "got [[0, 0, 'a'], [0, 0, 0]]")),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0, 1], "
                                     "rotations_deg = [[0, 0, 0]] }",
     ("colliders[0].motion.rotations_deg: must hold 2 finite [x, y, z] rows (one per time), "
     "got shape (1, 3)")),
    ("[effects.gravity]", COLLIDER + "motion = { kind = 'keyframes', times_s = [0, 1], speed = 1 }",
     ("unknown key(s) ['colliders[0].motion.speed']; "
     "known here: ['kind', 'positions_m', 'rotations_deg', 'times_s']")),
    # [effects]
    ("[effects.gravity]\n", "", "effects: missing (required)"),
    ("[effects.gravity]", "[effects.magnetism]",
     f"unknown key(s) ['effects.magnetism']; known here: {KNOWN_EFFECTS}"),
    ("[effects.gravity]", "[effects.gravity]\nacceleration_m_s2 = [0, -9.81]",
     "effects.gravity.acceleration_m_s2: must be a list of 3 numbers, got [0, -9.81]"),
    ("[effects.gravity]", "[effects.wind]\ndrag_1_s = 1",
     "effects.wind.velocity_m_s: missing (required)"),
    ("[effects.gravity]", "[effects.wind]\nvelocity_m_s = [1, 0, 0]\ndrag_1_s = -0.1",
     "effects.wind.drag_1_s: must be >= 0.0, got -0.1"),
    ("[effects.gravity]", "[effects.damping]",
     "effects.damping.coefficient_1_s: missing (required)"),
    ("[effects.gravity]", "[effects.damping]\ncoefficient_1_s = -1",
     "effects.damping.coefficient_1_s: must be >= 0.0, got -1"),
    ("[effects.gravity]", "[effects.stretch]", "effects.stretch.stiffness_n_m: missing (required)"),
    ("[effects.gravity]", "[effects.shear]\nstiffness_n_m = 0",
     "effects.shear.stiffness_n_m: must be > 0, got 0"),
    ("[effects.gravity]", "[effects.bend]\nstiffness_n_m = -1",
     "effects.bend.stiffness_n_m: must be > 0, got -1"),
    ("[effects.gravity]", COLLIDER.replace("]\n[", "]\neps_m = 0\n[", 1),
     "effects.collisions.eps_m: must be > 0, got 0"),
    ("[effects.gravity]", "[effects.friction]\nrestitution = 0.5\n" + COLLIDER,
     "effects.friction.coefficient: missing (required)"),
    ("[effects.gravity]", "[effects.friction]\ncoefficient = 0.3\nrestitution = 1.5\n" + COLLIDER,
     "effects.friction.restitution: must be <= 1.0, got 1.5"),
    ("[effects.gravity]", "[effects.friction]\ncoefficient = 0.3\nrestitution = -0.5\n" + COLLIDER,
     "effects.friction.restitution: must be >= 0.0, got -0.5"),
    # pins
    ("[effects.gravity]", "[effects.pins]\ncorners = 'top-left'",
     ("effects.pins.corners: must be a list of ['top-left', 'top-right', 'bottom-left', "
     "'bottom-right'], got 'top-left'")),
    ("[effects.gravity]", "[effects.pins]\ncorners = ['top-left', 'middle']",
     ("effects.pins.corners: must be a list of ['top-left', 'top-right', 'bottom-left', "
     "'bottom-right'], got ['top-left', 'middle']")),
    ("[effects.gravity]", "[effects.pins]\nvertices = '0 0'",
     "effects.pins.vertices: must be a list of [column, row] integer pairs, got '0 0'"),
    ("[effects.gravity]", "[effects.pins]\nvertices = [[1]]",
     "effects.pins.vertices: must be a list of [column, row] integer pairs, got [[1]]"),
    ("[effects.gravity]", "[effects.pins]\nvertices = [[1, 2, 3]]",
     "effects.pins.vertices: must be a list of [column, row] integer pairs, got [[1, 2, 3]]"),
    ("[effects.gravity]", "[effects.pins]\nvertices = [[1, 2.0]]",
     "effects.pins.vertices: must be a list of [column, row] integer pairs, got [[1, 2.0]]"),
    ("[effects.gravity]", "[effects.pins]\nvertices = [1, 2]",
     "effects.pins.vertices: must be a list of [column, row] integer pairs, got [1, 2]"),
    ("[effects.gravity]", "[effects.pins]\nvertices = [[-1, 0]]",
     "effects.pins.vertices: [-1, 0] is outside the 10 x 8 cloth"),
    ("[effects.gravity]", "[effects.pins]\nvertices = [[0, -1]]",
     "effects.pins.vertices: [0, -1] is outside the 10 x 8 cloth"),
    ("[effects.gravity]", "[effects.pins]\nvertices = [[0, 0], [10, 7]]",
     "effects.pins.vertices: [10, 7] is outside the 10 x 8 cloth"),
    ("[effects.gravity]", "[effects.pins]\nvertices = [[9, 8]]",
     "effects.pins.vertices: [9, 8] is outside the 10 x 8 cloth"),
    ("[effects.gravity]", "[effects.pins]",
     "effects.pins.corners: pins need at least one of corners or vertices"),
    ("[effects.gravity]", "[effects.pins]\ncorners = []\nvertices = []",
     "effects.pins.corners: pins need at least one of corners or vertices"),
    ("[effects.gravity]", "[effects.pins]\nvertices = [[0, 0]]\ncorner = ['top-left']", ("unknown key(s) "
     "['effects.pins.corner']; known here: ['corners', 'vertices']")),
    # effects that need each other
    ("[effects.gravity]", "[effects.gravity]\n[[colliders]]\nmodel = 'sphere'",
     "colliders are declared but [effects.collisions] is absent; add it or remove the [[colliders]]"),
    ("[effects.gravity]", "[effects.collisions]",
     "effects.collisions needs at least one [[colliders]] entry"),
    ("[effects.gravity]", "[effects.friction]\ncoefficient = 0.3\n[[colliders]]\nmodel = 'sphere'",
     "colliders are declared but [effects.collisions] is absent; add it or remove the [[colliders]]"),
    ("[effects.gravity]", "[effects.friction]\ncoefficient = 0.3",
     "effects.friction needs effects.collisions"),
])
def test_each_invalid_value_is_refused_with_its_whole_message(tmp_path, old, new, message):
    assert old in BASE
    assert scene_error(tmp_path, BASE.replace(old, new, 1)) == message


@pytest.mark.parametrize("old, new", [
    ("width = 10", "width = 2"), ("height = 8", "height = 4096"),
    ("width = 10", "width = 4096"), ("height = 8", "height = 2"),
    ("dt_s = 1e-4", "dt_s = 0.01"),  # dt_s = duration_s: one step
    ("dt_s = 1e-4", "dt_s = 1e-4\nframe_every_steps = 1"),
    ("[effects.gravity]", "[effects.wind]\nvelocity_m_s = [1, 0, 0]\ndrag_1_s = 0"),
    ("[effects.gravity]", "[effects.friction]\ncoefficient = 0.3\nrestitution = 1.0\n" + COLLIDER),
    ("[effects.gravity]", "[effects.friction]\ncoefficient = 0.3\nrestitution = 0\n" + COLLIDER),
    ("[effects.gravity]", "[effects.pins]\nvertices = [[0, 0], [9, 7], [9, 0], [0, 7]]"),
    ("[effects.gravity]", ("[effects.pins]\ncorners = ['top-left', 'top-right', 'bottom-left', "
                          "'bottom-right']")),
])
def test_values_at_their_limits_are_accepted(tmp_path, old, new):
    assert old in BASE
    load_scene(write(tmp_path, BASE.replace(old, new, 1)))


def test_pins_keep_corners_and_vertices_as_declared(tmp_path):
    only_vertices = load_scene(write(tmp_path, BASE.replace(
        "[effects.gravity]", "[effects.pins]\nvertices = [[9, 7], [3, 0]]")))
    assert only_vertices.effects["pins"] == {"corners": [], "vertices": [[9, 7], [3, 0]]}
    both = load_scene(write(tmp_path, BASE.replace(
        "[effects.gravity]", "[effects.pins]\ncorners = ['bottom-right']\nvertices = [[0, 7]]")))
    assert both.effects["pins"] == {"corners": ["bottom-right"], "vertices": [[0, 7]]}


def test_missing_scene_file_and_bad_toml_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError) as info:
        load_scene(tmp_path / "absent.toml")
    assert str(info.value) == f"{tmp_path / 'absent.toml'}: no such scene file"
    with pytest.raises(FileNotFoundError):
        load_scene(tmp_path)  # a directory is not a scene file
    assert scene_error(tmp_path, "[scene\n").startswith("not valid TOML: ")


def stability_scene(tmp_path: Path, effects: str, dt: float = 1e-3) -> str:
    """A 3 x 3 cloth 0.5 m apart at 2 kg/m2: every vertex weighs 2 * 0.5^2 = 0.5 kg."""
    return (f"[scene]\nduration_s = 1.0\ndt_s = {dt}\n[cloth]\nwidth = 3\nheight = 3\n"
            f"spacing_m = 0.5\ndensity_kg_m2 = 2.0\n[effects]\n{effects}\n")


@pytest.mark.parametrize("effects, limits", [
    ("[effects.gravity]", {}),
    ("[effects.wind]\nvelocity_m_s = [1, 0, 0]", {"damping and wind drag": 1.0}),  # drag 1 1/s
    ("[effects.wind]\nvelocity_m_s = [1, 0, 0]\ndrag_1_s = 0\n[effects.damping]\ncoefficient_1_s = 0",
     {}),
    ("[effects.damping]\ncoefficient_1_s = 4", {"damping and wind drag": 0.25}),
    ("[effects.wind]\nvelocity_m_s = [1, 0, 0]\ndrag_1_s = 0.5\n[effects.damping]\ncoefficient_1_s = 1.5",
     {"damping and wind drag": 0.5}),  # 1 / (1.5 + 0.5)
    # springs: dt < 2 / sqrt(4 k_sum / m), m = 0.5 kg
    ("[effects.stretch]\nstiffness_n_m = 2", {"springs": 0.5}),  # 2 / sqrt(8 / 0.5)
    ("[effects.shear]\nstiffness_n_m = 2", {"springs": 0.5}),
    ("[effects.bend]\nstiffness_n_m = 2", {"springs": 0.5}),
    (("[effects.stretch]\nstiffness_n_m = 2\n[effects.shear]\nstiffness_n_m = 2\n"
     "[effects.bend]\nstiffness_n_m = 4\n[effects.damping]\ncoefficient_1_s = 2"),
     {"springs": 0.25, "damping and wind drag": 0.5}),  # 2 / sqrt(32 / 0.5)
])
def test_stability_limits_follow_their_closed_forms(tmp_path, effects, limits):
    from collider_client.sim.scene import stability_limits

    assert stability_limits(load_scene(write(tmp_path, stability_scene(tmp_path, effects)))) == limits


SPRINGS = ("[effects.stretch]\nstiffness_n_m = 2\n[effects.shear]\nstiffness_n_m = 2\n"
           "[effects.bend]\nstiffness_n_m = 4")
DRAG = "[effects.wind]\nvelocity_m_s = [1, 0, 0]\ndrag_1_s = 0.5\n[effects.damping]\ncoefficient_1_s = 1.5"


def test_dt_beyond_a_stability_limit_is_refused_with_the_numbers(tmp_path):
    # springs: the limit itself is already unstable (dt < 0.25 s); drag: the limit is allowed
    assert scene_error(tmp_path, stability_scene(tmp_path, SPRINGS, dt=0.25)) == (
        "scene.dt_s = 0.25 is unstable for these springs (vertex mass 0.5 kg from "
        "cloth.density_kg_m2, stiffness sum 8 N/m): use dt_s < 0.25, softer springs or a denser cloth")
    load_scene(write(tmp_path, stability_scene(tmp_path, SPRINGS, dt=0.2499)))
    assert scene_error(tmp_path, stability_scene(tmp_path, DRAG, dt=0.6)) == (
        "scene.dt_s = 0.6 is unstable for effects.damping.coefficient_1_s + effects.wind.drag_1_s "
        "= 2 1/s (the velocity factor 1 - rate * dt must stay >= 0): use dt_s <= 0.5 s or a "
        "smaller coefficient")
    load_scene(write(tmp_path, stability_scene(tmp_path, DRAG, dt=0.5)))
    # without wind, its default drag of 1 1/s does not count
    load_scene(write(tmp_path, stability_scene(tmp_path, "[effects.damping]\ncoefficient_1_s = 1.0",
                                               dt=1.0)))


def rotate(v, axis, angle_rad):
    """``v`` turned by ``angle_rad`` about ``axis`` (right hand), Rodrigues' formula on vectors."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    v = np.asarray(v, float)
    return (v * np.cos(angle_rad) + np.cross(k, v) * np.sin(angle_rad)
            + k * (k @ v) * (1 - np.cos(angle_rad)))


def extrinsic_xyz(rotation_deg):
    """The euler_matrix of the docs built independently: each world basis vector turned about the
    world x, then y, then z axis."""
    ax, ay, az = np.radians(rotation_deg)
    columns = [rotate(rotate(rotate(e, [1, 0, 0], ax), [0, 1, 0], ay), [0, 0, 1], az)
               for e in np.eye(3)]
    return np.column_stack(columns)


@pytest.mark.parametrize("rotation_deg", [(30, 0, 0), (0, 45, 0), (0, 0, 60), (30, -45, 120),
                                          (90, 90, 0), (-170, 20, 75)])
def test_euler_matrix_turns_about_world_x_then_y_then_z(rotation_deg):
    from collider_client.sim.motion import euler_matrix

    np.testing.assert_allclose(euler_matrix(np.array(rotation_deg, float)),
                               extrinsic_xyz(rotation_deg), atol=1e-12)


@pytest.mark.parametrize("rotation_vector_rad", [
    (0, 0, np.pi / 2), (0.5, 0, 0), (0, -0.5, 0), (0.3, -1.2, 0.5), (2.0, 2.0, 2.0), (0, 5.0, 0),
    (-1e-3, 2e-3, 3e-3), (0.1, 0.2, -0.3)])
def test_axis_angle_matrix_turns_by_the_norm_about_the_direction(rotation_vector_rad):
    from collider_client.sim.motion import axis_angle_matrix

    r = np.array(rotation_vector_rad, float)  # not unit: the angle is its norm
    matrix = axis_angle_matrix(r)
    for v in ([1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.3, -0.7, 2.0]):
        np.testing.assert_allclose(matrix @ v, rotate(v, r, np.linalg.norm(r)), atol=1e-12)


def test_axis_angle_matrix_of_tiny_and_zero_vectors():
    from collider_client.sim.motion import axis_angle_matrix

    assert np.array_equal(axis_angle_matrix(np.zeros(3)), np.eye(3))
    # 1e-15 rad about z still turns, to first order I + [r]x
    tiny = axis_angle_matrix(np.array([0.0, 0.0, 1e-15]))
    np.testing.assert_allclose([tiny[1, 0], tiny[0, 1]], [1e-15, -1e-15], rtol=1e-9, atol=0)


def test_collider_pose_of_each_motion_kind_against_independent_rotations():
    from collider_client.sim.motion import ColliderSpec, Motion, pose_function

    position = np.array([0.1, -0.2, 0.3])  # metres, world frame
    rotation_deg = np.array([90.0, 0.0, 30.0])
    base = extrinsic_xyz(rotation_deg)

    static = pose_function(ColliderSpec("m", position, rotation_deg, Motion()))
    for t in (0.0, 3.0):
        np.testing.assert_allclose(static(t)[:3, :3], base, atol=1e-12)
        np.testing.assert_allclose(static(t)[:3, 3], position)
        assert static(t)[3].tolist() == [0.0, 0.0, 0.0, 1.0]

    # velocity: turns about the world axis through the collider's origin, which moves at v
    velocity = np.array([0.5, 0.0, -0.25])
    omega_deg_s = np.array([10.0, -20.0, 30.0])
    moving = pose_function(ColliderSpec("m", position, rotation_deg, Motion(
        kind="velocity", velocity_m_s=velocity, angular_velocity_deg_s=omega_deg_s)))
    for t in (0.0, 0.5, 2.0):
        pose = moving(t)
        angle = np.radians(np.linalg.norm(omega_deg_s)) * t
        turned = np.column_stack([rotate(c, omega_deg_s, angle) for c in base.T])
        np.testing.assert_allclose(pose[:3, :3], turned, atol=1e-12)
        np.testing.assert_allclose(pose[:3, 3], position + velocity * t, atol=1e-15)
        assert pose[3].tolist() == [0.0, 0.0, 0.0, 1.0]

    # keyframes: offsets from the placement, interpolated per component, held outside the keys
    keyed = pose_function(ColliderSpec("m", position, rotation_deg, Motion(
        kind="keyframes", times_s=np.array([1.0, 3.0]),
        positions_m=np.array([[0.0, 0.0, 0.0], [2.0, 4.0, -6.0]]),
        rotations_deg=np.array([[10.0, 20.0, 30.0], [50.0, -40.0, 90.0]]))))
    for t, offset, turn in ((0.0, [0, 0, 0], [10, 20, 30]), (1.0, [0, 0, 0], [10, 20, 30]),
                            (2.0, [1, 2, -3], [30, -10, 60]), (2.5, [1.5, 3, -4.5], [40, -25, 75]),
                            (9.0, [2, 4, -6], [50, -40, 90])):
        pose = keyed(t)
        np.testing.assert_allclose(pose[:3, 3], position + offset, atol=1e-15)
        np.testing.assert_allclose(pose[:3, :3], extrinsic_xyz(turn) @ base, atol=1e-12)
        assert pose[3].tolist() == [0.0, 0.0, 0.0, 1.0]


def test_check_models_takes_a_clip_for_a_skinned_model_only(tmp_path):
    """``clip`` names a clip of a skinned model (left out: its first); on another model, or a
    name the model lacks, the refusal names the file and the key; ``time_offset_s`` and ``loop``
    apply to skinned models as to animated ones."""
    from collider_client.sim.scene import check_models
    from collider_contract import ModelInfo

    arm = ModelInfo("arm", "skinned", skeleton={"joints": ["a"], "parents": [-1], "loop": True,
                                                "clips": [{"name": "wave", "duration_s": 1.0,
                                                           "max_surface_speed": 1.0}]})
    infos = {"arm": arm, "sphere": ModelInfo("sphere", "voxel")}

    def scene(collider: str):
        text = BASE.replace("[effects.gravity]", "[effects.gravity]\n" + collider)
        return load_scene(write(tmp_path, text))

    ok = scene("[effects.collisions]\n[[colliders]]\nmodel = 'arm'\nclip = 'wave'\n"
               "time_offset_s = 0.5\nloop = false\n")
    assert ok.colliders[0].clip == "wave"
    check_models(ok, infos)
    check_models(scene("[effects.collisions]\n[[colliders]]\nmodel = 'arm'\n"), infos)
    with pytest.raises(SceneError, match=r"colliders\[0\]\.clip: model 'arm' has no clip 'run'; "
                                         r"its clips: \['wave'\]$"):
        check_models(scene("[effects.collisions]\n[[colliders]]\nmodel = 'arm'\nclip = 'run'\n"), infos)
    with pytest.raises(SceneError, match=r"colliders\[0\]\.clip: model 'sphere' is not skinned "
                                         r"\(the key applies to skinned models\)$"):
        check_models(scene(COLLIDER + "clip = 'wave'\n"), infos)
