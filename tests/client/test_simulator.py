"""The Verlet simulator: a small cloth dropped on a real (voxel) sphere stays outside it, the step
runs only the declared effects, outputs load back, and both backends give the same run."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import collider_client as cc
from collider_client.sim.run import run_scene
from collider_client.sim.scene import load_scene
from collider_client.sim.simulator import Simulator
from collider_contract.point_cache import read_pc2

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
    assert report.fields == ["distance", "contact", "collides"]
    # Every vertex of every step asked for (the cloth stays inside the sphere's inflated box).
    assert report.points_total == report.points_sent == 600 * 256
    # Colliding vertices at each frame written: the last is the run's last count.
    assert len(report.per_frame_colliding) == 13
    assert report.per_frame_colliding[-1] == report.colliding_last > 0
    # The same check through the exact mesh SDF that `--check-mesh` uses.
    import trimesh

    from collider_client.sim.motion import pose_function
    from collider_server.engine.meshes import ExactSDF, Mesh
    from collider_server.making.evaluation import exact_distance, penetration

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=SPHERE_RADIUS_M)
    exact = ExactSDF(Mesh(np.asarray(sphere.vertices), np.asarray(sphere.faces)))
    check = penetration(frames, [("sphere", exact_distance(exact), pose_function(scene.colliders[0]))])
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
    centre = lambda t: np.array([0.0, 0.0, -0.05 + 0.5 * t])
    assert sphere_depth(frames, centre) < 1e-3
    assert report.colliding_max > 20
    top = frames[-1][1][:, 2].max()
    assert top > 0.104  # lifted above where it started by the rising sphere


def test_an_animated_collider_is_met_at_the_scene_time_plus_its_time_offset(tmp_path, models_dir):
    """``time_offset_s`` = 0.25 s, a quarter of the pulsing sphere's period: the cloth falls on
    the sphere as it is 0.25 s later (radius 0.12 m at x = +0.1 at t = 0; 0.25 s earlier it is
    0.08 m at x = -0.1), and at every frame no vertex is inside that sphere beyond its 0.6 mm
    tessellation gap. An offset applied the other way (t - 0.25) leaves the falling cloth
    centimetres inside it."""
    from collider_server.making.animations import pulsing_sphere

    _, reference = pulsing_sphere()
    offset = 0.25
    path = tmp_path / "pulse.toml"
    path.write_text(DROP.format(motion=f"time_offset_s = {offset}", friction="")
                    .replace('model = "sphere"', 'model = "pulse"').replace("0.104]", "0.13]"))
    scene = load_scene(path)
    assert scene.colliders[0].time_offset_s == offset
    with cc.Client(models=models_dir, device="cpu") as client:
        report, frames = run_scene(scene, client, tmp_path / "out", show_progress=False, preview=False)
    assert report.colliding_max > 20  # the cloth met the sphere
    deepest = max(float(-reference.signed_distance(v, t + offset).min()) for t, v in frames)
    assert deepest < 0.6e-3 + 1e-4, deepest


def test_remote_and_embedded_runs_agree(tmp_path, models_dir, server_url):
    out = {}
    for backend in ("embedded", "remote"):
        args = ["--server", server_url] if backend == "remote" else ["--models", str(models_dir)]
        result = subprocess.run(
            [sys.executable, "-m", "collider_cli", "simulate",
             str(scene_file(tmp_path)), "--steps", "300", "--quiet", "--no-preview",
             "--output", str(tmp_path / backend), *args],
            capture_output=True, text=True, timeout=300)
        assert result.returncode == 0, result.stderr
        assert f"({backend} backend)" in result.stdout
        out[backend] = read_pc2(tmp_path / backend / "drop.pc2")
    np.testing.assert_allclose(out["embedded"], out["remote"], atol=1e-5)


def test_check_mesh_places_the_mesh_as_the_model_was_made(tmp_path, monkeypatch):
    """A model baked from a 1 m sphere file with --fit-size 0.2 is a 0.1 m sphere: the exact
    check must measure against the file placed the same way, not the raw 1 m sphere; so must the
    collider points drawn in the preview."""
    pytest.importorskip("collider_server", reason="the engine (server extras) is not installed")
    import trimesh

    from collider_cli import main
    from collider_client.sim import run as run_module

    seen, real_run_scene = [], run_module.run_scene

    def spy(*args, **kwargs):
        seen.append(kwargs)
        return real_run_scene(*args, **kwargs)

    monkeypatch.setattr(run_module, "run_scene", spy)
    big = tmp_path / "big.obj"
    trimesh.creation.icosphere(subdivisions=5, radius=1.0).export(big)  # 10,242 vertices
    models = tmp_path / "models"
    assert main(["bake", str(big), "--kind", "voxel", "--resolution", "48", "--name", "sphere",
                 "--fit-size", "0.2", "--models", str(models), "--quiet"]) == 0
    out = tmp_path / "out"
    code = main(["simulate", str(scene_file(tmp_path)), "--models", str(models), "--steps", "300",
                 "--no-preview", "--quiet", "--output", str(out), "--check-mesh", f"sphere={big}"])
    assert code == 0
    text = (out / "drop.report.json").read_text()
    assert text.startswith('{\n  "')  # rewritten with the check, indented as before
    check = json.loads(text)["exact_check"]
    assert check["max_depth_m"] < 1e-3  # the raw 1 m file would put every vertex ~0.9 m inside
    assert check["min_distance_m"] < 3e-3  # and the cloth did reach the sphere
    # Measured every step too: nothing crossed into the sphere, and the conservative advance
    # measured far fewer exact distances than every vertex at every step.
    assert check["crossed_points"] == 0 and check["steps"] == 299
    assert check["max_depth_at_a_step_m"] < 1e-3
    assert 256 <= check["exact_distances"] < 300 * 256 / 4
    # The preview's collider points: 4,000 distinct vertices of the file, placed as the model.
    (shown,) = seen
    points = shown["collider_points"]["sphere"]
    assert points.shape == (4000, 3) and len(np.unique(points, axis=0)) == 4000
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), SPHERE_RADIUS_M, rtol=1e-6)


# -- what a run writes: OBJ, PC2, the PNG preview ------------------------------------------------


def test_pc2_frames_reads_each_written_frame_with_its_time(tmp_path):
    from collider_client.sim.output import PC2Frames
    from collider_contract.point_cache import PC2Writer

    path = tmp_path / "a.pc2"
    frames = [np.arange(6, dtype=np.float64).reshape(2, 3) * k / 3 for k in range(3)]
    with PC2Writer(path, 2) as pc2:
        for f in frames:
            pc2.write(f)
    stored = PC2Frames(path, [0.0, 0.1, 0.2], 2)
    assert stored[-3][0] == 0.0 and stored[2][0] == 0.2  # first and last, both ways
    np.testing.assert_array_equal(stored[-3][1], frames[0].astype(np.float32))
    with pytest.raises(IndexError, match="frame 3 of 3"):
        stored[3]
    with pytest.raises(IndexError, match="frame -4 of 3"):
        stored[-4]


def _preview_cloth(width, height, spacing=0.1):
    """(W*H, 3) positions of a curved cloth, z = x^2 (metres, world frame)."""
    x, y = np.meshgrid(np.arange(width) * spacing, np.arange(height) * spacing)
    return np.stack([x, y, x ** 2], axis=-1).reshape(-1, 3)


def test_preview_has_a_panel_per_frame_with_the_colliders_at_that_frames_pose():
    from matplotlib.colors import to_rgb, to_rgba

    from collider_client.sim.output import preview_figure

    cloth = _preview_cloth(4, 3)  # x 0..0.3, y 0..0.2, z 0..0.09 m
    collider = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.05]])
    frames = {5: cloth + [0.0, 0.0, -0.2], 0: cloth}
    # A moving collider: at x + 1 m in frame 0, at z - 0.5 m in frame 5.
    shown = {0: [collider + [1.0, 0.0, 0.0]], 5: [collider + [0.0, 0.0, -0.5]]}
    fig = preview_figure(frames, 4, 3, {0: 0.0, 5: 0.05}, "drop", shown)
    assert fig.get_suptitle() == "drop" and fig._suptitle.get_fontsize() == 10
    np.testing.assert_allclose(fig.get_size_inches(), [8.4, 4.4])  # 4.2 x 4.4 in a panel
    first, second = fig.axes
    assert [ax.get_subplotspec().get_geometry() for ax in fig.axes] == [(1, 2, 0, 0), (1, 2, 1, 1)]
    assert first.get_title() == "frame 0, t = 0.000 s"
    assert second.get_title() == "frame 5, t = 0.050 s"
    # Every panel has the same cube of limits holding all cloth and collider points:
    # x 0..1.1, y 0..0.2, z -0.5..0.09, half the largest side 0.55 m.
    for ax in fig.axes:
        np.testing.assert_allclose(ax.get_xlim(), [0.55 - 0.55, 0.55 + 0.55])
        np.testing.assert_allclose(ax.get_ylim(), [0.1 - 0.55, 0.1 + 0.55])
        np.testing.assert_allclose(ax.get_zlim(), [-0.205 - 0.55, -0.205 + 0.55])
        assert [ax.xaxis.label.get_text(), ax.yaxis.label.get_text(), ax.zaxis.label.get_text()] \
            == ["x (m)", "y (m)", "z (m)"]
        assert {ax.xaxis.label.get_fontsize(), ax.yaxis.label.get_fontsize(),
                ax.zaxis.label.get_fontsize()} == {7.0}
        assert ax.title.get_fontsize() == 9.0 and ax.xaxis.get_tick_params()["labelsize"] == 6
        surface, points = ax.collections
        # The cloth: blue faces shaded by their slope (each face the base colour scaled),
        # dark blue edges; the collider: translucent red points.
        faces = surface.get_facecolor()[:, :3] / to_rgb("#4a90d9")
        np.testing.assert_allclose(faces, np.repeat(faces[:, :1], 3, axis=1), rtol=1e-6)
        assert np.ptp(faces[:, 0]) > 0.01  # shaded: the faces differ
        np.testing.assert_allclose(surface.get_edgecolor()[0, :3], to_rgb("#1f4e79"))
        assert surface.get_alpha() == 0.9 and list(surface.get_linewidth()) == [0.2]
        np.testing.assert_allclose(points.get_facecolor()[0], to_rgba("#c0392b", 0.6))
        assert points.get_alpha() == 0.6 and list(points.get_sizes()) == [1.0]
    # What each panel drew (its data limits): its own frame of the cloth, all 4 x 3 vertices,
    # and the collider at its own pose.
    np.testing.assert_allclose(first.xy_dataLim.get_points(), [[0.0, 0.0], [1.1, 0.2]])
    np.testing.assert_allclose(first.zz_dataLim.intervalx, [0.0, 0.09])
    np.testing.assert_allclose(second.xy_dataLim.get_points(), [[0.0, 0.0], [0.3, 0.2]])
    np.testing.assert_allclose(second.zz_dataLim.intervalx, [-0.5, -0.11])


def test_preview_draws_one_list_of_collider_points_in_every_panel_and_thins_a_large_cloth():
    from collider_client.sim.output import preview_figure

    # 120 x 3 vertices 0.01 m apart: drawn every second vertex (plot_surface is slow above
    # ~60 x 60 cells), so the last column drawn is x = 1.18 m, the last row y = 0.02 m.
    cloth = _preview_cloth(120, 3, spacing=0.01)
    still = np.array([[0.5, 0.0, -1.0], [0.6, 0.01, -0.9]])
    fig = preview_figure({0: cloth, 3: cloth}, 120, 3, {0: 0.0, 3: 0.3}, "t", [still])
    for ax in fig.axes:
        assert len(ax.collections) == 2  # the cloth and the one collider
        np.testing.assert_allclose(ax.xy_dataLim.get_points(), [[0.0, 0.0], [1.18, 0.02]])
        np.testing.assert_allclose(ax.zz_dataLim.intervalx, [-1.0, 1.18 ** 2])
    fig = preview_figure({0: cloth}, 120, 3, {0: 0.0}, "t")  # no colliders: the cloth only
    assert len(fig.axes[0].collections) == 1


def test_the_preview_draws_the_scenes_up_axis_vertical():
    """Issue 35: a scene with gravity along -y was drawn with z vertical, sideways. The panels'
    vertical axis is the scene's up (minus gravity's direction), the world's axis names kept."""
    from collider_client.sim.output import preview_figure, view_axes

    for up, labels in (((0, 0, 1), ["x", "y", "z"]), ((0, 1, 0), ["z", "x", "y"]),
                       ((1, 0, 0), ["y", "z", "x"]), ((0, -1, 0), ["x", "z", "-y"]),
                       ((0, 0, -1), ["y", "x", "-z"])):
        rows, names = view_axes(up)
        assert names == [f"{label} (m)" for label in labels]
        np.testing.assert_allclose(rows[2], up)
        assert np.linalg.det(rows) == pytest.approx(1.0)  # right-handed: not a mirror image
    rows, names = view_axes((0.0, 0.6, 0.8))
    np.testing.assert_allclose(rows @ rows.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rows) == pytest.approx(1.0) and names[2] == "along (0, 0.6, 0.8) (m)"
    # A cloth hanging 1 m along -y below a collider point 2 m up: with y up, the panel's
    # vertical holds the world's y.
    cloth = _preview_cloth(4, 3)[:, [0, 2, 1]] * [1.0, -10.0, 1.0]  # y from 0 down to -0.9
    fig = preview_figure({0: cloth}, 4, 3, {0: 0.0}, "y up", [np.array([[0.0, 2.0, 0.0]])],
                         up=(0.0, 1.0, 0.0))
    (ax,) = fig.axes
    assert ax.zaxis.label.get_text() == "y (m)" and ax.xaxis.label.get_text() == "z (m)"
    np.testing.assert_allclose(ax.zz_dataLim.intervalx, [-0.9, 2.0])


def test_a_scenes_up_is_minus_gravity(tmp_path):
    path = tmp_path / "up.toml"
    base = "[scene]\nduration_s = 0.01\ndt_s = 1e-3\n[cloth]\nwidth = 2\nheight = 2\nspacing_m = 0.01\n"
    path.write_text(base + "[effects.gravity]\nacceleration_m_s2 = [0.0, -9.81, 0.0]\n")
    np.testing.assert_allclose(load_scene(path).up, [0.0, 1.0, 0.0])
    path.write_text(base + "[effects.gravity]\n")  # the default: -z
    np.testing.assert_allclose(load_scene(path).up, [0.0, 0.0, 1.0])
    path.write_text(base + "[effects.damping]\ncoefficient_1_s = 1.0\n")  # no gravity: z up
    np.testing.assert_allclose(load_scene(path).up, [0.0, 0.0, 1.0])


def collider_pixels(png) -> int:
    """How many pixels of a preview PNG are the colliders' red (#c0392b over white, blended):
    red well above green and blue. The cloth is blue, the axes grey, the text black."""
    import matplotlib.image

    rgb = matplotlib.image.imread(png)[..., :3]
    return int(((rgb[..., 0] > 0.6) & (rgb[..., 0] - rgb[..., 1] > 0.15)
                & (rgb[..., 0] - rgb[..., 2] > 0.15)).sum())


@pytest.mark.parametrize("gravity", ["z", "y"])
def test_simulate_draws_the_colliders_from_the_model_in_the_png(tmp_path, models_dir, gravity):
    """Issue 35: the tour's drape picture showed no bunny (colliders were drawn only with
    --check-mesh). Without it the PNG shows the model's own surface (marching cubes of its
    distance), here the voxel sphere's, in red; with gravity along -y too (the cloth in the
    x-z plane, the picture drawn with y up)."""
    from collider_cli import main
    from collider_client.sim import run as run_module

    path = scene_file(tmp_path)
    if gravity == "y":
        text = path.read_text().replace("[effects.gravity]", "[effects.gravity]\nacceleration_m_s2 = [0.0, -9.81, 0.0]")
        path.write_text(text.replace("density_kg_m2", "axes = \"xz\"\ndensity_kg_m2")
                        .replace("[-0.075, -0.075, 0.104]", "[-0.075, 0.104, -0.075]"))
    out = tmp_path / "out"
    shown, ups = [], []
    real_run, real_write = run_module.run_scene, run_module.write_preview

    def spy(*args, **kwargs):
        shown.append(kwargs["collider_points"])
        return real_run(*args, **kwargs)

    def write_spy(*args):
        ups.append(args[-1])
        return real_write(*args)

    import unittest.mock

    with unittest.mock.patch.object(run_module, "run_scene", spy), \
            unittest.mock.patch.object(run_module, "write_preview", write_spy):
        assert main(["simulate", str(path), "--models", str(models_dir), "--steps", "20", "--quiet",
                     "--output", str(out)]) == 0
    np.testing.assert_allclose(ups[0], [0.0, 1.0, 0.0] if gravity == "y" else [0.0, 0.0, 1.0])
    points = shown[0]["sphere"]  # the model's surface, collider frame
    assert len(points) > 1000
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), SPHERE_RADIUS_M, atol=2e-3)
    assert collider_pixels(out / "drop.png") > 500


def test_write_preview_saves_a_png_of_462_x_484_pixels_a_panel(tmp_path):
    import struct

    import matplotlib.pyplot as plt

    from collider_client.sim.output import write_preview

    open_before = plt.get_fignums()
    cloth = _preview_cloth(4, 3)
    write_preview(tmp_path / "p.png", {0: cloth, 1: cloth}, 4, 3, {0: 0.0, 1: 0.1}, "t")
    data = (tmp_path / "p.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert struct.unpack(">II", data[16:24]) == (2 * 462, 484)  # 110 dpi
    assert plt.get_fignums() == open_before  # the figure is closed, not left in pyplot


# -- run_scene: steps, progress, the per-step callback, errors before the run ----------------------

FALL = ("[scene]\nduration_s = 0.05\ndt_s = 1e-3\nframe_every_steps = 10\n"
        "[cloth]\nwidth = 4\nheight = 3\nspacing_m = 0.01\n[effects.gravity]\n")


def test_run_scene_runs_the_steps_asked_with_a_progress_bar_and_calls_on_step(tmp_path, capsys):
    path = tmp_path / "fall.toml"
    path.write_text(FALL)  # 50 steps of 1 ms, a frame every 10; run for 60
    scene = load_scene(path)
    calls = []
    out = tmp_path / "a" / "b"  # made, parents too
    import time

    started = time.perf_counter()
    report, frames = run_scene(scene, None, out, steps=60,
                               on_step=lambda sim, i: calls.append((i, sim.t)))
    assert 0 < report.wall_s <= time.perf_counter() - started
    assert (report.scene, report.vertices, report.frames) == ("fall", 12, 7)
    # No colliders: nothing asked, nothing colliding.
    assert (report.fields, report.points_total, report.points_sent, report.queries,
            report.colliding_max, report.colliding_last, report.deepest_penetration_m) \
        == ([], 0, 0, 0, 0, 0, 0.0)
    assert [i for i, _ in calls] == list(range(1, 61))  # after each step, 1-based
    np.testing.assert_allclose([t for _, t in calls], np.arange(1, 61) * 1e-3)
    assert report.steps == 60 and report.backend == "embedded"
    assert [t for t, _ in frames] == pytest.approx([0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06])
    assert report.per_frame_colliding == [0] * 7  # no colliders
    assert (out / "fall.obj").read_text().splitlines()[1] == "o fall"
    assert (out / "fall.png").is_file()  # the preview is on by default
    bar = capsys.readouterr().err  # the progress bar (on by default) ends at 60 of 60 steps
    assert "fall: 100%" in bar and "60/60" in bar and ("step/s" in bar or "s/step" in bar)
    # Again into the same folder, quiet: no bar; and the scene's own 50 steps.
    report, _ = run_scene(scene, None, out, show_progress=False, preview=False)
    assert report.steps == 50 and capsys.readouterr().err == ""


def test_run_scene_refuses_before_the_run(tmp_path, models_dir, monkeypatch):
    import sys

    path = tmp_path / "fall.toml"
    path.write_text(FALL + "[effects.collisions]\n[[colliders]]\nmodel = 'teapot'\n")
    scene = load_scene(path)
    with cc.Client(models=models_dir, device="cpu") as client:
        with pytest.raises(ValueError, match=r"colliders\[0\]\.model: no model named 'teapot' "
                                             r"\(available: \['arm', 'arm-neural', 'box', 'pulse', 'pulse-voxel', 'sphere'\]\)$"):
            run_scene(scene, client, tmp_path / "out", show_progress=False)
    (tmp_path / "empty").mkdir()
    with cc.Client(models=tmp_path / "empty", device="cpu") as client:
        with pytest.raises(ValueError, match=r"no model named 'teapot' \(available: none\)$"):
            run_scene(scene, client, tmp_path / "out", show_progress=False)
    with pytest.raises(ValueError, match="the scene has colliders; a client is needed"):
        run_scene(scene, None, tmp_path / "out", show_progress=False)
    # No matplotlib: said before the run, nothing written.
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(ValueError) as info:
        run_scene(scene, None, tmp_path / "late", show_progress=False)
    assert str(info.value) == ("the PNG preview needs matplotlib (pip install matplotlib, or the "
                               "server extras); or pass --no-preview")
    assert not (tmp_path / "late").exists()


def test_physical_memory_is_this_machines():
    from collider_client.sim.run import _physical_memory

    meminfo = Path("/proc/meminfo")
    if not meminfo.is_file():
        pytest.skip("no /proc/meminfo to compare with")
    total_kib = int(meminfo.read_text().split("MemTotal:")[1].split()[0])
    assert _physical_memory() == pytest.approx(total_kib * 1024, rel=0.05)


# -- `collider simulate`: options, refusals, what it runs and prints (in process) -----------------


def simulate_parser():
    import argparse

    from collider_cli.commands.simulate import register

    parser = argparse.ArgumentParser(prog="collider")
    register(parser.add_subparsers(dest="command"))
    return parser


def simulate(*argv):
    args = simulate_parser().parse_args(["simulate", *map(str, argv)])
    return args.func(args)


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_simulate_options_defaults_and_help(capsys, monkeypatch):
    from collider_cli.commands.simulate import run_simulate
    from collider_client.sim.scene import shipped_scenes

    parser = simulate_parser()
    defaults = {"command": "simulate", "scene": "drop", "server": None, "token": None, "models": None,
                    "device": None, "threads": None, "output": Path("out"), "steps": None, "no_preview": False,
                    "quiet": False, "check_mesh": [], "check_animation": [], "view": False, "host": "127.0.0.1",
                    "port": 8080, "paused": False, "func": run_simulate}
    assert vars(parser.parse_args(["simulate", "drop"])) == defaults
    given = parser.parse_args([
        "simulate", "drop", "--server", "http://h:1", "--token", "t", "--models", "m",
        "--device", "cpu", "--threads", "3", "--output", "o", "--steps", "7", "--no-preview",
        "--quiet", "--check-mesh", "a=b", "--check-mesh", "c=d", "--check-animation", "a=e.pc2",
        "--view", "--host", "0.0.0.0",
        "--port", "9000", "--paused"])
    assert vars(given) == dict(defaults, server="http://h:1", token="t", models=Path("m"),
                               device="cpu", threads=3, output=Path("o"), steps=7, no_preview=True,
                               quiet=True, check_mesh=["a=b", "c=d"], check_animation=["a=e.pc2"],
                               view=True, host="0.0.0.0",
                               port=9000, paused=True)
    # The help: what the command writes, the shipped scenes, each default as parsed above.
    monkeypatch.setenv("COLUMNS", "1000")
    with pytest.raises(SystemExit):
        parser.parse_args(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for phrase in (
            ("Simulate a cloth scene with the reference Verlet simulator. SCENE is a TOML file or a "
            f"shipped scene name ({', '.join(shipped_scenes())}). Writes OBJ + PC2 (Blender: "
            "import the OBJ, add a Mesh Cache modifier with the PC2), a PNG preview and a report."),
            "--output OUTPUT output folder (default out/)",
            ("--threads THREADS embedded engine CPU threads (default: cores - 1, at least 1, as the "
            "server)"),
            ("--check-mesh MODEL=MESH also measure penetration of every output frame against the "
            "exact SDF of MESH (collider frame) for collider MODEL; for a skinned MODEL, MESH is its "
            "character file (glTF or USD), skinned in the scene's clip at each frame's time (the exact "
            "union at that pose); repeatable"),
            "--check-animation MODEL=CACHE with --check-mesh for an animated MODEL: its vertex cache",
            "live view (extra [view]: pip install 'neural-collider[view]'):",
            ("--view show the run live in the browser (play / pause / step); the view stays up "
            "after the run until Ctrl-C"),
            "--host HOST address the view listens on (default 127.0.0.1;",
            "--port PORT port of the view (default 8080)"):
        assert phrase in text


def test_resolve_scene_names_the_shipped_scenes_when_none_matches(tmp_path):
    from collider_client.sim.scene import SCENES_DIR, resolve_scene, shipped_scenes

    assert resolve_scene("flag_in_wind") == SCENES_DIR / "flag_in_wind.toml"
    with pytest.raises(FileNotFoundError) as info:
        resolve_scene(str(tmp_path / "nope"))
    assert str(info.value) == (f"no scene file {str(tmp_path / 'nope')!r}; shipped scenes: "
                               + ", ".join(shipped_scenes()))


def test_simulate_refuses_bad_options_before_the_run(tmp_path):
    drop = scene_file(tmp_path)  # one collider, model "sphere"
    fall = tmp_path / "fall.toml"
    fall.write_text(FALL)  # no colliders
    out = tmp_path / "out"
    with pytest.raises(ValueError, match="^--steps must be >= 1, got 0$"):
        simulate(drop, "--steps", "0", "--output", out)
    for item in ("sphere", "=m.obj", "sphere="):
        with pytest.raises(ValueError) as info:
            simulate(drop, "--check-mesh", item, "--output", out)
        assert str(info.value) == f"--check-mesh wants MODEL=MESH, got {item!r}"
    with pytest.raises(ValueError) as info:
        simulate(drop, "--check-mesh", "box=m.obj", "--output", out)
    assert str(info.value) == ("--check-mesh names model(s) ['box'] that the scene does not use; "
                               "its colliders: ['sphere']")
    with pytest.raises(ValueError, match="its colliders: none$"):
        simulate(fall, "--check-mesh", "box=m.obj", "--output", out)
    missing = tmp_path / "a=b.obj"  # MODEL is up to the first "="
    with pytest.raises(FileNotFoundError) as info:
        simulate(drop, "--check-mesh", f"sphere={missing}", "--output", out)
    assert str(info.value) == f"--check-mesh sphere={missing}: no such file"
    assert not out.exists()


class RecordingClient(cc.Client):
    """A real client that records how it was made and whether it was closed."""

    made: list = []

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.args, self.kwargs, self.closed = args, kwargs, False
        RecordingClient.made.append(self)

    def close(self):
        self.closed = True
        super().close()


@pytest.fixture
def recording_client(monkeypatch):
    RecordingClient.made = []
    monkeypatch.setattr(cc, "Client", RecordingClient)
    return RecordingClient.made


def test_simulate_embedded_run_prints_and_writes(tmp_path, models_dir, recording_client, capsys,
                                                 monkeypatch):
    import os

    import torch

    threads = torch.get_num_threads()
    out = tmp_path / "out"
    try:
        monkeypatch.setattr(os, "cpu_count", lambda: 8)
        assert simulate(scene_file(tmp_path), "--models", models_dir, "--device", "cpu",
                        "--steps", "2", "--no-preview", "--quiet", "--output", out) == 0
        printed = capsys.readouterr()
        (made,) = recording_client
        assert made.kwargs == {"models": models_dir, "device": "cpu", "threads": 7}  # cores - 1
        assert made.closed
        assert "(embedded backend)" in printed.out and printed.err == ""  # --quiet: no bar
        assert f"wrote {out / 'drop.obj'}, .pc2, .report.json\n" in printed.out
        assert json.loads((out / "drop.report.json").read_text())["steps"] == 2
        assert not (out / "drop.png").exists()
        # Core count unknown: taken as 2, so 1 thread; --threads wins over it; with the preview
        # and the progress bar.
        monkeypatch.setattr(os, "cpu_count", lambda: None)
        simulate(scene_file(tmp_path), "--models", models_dir, "--steps", "1", "--output", out)
        simulate(scene_file(tmp_path), "--models", models_dir, "--steps", "1", "--output", out,
                 "--threads", "2", "--quiet")
    finally:
        torch.set_num_threads(threads)
    printed = capsys.readouterr()
    assert [c.kwargs["threads"] for c in recording_client[1:]] == [1, 2]
    assert f"wrote {out / 'drop.obj'}, .pc2, .png, .report.json\n" in printed.out
    assert "drop: 100%" in printed.err and (out / "drop.png").is_file()
    assert re.search(r"colliding=\d+", printed.err)  # the bar shows the colliding count
    assert json.loads((out / "drop.report.json").read_text())["steps"] == 1


def test_simulate_remote_run_and_an_unreachable_server(tmp_path, server_url, recording_client,
                                                       capsys):
    out = tmp_path / "out"
    simulate(scene_file(tmp_path), "--server", server_url, "--token", "secret", "--steps", "2",
             "--no-preview", "--quiet", "--output", out)
    (made,) = recording_client
    assert made.args == (server_url,) and made.kwargs == {"token": "secret"} and made.closed
    assert "(remote backend)" in capsys.readouterr().out
    down = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(ValueError, match="cannot connect"):
        simulate(scene_file(tmp_path), "--server", down, "--no-preview", "--quiet", "--output", out)
    mesh = tmp_path / "m.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="cannot connect"):  # asked for the mesh placement
        simulate(scene_file(tmp_path), "--server", down, "--check-mesh", f"sphere={mesh}",
                 "--no-preview", "--quiet", "--output", out)
    assert [c.closed for c in recording_client] == [True, True, True]


def test_simulate_view_shows_the_run_and_stays_up(tmp_path, models_dir, monkeypatch, capsys):
    """--view: the view on the given port follows the run to its last step, then stays up
    (here: the wait for Ctrl-C records what it was given and stops the view at once)."""
    pytest.importorskip("viser")
    from collider_cli.views import page as view_module
    from collider_client.sim import run as run_module

    waited, seen = [], []
    monkeypatch.setattr(view_module, "wait_until_interrupted",
                        lambda server, message: (waited.append((server, message)), server.stop()))
    real_run_scene = run_module.run_scene

    def spy(*args, **kwargs):
        seen.append(kwargs)
        return real_run_scene(*args, **kwargs)

    monkeypatch.setattr(run_module, "run_scene", spy)
    port = free_port()
    assert simulate(scene_file(tmp_path), "--models", models_dir, "--device", "cpu", "--view",
                    "--port", port, "--steps", "3", "--no-preview", "--quiet",
                    "--output", tmp_path / "out") == 0
    url = f"http://127.0.0.1:{port}/"
    assert f"view at {url}  (Ctrl-C to stop)" in capsys.readouterr().out
    ((server, message),) = waited
    assert server.get_port() == port
    assert message == f"run finished; the view stays at {url} (Ctrl-C to stop)"
    controls = seen[0]["on_step"].__self__
    assert controls.status.content.startswith("**step 3 / 3**")  # shown to the last step
    assert controls.play.label == "finished"
    assert len(controls.view.colliders.handles) == 1  # the sphere, drawn through the client


def test_start_live_view_paused_and_the_view_closed_when_the_run_fails(tmp_path, models_dir,
                                                                        monkeypatch):
    import argparse

    pytest.importorskip("viser")
    from collider_cli.commands.simulate import start_live_view
    from collider_cli.views import page as view_module

    fall = tmp_path / "fall.toml"
    fall.write_text(FALL)
    port = free_port()
    args = argparse.Namespace(host="127.0.0.1", port=port, steps=None, paused=True)
    server, on_step = start_live_view(args, load_scene(fall), None)
    try:
        assert server.get_port() == port
        controls = on_step.__self__
        assert controls.play.label == "play"  # paused: the button starts the run
        assert controls.status.content.startswith("**step 0 / 50**")  # the scene's 50 steps
        assert controls.view.colliders.handles == []
    finally:
        server.stop()
    # A server that is down: the view started for the run is stopped again.
    started, real_start_server = [], view_module.start_server

    def start_server(host, port):
        server = real_start_server(host, port)
        stop = server.stop
        server.stop = lambda: (started.append("stopped"), stop())
        started.append(server)
        return server

    monkeypatch.setattr(view_module, "start_server", start_server)
    with pytest.raises(ValueError, match="cannot connect"):  # said before the view opens
        simulate(scene_file(tmp_path), "--server", f"http://127.0.0.1:{free_port()}", "--view",
                 "--port", free_port(), "--no-preview", "--quiet", "--output", tmp_path / "out")
    assert started == []
    # The run refused after the view opened (a model the repository lacks): the view is stopped.
    teapot = tmp_path / "teapot.toml"
    teapot.write_text(FALL + "[effects.collisions]\n[[colliders]]\nmodel = 'teapot'\n")
    with pytest.raises(ValueError, match=r"colliders\[0\]\.model: no model named 'teapot'"):
        simulate(teapot, "--models", models_dir, "--device", "cpu", "--view", "--port", free_port(),
                 "--no-preview", "--quiet", "--output", tmp_path / "out")
    assert started[1:] == ["stopped"]


# -- quad faces, the run report and the exact --check-mesh measurement, from known inputs --------


def test_quad_faces_of_a_4_by_3_grid_are_listed_row_by_row_counter_clockwise():
    from collider_client.sim.cloth import grid_positions, quad_faces

    # Vertices (flat index r * W + c):  8  9 10 11  /  4  5  6  7  /  0  1  2  3  (row 0 at the bottom)
    faces = quad_faces(4, 3)
    assert faces.dtype == np.int64
    np.testing.assert_array_equal(faces, [[0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6],
                                          [4, 5, 9, 8], [5, 6, 10, 9], [6, 7, 11, 10]])
    # Counter-clockwise seen from +normal (+z for an "xy" cloth): each corner turns left.
    p = grid_positions(4, 3, 0.01, np.zeros(3), "xy").reshape(-1, 3)[faces]
    turn = np.cross(np.roll(p, -1, axis=1) - p, np.roll(p, -2, axis=1) - np.roll(p, -1, axis=1))
    np.testing.assert_allclose(turn[..., 2], 1e-4)  # spacing^2 at every corner of every quad
    np.testing.assert_allclose(turn[..., :2], 0.0)


def run_report(**kwargs):
    from collider_client.sim.simulator import RunReport, Timings

    values = {"scene": "drop", "backend": "embedded", "vertices": 6, "steps": 4, "dt_s": 2e-4, "frames": 3,
                  "effects": ["gravity", "stretch", "collisions"], "fields": ["distance", "contact"],
                  "wall_s": 0.2, "timings": Timings(integration_s=0.08, collision_s=0.04, query_s=0.02),
                  "points_total": 200, "points_sent": 25, "queries": 7, "colliding_max": 5, "colliding_last": 3,
                  "deepest_penetration_m": -0.0025}
    values.update(kwargs)
    return RunReport(**values)


def test_run_report_times_per_step_are_the_sums_over_the_steps_in_ms():
    ms = run_report().per_step_ms()
    assert ms == pytest.approx({"total": 50.0, "integration": 20.0, "collision": 10.0,
                                "query": 5.0}, rel=1e-12)
    # One step: the sums themselves; no step at all: the sums too, not a division by zero.
    for steps in (1, 0):
        assert run_report(steps=steps).per_step_ms() == pytest.approx(
            {"total": 200.0, "integration": 80.0, "collision": 40.0, "query": 20.0}, rel=1e-12)


def test_run_report_text_states_each_figure():
    lines = run_report().text().split("\n")
    assert lines == [
        "scene            drop  (embedded backend)",
        "cloth            6 vertices, 4 steps of 0.0002 s, 3 frames written",
        "effects          gravity, stretch, collisions",
        "fields asked     distance, contact",
        ("time per step    50.000 ms = integration 20.000 + collision 10.000 + query "
        "(engine/transport) 5.000 ms"),
        "points sent      25 of 200 (12.5 %) in 7 queries",
        "colliding        max 5, at the end 3 vertices",
        "deepest penetration (reported by the collider, before projection) 2.500 mm",
    ]
    # No collisions: no fields, no points; a collider that was never entered: 0 mm deep.
    text = run_report(fields=[], points_total=0, points_sent=0, queries=0,
                      deepest_penetration_m=0.004, exact_check={"max_depth_m": 0.0}).text()
    assert "fields asked     none (no collisions)\n" in text
    assert "points sent      0 of 0 (0.0 %) in 0 queries" in text
    assert text.split("\n")[-2].endswith(" 0.000 mm")
    assert text.split("\n")[-1] == "exact check      deepest vertex 0.000 mm inside the exact mesh"  # words, not a dict
    assert "(100.0 %)" in run_report(points_total=1, points_sent=1).text()
    # False contacts (the collider answered deeper than a vertex could have gone): said.
    assert run_report(false_contacts=7).text().split("\n")[-1] == (
        "false contacts   7 answered deeper than their vertex could have gone in its step (the "
        "collider's error): not responded, each vertex went on as if unanswered")


def test_run_report_dict_carries_the_timings_and_the_per_step_times():
    d = run_report().to_dict()
    assert d["timings_s"] == {"integration_s": 0.08, "collision_s": 0.04, "query_s": 0.02}
    assert d["time_per_step_ms"]["total"] == pytest.approx(50.0)
    assert "timings" not in d and d["effects"] == ["gravity", "stretch", "collisions"]
    assert json.loads(json.dumps(d))["deepest_penetration_m"] == -0.0025


def _spec(model, position=(0.0, 0.0, 0.0), velocity=None):
    from collider_client.sim.motion import ColliderSpec, Motion

    motion = Motion() if velocity is None else Motion("velocity", np.asarray(velocity, float))
    return ColliderSpec(model, np.asarray(position, float), np.zeros(3), motion)


def _box_exact(size_m: float):
    import trimesh

    from collider_server.engine.meshes import ExactSDF, Mesh

    box = trimesh.creation.box(extents=(size_m,) * 3)
    return ExactSDF(Mesh(np.asarray(box.vertices), np.asarray(box.faces)))


def test_exact_penetration_measures_each_placed_collider_at_each_frame():
    """Box of 0.2 m (faces at +-0.1 m in its frame), exact. Colliders, in order: ``box`` at
    x = 1 m rising at 1 m/s along z, ``box`` again at x = 5 m (nothing near it). Depths in
    metres, world frame."""
    pytest.importorskip("collider_server", reason="the engine (server extras) is not installed")
    from collider_client.sim.motion import pose_function
    from collider_server.making.evaluation import exact_distance, penetration

    box = exact_distance(_box_exact(0.2))
    colliders = [("box", box, pose_function(_spec("box", (1.0, 0.0, 0.0), velocity=(0.0, 0.0, 1.0)))),
                 ("box", box, pose_function(_spec("box", (5.0, 0.0, 0.0))))]
    frames = [
        (0.0, np.array([[1.0, 0.0, 0.05], [3.0, 0.0, 0.0]], np.float32)),  # 0.05 m deep at t = 0
        (0.5, np.array([[1.0, 0.0, 0.5], [3.0, 0.0, 0.0]], np.float32)),   # the box's centre then
    ]
    check = penetration(frames, colliders)
    assert check["by_model"] == {"box": pytest.approx(0.1, abs=1e-6)}
    assert check["max_depth_m"] == pytest.approx(0.1, abs=1e-6)
    assert check["min_distance_m"] == pytest.approx(-0.1, abs=1e-6)
    assert check["frames"] == 2
    # Only outside: no depth, and the closest distance is how near the cloth came (0.02 m).
    outside = [(0.0, np.array([[1.0, 0.0, 0.12]])), (0.5, np.array([[1.0, 0.0, 0.65]]))]
    check = penetration(outside, colliders)
    assert check["max_depth_m"] == 0.0 and check["by_model"] == {"box": 0.0}
    assert check["min_distance_m"] == pytest.approx(0.02, abs=1e-6)
    # A scaled pose (a 2 m box under scale 0.1 is the 0.2 m box): depths in world metres.
    scaled = np.diag([0.1, 0.1, 0.1, 1.0])
    scaled[:3, 3] = (1.0, 0.0, 0.0)
    check = penetration([(0.0, np.array([[1.0, 0.0, 0.05]]))],
                        [("box", exact_distance(_box_exact(2.0)), lambda t: scaled)])
    assert check["max_depth_m"] == pytest.approx(0.05, abs=1e-6)


def test_surface_crossings_count_a_point_that_passes_through_a_thin_plate_between_frames():
    """Issue 35: a cloth that falls through a thin part and ends outside again showed no depth
    at the written frames. A point falls 1 mm a step through a plate 4 mm thick (z in
    [-2, 2] mm; its frame and the world's): outside before it and after it, inside for four
    steps. The per-step check counts it as crossed, and the one that stays above is not; the
    resting one is measured again only when it could have reached the plate."""
    pytest.importorskip("collider_server", reason="the engine (server extras) is not installed")
    import trimesh

    from collider_server.engine.meshes import ExactSDF, Mesh
    from collider_server.making.evaluation import SurfaceCrossings, exact_distance, penetration

    plate = trimesh.creation.box(extents=(0.2, 0.2, 0.004))
    colliders = [("plate", exact_distance(ExactSDF(Mesh(np.asarray(plate.vertices), np.asarray(plate.faces)))),
                  lambda t: np.eye(4))]
    crossings = SurfaceCrossings(colliders)
    steps = []
    for i in range(13):  # z from +6 mm down to -6 mm, 1 mm a step; the other point rests at +3 mm
        points = np.array([[0.0, 0.0, 0.006 - 0.001 * i], [0.05, 0.0, 0.003]])
        crossings.step(i * 1e-3, points, [0.0])
        steps.append((i * 1e-3, points))
    result = crossings.result()
    assert result["crossed_points"] == 1 and result["crossed_by_model"] == {"plate": 1}
    assert result["inside_at_end"] == 0  # it left the plate below: outside again
    assert result["max_depth_at_a_step_m"] == pytest.approx(0.002, abs=1e-9)
    assert result["steps"] == 12
    # The resting point (1 mm from the plate, still): measured once, not every step; the falling
    # one about every other step (1 mm a step against its distance).
    assert result["exact_distances"] < 2 + 12
    # The written frames, first and last alone, see nothing: both outside.
    assert penetration([steps[0], steps[-1]], colliders)["max_depth_m"] == 0.0
    # A surface that moves (its bound given) makes the still point measured again.
    moving = SurfaceCrossings(colliders)
    for i in range(5):
        moving.step(i * 1e-3, np.array([[0.05, 0.0, 0.003]]), [0.6e-3])
    assert moving.result()["exact_distances"] == 3  # steps 0, 2 and 4: 2 x 0.6 mm >= its 1 mm


def test_exact_penetration_without_meshes_measures_nothing():
    pytest.importorskip("collider_server", reason="the engine (server extras) is not installed")
    from collider_server.making.evaluation import penetration

    assert penetration([(0.0, np.zeros((1, 3)))], []) == {
        "max_depth_m": 0.0, "min_distance_m": float("inf"), "frames": 1, "by_model": {}}


def test_preview_draws_a_moving_collider_at_each_frames_pose(tmp_path, models_dir, monkeypatch):
    from collider_client.sim import run as run_module

    drawn, real_write_preview = [], run_module.write_preview

    def spy(path, frames, width, height, times_s, title, collider_points=None, up=(0.0, 0.0, 1.0)):
        drawn.append((times_s, collider_points))
        return real_write_preview(path, frames, width, height, times_s, title, collider_points, up)

    monkeypatch.setattr(run_module, "write_preview", spy)
    # The sphere rises at 0.5 m/s and turns at 90 deg/s about z: frames every 50 steps of 0.2 ms.
    motion = ("position_m = [0.0, 0.0, -0.05]\nmotion = { kind = 'velocity', "
              "velocity_m_s = [0.0, 0.0, 0.5], angular_velocity_deg_s = [0.0, 0.0, 90.0] }")
    scene = load_scene(scene_file(tmp_path, motion=motion))
    points = np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.1]])  # collider frame
    with cc.Client(models=models_dir, device="cpu") as client:
        run_scene(scene, client, tmp_path / "out", show_progress=False, steps=100,
                  collider_points={"sphere": points})
    ((times_s, shown),) = drawn
    assert times_s == pytest.approx({0: 0.0, 2: 0.02})  # preview_frames [0, -1] of 3 frames
    for i, t in times_s.items():
        turn = np.radians(90.0 * t)
        expected = np.array([[0.1 * np.cos(turn), 0.1 * np.sin(turn), -0.05 + 0.5 * t],
                             [0.0, 0.0, 0.1 - 0.05 + 0.5 * t]])
        (placed,) = shown[i]
        np.testing.assert_allclose(placed, expected, atol=1e-12)


def test_run_report_gives_the_deepest_penetration_seen(tmp_path, models_dir):
    # A 4 x 3 cloth 1 cm apart starting inside the 0.1 m sphere, its row y = 0 at z = 0.09 m:
    # the first query finds its centre vertices about 1 cm deep.
    path = tmp_path / "inside.toml"
    path.write_text("[scene]\nduration_s = 2e-4\ndt_s = 2e-4\n[cloth]\nwidth = 4\nheight = 3\n"
                    "spacing_m = 0.01\norigin_m = [-0.015, -0.01, 0.09]\n[[colliders]]\n"
                    "model = 'sphere'\n[effects.collisions]\neps_m = 1e-3\n")
    with cc.Client(models=models_dir, device="cpu") as client:
        report, frames = run_scene(load_scene(path), client, tmp_path / "out", show_progress=False,
                                   preview=False)
    deepest = -(SPHERE_RADIUS_M - np.linalg.norm(frames[0][1], axis=1).min())
    assert report.deepest_penetration_m == pytest.approx(deepest, abs=2e-3)  # voxel model
    assert report.deepest_penetration_m < -5e-3


ON_ARM = """
[scene]
name = "cloth on the skinned arm"
duration_s = 0.15
dt_s = 1e-3
frame_every_steps = 10
preview_frames = [0, -1]

[cloth]
width = 12
height = 12
spacing_m = 0.012
origin_m = [0.30, -0.066, 0.047]
density_kg_m2 = 0.5

[[colliders]]
model = "arm"
clip = "{clip}"

[effects.gravity]
[effects.stretch]
stiffness_n_m = 40.0
[effects.shear]
stiffness_n_m = 10.0
[effects.damping]
coefficient_1_s = 1.0
[effects.collisions]
eps_m = 1e-3
"""


@pytest.mark.parametrize("clip", ["wave", "reach"])
def test_a_cloth_on_a_skinned_arm_is_never_deeper_than_a_tenth_of_a_millimetre(tmp_path, models_dir,
                                                                               clip):
    """A small cloth falls on the forearm of the skinned arm while ``clip`` moves it for 0.15 s
    (150 steps): at every output frame no vertex is deeper than 0.1 mm inside the exact skinned
    surface at that frame's time in that clip (asked of the engine directly), and the arm met
    the cloth."""
    from collider_contract import SkeletonPose
    from collider_server.making.skinned import skinned_arm, skinned_collider

    path = tmp_path / "arm.toml"
    path.write_text(ON_ARM.format(clip=clip))
    scene = load_scene(path)
    with cc.Client(models=models_dir, device="cpu") as client:
        report, frames = run_scene(scene, client, tmp_path / "out", show_progress=False, preview=False)
    assert report.colliding_max > 20 and len(frames) == 16
    exact = skinned_collider(skinned_arm(), "arm")
    deepest = max(float(-exact.evaluate_at(np.asarray(v, np.float64), False, t,
                                           SkeletonPose(clip=clip))[0].min()) for t, v in frames)
    assert deepest < 1e-4, f"{1e3 * deepest:.3f} mm inside"


def test_the_png_draws_a_skinned_collider_in_its_clip_at_the_panels_time(models_dir):
    """``collider simulate``'s picture asks a skinned model in the scene's clip at each panel's
    time: the arm's surface at 0.9 s in "reach" lies on the exact "reach" pose (within the
    48^3 grid's marching cubes) and far from the "wave" pose at that time."""
    from collider_cli.commands.simulate import model_surfaces
    from collider_client.sim.motion import ColliderSpec, Motion
    from collider_contract import SkeletonPose
    from collider_server.making.skinned import skinned_arm, skinned_collider

    spec = ColliderSpec("arm", np.zeros(3), np.zeros(3), Motion(), clip="reach")
    with cc.Client(models=models_dir, device="cpu") as client:
        points = model_surfaces(client, [spec])["arm"](0.9)
    exact = skinned_collider(skinned_arm(), "arm")

    def off(clip):
        distance = exact.evaluate_at(np.asarray(points, np.float64), False, 0.9, SkeletonPose(clip=clip))[0]
        return float(np.abs(distance).mean())

    assert len(points) > 500
    assert off("reach") < 2e-3 and off("wave") > 5 * off("reach")


ON_CYLINDER = """
[scene]
name = "cloth on the bending cylinder"
duration_s = 0.3
dt_s = 1e-3
frame_every_steps = 30

[cloth]
width = 10
height = 10
spacing_m = 0.02
origin_m = [-0.09, 0.1, 0.12]
axes = "xy"
density_kg_m2 = 0.5

[[colliders]]
model = "cylinder"
clip = "animation 0"
time_offset_s = {offset}

[effects.gravity]
[effects.stretch]
stiffness_n_m = 40.0
[effects.damping]
coefficient_1_s = 1.0
[effects.collisions]
eps_m = 1e-3
"""


def test_check_mesh_of_a_skinned_model_measures_each_frame_against_its_character_at_that_time(tmp_path):
    """``collider simulate --check-mesh MODEL=CHARACTER`` of a skinned model (the public
    RiggedSimple glTF, its upper half bending down over the clip): each written frame is measured
    against the character file's exact skin in the scene's clip at the frame's animation time
    (time offset included), as an independent evaluation (the file read and posed here, then the
    exact skinned kind's distance at each frame of the PC2) finds; the cloth reached the cylinder
    and nothing went inside."""
    from collider_cli import main
    from collider_contract import SkeletonPose
    from collider_server.making.characters import skinned_from_file
    from collider_server.making.placement import MeshPlacement

    sample = Path(__file__).parents[1] / "data" / "gltf" / "RiggedSimple.gltf"
    models, out = tmp_path / "models", tmp_path / "out"
    assert main(["bake", str(sample), "--kind", "skinned", "--name", "cylinder", "--fit-size", "1.0",
                 "--models", str(models), "--quiet"]) == 0
    scene = tmp_path / "cylinder.toml"
    scene.write_text(ON_CYLINDER.format(offset=0.6))
    assert main(["simulate", str(scene), "--models", str(models), "--no-preview", "--quiet", "--output", str(out),
                 "--check-mesh", f"cylinder={sample}"]) == 0
    check = json.loads((out / "cylinder.report.json").read_text())["exact_check"]
    exact, _, _ = skinned_from_file(sample, "cylinder", MeshPlacement(fit_size=1.0), loop=False)
    frames = read_pc2(out / "cylinder.pc2")
    distances = [exact.evaluate_at(frame.astype(np.float64), False, 0.6 + 0.03 * k,
                                   SkeletonPose(clip="animation 0"))[0] for k, frame in enumerate(frames)]
    assert check["frames"] == len(frames) == 11
    assert check["min_distance_m"] == pytest.approx(min(d.min() for d in distances), abs=1e-9)
    assert check["min_distance_m"] < 3e-3  # the cloth lies on the cylinder ...
    assert check["max_depth_m"] < 1e-4 and check["crossed_points"] == 0  # ... and never went inside
    # The same frames against the pose at the clip's start are not what was measured: it moved.
    still = min(exact.evaluate_at(frame.astype(np.float64), False, 0.0, SkeletonPose(clip="animation 0"))[0].min()
                for frame in frames[3:])
    assert abs(still - min(d.min() for d in distances[3:])) > 5e-3


def test_check_mesh_of_a_skinned_model_refuses_a_vertex_cache_or_another_character(capsys, tmp_path):
    from collider_cli import main

    sample = Path(__file__).parents[1] / "data" / "gltf" / "RiggedSimple.gltf"
    models = tmp_path / "models"
    assert main(["bake", str(sample), "--kind", "skinned", "--name", "cylinder", "--models", str(models),
                 "--quiet"]) == 0
    scene = tmp_path / "cylinder.toml"
    scene.write_text(ON_CYLINDER.format(offset=0.0))
    capsys.readouterr()
    assert main(["simulate", str(scene), "--models", str(models), "--steps", "2", "--no-preview", "--quiet",
                 "--output", str(tmp_path / "out"), "--check-mesh", f"cylinder={sample}",
                 "--check-animation", "cylinder=a.pc2"]) == 2
    err = capsys.readouterr().err
    assert "--check-animation cylinder: the model is skinned; its character file" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
