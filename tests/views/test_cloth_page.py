"""The cloth views in process (collider_cli.views.cloth): the live view of
``collider simulate --view`` and the replay of ``collider view --replay``, built on a real viser
server, fed by the real simulator and the real SDK (embedded engine), driven as the browser
would (their controls' callbacks), and compared with values computed here by other means.

The scene: a 9 x 9 cloth, 2 cm apart, held 0.5 mm above ``ball`` (a sphere of radius 10 cm,
voxel collider) which rises, slides and turns: the colliders must be drawn where their pose
puts them at the time shown. World frame, metres, seconds.
"""

from __future__ import annotations

import itertools
import struct
import threading
import time

import numpy as np
import pytest

from .page_driver import click, interrupt_once_printed, node, pose_of

pytest.importorskip("viser", reason="the [view] extra (viser) is not installed")

RADIUS = 0.1
DT = 1e-3
SCENE = f"""
[scene]
name = "ball rising under a cloth"
duration_s = 0.012
dt_s = {DT}
frame_every_steps = 5

[cloth]
width = 9
height = 9
spacing_m = 0.02
origin_m = [-0.08, -0.08, {RADIUS + 5e-4}]
axes = "xy"
density_kg_m2 = 0.3

[[colliders]]
model = "ball"
position_m = [0.0, 0.0, 0.0]
rotation_deg = [0.0, 0.0, 30.0]
motion = {{ kind = "velocity", velocity_m_s = [0.5, 0.0, 0.3], angular_velocity_deg_s = [0.0, 0.0, 900.0] }}

[effects.gravity]

[effects.collisions]
eps_m = 1e-3
"""
FALLING = """
[scene]
name = "a falling cloth"
duration_s = 0.003
dt_s = 1e-3
frame_every_steps = 1

[cloth]
width = 3
height = 2
spacing_m = 0.1
origin_m = [0.0, 0.0, 1.0]
axes = "xz"
density_kg_m2 = 0.3

[effects.gravity]
"""


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """(ball collider, SDK client on its model repository, model infos, scene, scene file)."""
    import trimesh

    import collider_client as cc
    from collider_client.sim.scene import load_scene
    from collider_server.engine.meshes import Mesh
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider

    root = tmp_path_factory.mktemp("cloth-view")
    tri = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)
    mesh = Mesh(np.asarray(tri.vertices, np.float64), np.asarray(tri.faces, np.int64), "ball")
    collider = bake_collider(mesh, "voxel", "ball", resolution=24, show_progress=False, device="cpu")
    save_collider(collider, root / "models" / "ball.safetensors")
    path = root / "ball.rising.toml"  # a dot in the name: outputs are ball.rising.obj, ...
    path.write_text(SCENE)
    with cc.Client(models=root / "models", device="cpu") as client:
        infos = {m.name: m for m in client.list_models()}
        yield collider, client, infos, load_scene(path), root


@pytest.fixture(scope="module")
def server():
    from collider_cli.views.page import start_server

    server = start_server("127.0.0.1", 0)
    yield server
    server.stop()


def rest_of(scene) -> np.ndarray:
    from collider_client.sim.cloth import grid_positions

    c = scene.cloth
    return grid_positions(c.width, c.height, c.spacing_m, c.origin_m, c.axes).reshape(-1, 3)


def pose_at(t: float) -> np.ndarray:
    """The ball's pose at ``t`` by hand: turned 30 deg + 900 deg/s about z, moved (0.5, 0, 0.3) m/s."""
    angle = np.radians(30.0 + 900.0 * t)
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    pose[:3, 3] = np.array([0.5, 0.0, 0.3]) * t
    return pose


def assert_ball_at(server, t: float) -> None:
    np.testing.assert_allclose(pose_of(node(server, "/colliders/0_ball")), pose_at(t), atol=1e-6)


def assert_cloth_shows(server, vertices: np.ndarray, colliding: np.ndarray | None) -> None:
    np.testing.assert_array_equal(node(server, "/cloth").vertices, vertices.astype(np.float32))
    dots = node(server, "/colliding")
    if colliding is None or not colliding.any():
        assert dots.visible is False
        return
    assert dots.visible
    # Exactly the colliding rows (stored at viser's float16 point precision), all red.
    np.testing.assert_array_equal(dots.points, vertices[colliding].astype(np.float16))
    assert dots.colors.shape == (int(colliding.sum()), 3) and np.all(dots.colors == [230, 30, 30])


# -- the parts -----------------------------------------------------------------------------------


def test_triangles_split_each_quad_in_two():
    from collider_cli.views.cloth import triangles

    # A 3 x 2 grid (rows of 3): quads (0 1 4 3) and (1 2 5 4), each split along its 0-2 diagonal.
    t = triangles(3, 2)
    assert t.dtype == np.uint32
    assert t.tolist() == [[0, 1, 4], [1, 2, 5], [0, 4, 3], [1, 5, 4]]
    assert triangles(9, 9).shape == (2 * 8 * 8, 3)


def test_pose_parts_of_a_similarity():
    from collider_cli.views.cloth import _pose_parts

    pose = np.eye(4)
    pose[:3, :3] = 2.0 * np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 deg about z
    pose[:3, 3] = [1.0, 2.0, 3.0]
    wxyz, position, scale = _pose_parts(pose)
    half = np.sqrt(0.5)
    np.testing.assert_allclose(np.abs(wxyz), [half, 0, 0, half], atol=1e-12)
    assert wxyz[0] * wxyz[3] > 0  # +90 deg, not -90
    np.testing.assert_allclose(position, [1.0, 2.0, 3.0])
    assert scale == pytest.approx(2.0)
    # A degenerate (zero) linear part: scale 1, not a division by zero.
    assert _pose_parts(np.diag([0.0, 0.0, 0.0, 1.0]))[2] == 1.0


def test_collider_surface_through_the_client(world, monkeypatch):
    """The ball's zero level set in its own frame, through the SDK: the same as marching cubes of
    the collider's own distances on a 48^3 grid over its domain, about 10 cm from its centre."""
    import dataclasses
    import sys

    from collider_cli.views.cloth import collider_surface_via_client
    from collider_server.making.surface import distance_grid, level_surface

    collider, client, infos, _, _ = world
    info = infos["ball"]
    verts, faces = collider_surface_via_client(client, info)
    assert verts.dtype == np.float32 and faces.dtype == np.uint32
    grid = distance_grid(lambda p: collider.query(p, ["distance"]).distance,
                         collider.domain_min, collider.domain_max, 48)
    expected_verts, expected_faces = level_surface(grid)
    np.testing.assert_allclose(verts, expected_verts, atol=1e-6)
    np.testing.assert_array_equal(faces, expected_faces)
    np.testing.assert_allclose(np.linalg.norm(verts, axis=1), RADIUS, atol=2e-3)
    coarse = collider_surface_via_client(client, info, resolution=12)
    assert len(coarse[1]) < len(faces) / 10
    # Whatever the client asks by default: the surface asks for distances.
    import collider_client as cc

    _, _, _, _, root = world
    with cc.Client(models=root / "models", device="cpu", fields=["collides"]) as collides_only:
        np.testing.assert_array_equal(collider_surface_via_client(collides_only, info)[1], faces)
    # A domain that the surface does not cross: nothing to draw.
    outside = dataclasses.replace(info, domain_min=np.array([0.2, 0.2, 0.2]),
                                  domain_max=np.array([0.3, 0.3, 0.3]))
    assert collider_surface_via_client(client, outside) is None
    monkeypatch.setitem(sys.modules, "skimage", None)  # without scikit-image: no surface
    assert collider_surface_via_client(client, info) is None


# -- the cloth view ------------------------------------------------------------------------------


def test_cloth_view_draws_the_cloth_its_colliding_vertices_and_the_colliders(world, server):
    from collider_cli.views.cloth import ClothView, triangles

    _, client, infos, scene, _ = world
    rest = rest_of(scene)
    view = ClothView(server, scene, rest, client, infos)
    cloth = node(server, "/cloth")
    np.testing.assert_array_equal(cloth.vertices, rest.astype(np.float32))
    np.testing.assert_array_equal(cloth.faces, triangles(9, 9))
    assert tuple(cloth.color) == (70, 130, 200) and cloth.side == "double"
    dots = node(server, "/colliding")
    assert dots.visible is False and dots.point_shape == "circle"
    assert dots.point_size == pytest.approx(2.5 * 0.02)
    ball = node(server, "/colliders/0_ball")
    assert tuple(ball.color) == (200, 200, 190) and ball.side == "double"
    np.testing.assert_allclose(np.linalg.norm(ball.vertices, axis=1), RADIUS, atol=2e-3)
    assert_ball_at(server, 0.0)
    # The camera frames the cloth and the ball's domain box at its start pose.
    corners = infos["ball"].domain_corners() @ pose_at(0.0)[:3, :3].T
    lo = np.minimum(rest.min(axis=0), corners.min(axis=0))
    hi = np.maximum(rest.max(axis=0), corners.max(axis=0))
    np.testing.assert_allclose(server.initial_camera.look_at, 0.5 * (lo + hi), atol=1e-9)
    # A frame: the cloth moved, some vertices colliding (not the first ones), the ball later.
    moved = rest + np.array([0.0, 0.0, -0.01]) * np.arange(len(rest))[:, None] / len(rest)
    colliding = np.zeros(len(rest), bool)
    colliding[[40, 41, 49, 80]] = True
    view.show(moved, 0.01, colliding)
    assert_cloth_shows(server, moved, colliding)
    assert_ball_at(server, 0.01)
    view.show(rest, 0.004, np.zeros(len(rest), bool))  # none colliding: the red points go
    assert_cloth_shows(server, rest, None)
    assert_ball_at(server, 0.004)
    view.show(moved, 0.002, colliding)
    view.show(moved, 0.003, None)  # no collision answer at all (a scene without colliders)
    assert_cloth_shows(server, moved, None)


def test_cloth_view_without_client_or_model_draws_no_collider(world):
    from collider_cli.views.cloth import ClothView
    from collider_cli.views.page import start_server

    _, client, _, scene, _ = world
    for client_, infos_ in ((None, None), (client, {}), (client, None)):
        server = start_server("127.0.0.1", 0)
        try:
            view = ClothView(server, scene, rest_of(scene), client_, infos_)
            assert view.colliders.handles == [] and server.scene.get_handle_by_name("/colliders/0_ball") is None
            # Framed on the cloth alone.
            rest = rest_of(scene)
            np.testing.assert_allclose(server.initial_camera.look_at,
                                       0.5 * (rest.min(axis=0) + rest.max(axis=0)), atol=1e-9)
        finally:
            server.stop()


def test_colliders_are_named_by_their_place_in_the_scene(world, server):
    """Two colliders of one model: each its own node (index and model), each at its own pose."""
    import copy

    from collider_cli.views.cloth import Colliders
    from collider_client.sim.motion import pose_function

    _, client, infos, scene, _ = world
    two = copy.deepcopy(scene)
    second = copy.deepcopy(scene.colliders[0])
    second.position_m = np.array([0.0, 0.5, 0.0])
    two.colliders.append(second)
    colliders = Colliders.add(server, two, client, infos)
    assert len(colliders.handles) == 2
    colliders.place(0.006)
    np.testing.assert_allclose(pose_of(node(server, "/colliders/1_ball")),
                               pose_function(second)(0.006), atol=1e-6)
    assert_ball_at(server, 0.006)
    # A collider whose model the client does not have is left out, not the ones after it.
    unknown = copy.deepcopy(two)
    unknown.colliders[0].model = "no-such-model"
    assert len(Colliders.add(server, unknown, client, infos).handles) == 1


# -- the live controls ---------------------------------------------------------------------------


def _live(world, server, total: int, paused: bool, clock_values, scene=None, colliders=True):
    """Live controls on a view of ``scene`` (the ball's by default; ``colliders``: draw them)
    and the simulator they drive; ``clock_values``: the wall times the controls read, in turn."""
    from collider_cli.views.cloth import ClothView, LiveControls
    from collider_client.sim.simulator import Simulator

    _, client, infos, ball_scene, _ = world
    scene = scene or ball_scene
    view = ClothView(server, scene, rest_of(scene), *((client, infos) if colliders else ()))
    sim = Simulator(scene, client, infos)
    # paused None: LiveControls' default (running).
    more = {} if paused is None else {"paused": paused}
    controls = LiveControls(server, view, total, clock=iter(clock_values).__next__, **more)
    return controls, sim


def status(step: int, total: int, t: float, ms: str, colliding: int) -> str:
    return (f"**step {step} / {total}**, t = {t:.4f} s  \ntime per step: {ms}  \n"
            f"colliding vertices: {colliding}")


def test_live_view_refreshes_at_most_every_tenth_of_a_second(world, server):
    """Running: a step is shown when 0.1 s of wall time passed since the last shown one, and the
    last step always; the status gives the time per step since the last shown step; the
    colliders are drawn at the simulation's time."""
    # Wall times: start 0, then steps 1..4 at 0.05, 0.1, 0.15, 0.16 s.
    controls, sim = _live(world, server, 4, None, [0.0, 0.05, 0.1, 0.15, 0.16])  # not paused
    assert controls.play.label == "pause" and controls.step.label == "step"
    first = status(0, 4, 0.0, "-", 0)
    assert controls.status.content == first
    rest = sim.vertices.copy()
    sim.step()
    controls.on_step(sim, 1)  # 0.05 s after the start: not shown
    assert controls.status.content == first
    assert_cloth_shows(server, rest, None)
    assert_ball_at(server, 0.0)
    for i in (2, 3, 4):
        sim.step()
        controls.on_step(sim, i)
        if i == 2:  # 0.1 s: shown, 2 steps in 0.1 s
            assert controls.status.content == status(2, 4, 2 * DT, "50.00 ms", int(sim.colliding.sum()))
            shown = sim.vertices.copy()
            assert_cloth_shows(server, shown, sim.colliding)
            assert_ball_at(server, 2 * DT)
        if i == 3:  # 0.05 s later: not shown
            assert controls.status.content.startswith("**step 2 / 4**")
            np.testing.assert_array_equal(node(server, "/cloth").vertices, shown.astype(np.float32))
    # The last step: shown (0.06 s after step 2: 30 ms a step), and the controls are done.
    colliding = sim.colliding
    assert 0 < colliding.sum() < len(colliding)
    assert controls.status.content == status(4, 4, 4 * DT, "30.00 ms", int(colliding.sum()))
    assert_cloth_shows(server, sim.vertices, colliding)
    assert_ball_at(server, 4 * DT)
    assert controls.play.label == "finished" and controls.play.disabled and controls.step.disabled


def test_live_view_paused_steps_one_at_a_time(world, server):
    """Started paused: every step is shown, however soon after the last; "step" lets exactly
    one more run, "play" lets it go on; time spent paused is not counted in the time per step."""
    # Wall times: start 0; step 1 at 1 s, resumed at 101 s (paused 100 s); step 2 at 101.01 s,
    # resumed at 101.02 s; step 3 at 101.03 s (0.02 s after the last shown), resumed at
    # 101.04 s; step 4 at 101.06 s.
    clock = [0.0, 1.0, 101.0, 101.01, 101.02, 101.03, 101.04, 101.06]
    controls, sim = _live(world, server, 4, True, clock)
    assert controls.play.label == "play"
    times = {1: "1000.00 ms", 2: "10.00 ms", 3: "10.00 ms"}
    for i in (1, 2, 3):
        click(controls.step)  # pressed before the step: the run goes one step, then waits
        sim.step()
        controls.on_step(sim, i)
        assert controls.status.content == status(i, 4, i * DT, times[i], int(sim.colliding.sum()))
        assert_cloth_shows(server, sim.vertices, sim.colliding)
        assert_ball_at(server, i * DT)
        assert controls.play.label == "play"
    click(controls.play)
    assert controls.play.label == "pause"
    sim.step()
    controls.on_step(sim, 4)
    assert controls.status.content == status(4, 4, 4 * DT, "20.00 ms", int(sim.colliding.sum()))
    assert controls.play.label == "finished"


def test_live_view_blocks_the_run_while_paused(world, server):
    """The simulator's thread waits in ``on_step`` while paused, until "step" or "play"; "step"
    while running pauses the run after one more step."""
    controls, sim = _live(world, server, 5, True, [float(i) for i in range(20)], colliders=False)
    steps: list[int] = []
    resumed = {i: threading.Event() for i in range(1, 6)}

    def run():  # the simulator's loop, in its own thread as in `collider simulate --view`
        for i in range(1, 6):
            sim.step()
            controls.on_step(sim, i)
            steps.append(i)
            resumed[i].set()

    threading.Thread(target=run, daemon=True).start()
    assert not resumed[1].wait(0.3)  # paused: step 1 does not return
    click(controls.step)
    assert resumed[1].wait(30) and not resumed[2].wait(0.3)  # one more step, then waits again
    click(controls.play)
    assert resumed[2].wait(30)
    click(controls.step)  # while running: pauses (after at most one more step)
    assert controls.play.label in ("play", "finished")
    # The step in flight when clicked ends, then the run is held (the last one never waits: it
    # finishes): wait for either, however slow the machine.
    deadline = time.monotonic() + 30
    while not (controls.held.is_set() or resumed[5].is_set()) and time.monotonic() < deadline:
        resumed[5].wait(0.01)
    held = len(steps)
    if held < 5:
        assert controls.held.is_set() and len(steps) == held  # paused: held in on_step, not one step more
        click(controls.play)
    assert resumed[5].wait(30)
    assert steps == [1, 2, 3, 4, 5] and controls.play.label == "finished"


def test_live_view_pause_after_play_holds(world, server):
    """"play" while the run is busy (nobody waiting), then "pause": the run stops at its next
    step, whether or not "step" was pressed before; paused at the last step, the run ends."""
    controls, sim = _live(world, server, 5, True, [float(i) for i in range(20)], colliders=False)

    def held(i: int) -> None:  # step i, paused: held until "step"
        sim.step()
        returned = threading.Event()
        threading.Thread(target=lambda: (controls.on_step(sim, i), returned.set()),
                         daemon=True).start()
        assert not returned.wait(0.3), f"step {i} went through a pause"
        click(controls.step)
        assert returned.wait(30)

    click(controls.play)  # the run is not waiting: nobody takes this wake-up now
    sim.step()
    controls.on_step(sim, 1)
    click(controls.play)  # pause
    assert controls.play.label == "play"
    held(2)  # and "step" ran it: the next pause must hold as well
    click(controls.play)
    sim.step()
    controls.on_step(sim, 3)
    click(controls.play)
    held(4)
    sim.step()
    returned = threading.Event()
    threading.Thread(target=lambda: (controls.on_step(sim, 5), returned.set()), daemon=True).start()
    assert returned.wait(30)  # the last step, paused: the run ends, nothing to wait for
    assert controls.play.label == "finished"


def test_live_view_of_a_scene_without_colliders(world, server, tmp_path):
    from collider_client.sim.scene import load_scene

    path = tmp_path / "falling.toml"
    path.write_text(FALLING)
    scene = load_scene(path)
    controls, sim = _live(world, server, 3, False, [0.0, 0.2, 0.4, 0.6], scene=scene)
    sim.step()
    controls.on_step(sim, 1)
    assert sim.colliding is None
    assert controls.status.content == status(1, 3, DT, "200.00 ms", 0)
    assert_cloth_shows(server, sim.vertices, None)
    assert node(server, "/colliding").point_size == pytest.approx(2.5 * 0.1)


# -- the replay ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def run(world):
    """The scene run for 12 steps: frames at steps 0, 5, 10 and 12 (the last step)."""
    from collider_client.sim.run import run_scene

    _, client, _, scene, root = world
    out = root / "out"
    _, frames = run_scene(scene, client, out, show_progress=False, steps=12, preview=False)
    return out / "ball.rising", [np.asarray(f[1]).copy() for f in frames], [f[0] for f in frames]


def test_replay_shows_every_frame_at_its_time(world, run):
    """The frame slider: each frame's cloth, and the ball where it was when that frame was
    written (the last frame at the run's last step, not a multiple of frame_every)."""
    from collider_cli.views.cloth import serve_replay

    _, client, infos, scene, _ = world
    prefix, frames, times = run
    np.testing.assert_allclose(times, [0.0, 5 * DT, 10 * DT, 12 * DT], atol=1e-12)
    page = serve_replay(prefix, "127.0.0.1", 0, scene, client, infos)
    try:
        slider = page.slider
        assert (slider.label, slider.min, slider.max, slider.step) == ("frame", 0, 3, 1)
        assert slider.value == 0 and page.play.label == "play"
        assert page.status.content == "**frame 0 / 3**, t = 0.0000 s"
        assert_cloth_shows(page.server, frames[0], None)
        assert_ball_at(page.server, 0.0)
        for k in (2, 3, 1):
            slider.value = k
            assert page.status.content == f"**frame {k} / 3**, t = {times[k]:.4f} s"
            assert_cloth_shows(page.server, frames[k], None)
            assert_ball_at(page.server, times[k])
        np.testing.assert_array_equal(page.frames[3], frames[3])
    finally:
        page.server.stop()


def test_replay_times_without_the_runs_report(world, run, tmp_path):
    """Without the run's report (a run stopped early writes none), or with one of another run
    (another frame count) or unreadable: frame k at step k * frame_every."""
    import shutil

    from collider_cli.views.cloth import serve_replay

    _, client, infos, scene, _ = world
    prefix, frames, _ = run
    reports = {"none": None, "other": '{"frames": 7, "steps": 30}', "unreadable": "{frames: 4",
               "float": '{"frames": 4, "steps": 12.5}'}
    for name, report in reports.items():
        for suffix in (".obj", ".pc2"):
            shutil.copy(prefix.parent / f"ball.rising{suffix}", tmp_path / f"{name}{suffix}")
        if report is not None:
            (tmp_path / f"{name}.report.json").write_text(report)
        page = serve_replay(tmp_path / name, "127.0.0.1", 0, scene, client, infos)
        try:
            page.slider.value = 3
            assert page.status.content == "**frame 3 / 3**, t = 0.0150 s", name
            assert_ball_at(page.server, 15 * DT)
            assert_cloth_shows(page.server, frames[3], None)
        finally:
            page.server.stop()


def test_replay_plays_and_pauses(run):
    from collider_cli.views.cloth import serve_replay

    prefix, _, _ = run
    page = serve_replay(prefix, "127.0.0.1", 0)
    try:
        shown: list[int] = []
        wrapped = threading.Event()

        def seen(_):
            shown.append(int(page.slider.value))
            if shown[-2:] == [0, 1]:
                wrapped.set()

        page.slider.value = 3
        page.slider.on_update(seen)
        click(page.play)
        assert page.play.label == "pause"
        assert wrapped.wait(30)  # the player went on from the last frame to the first, then on
        click(page.play)
        assert page.play.label == "play"
        assert shown[0] == 0 and all(b == (a + 1) % 4 for a, b in itertools.pairwise(shown))
    finally:
        page.server.stop()


def test_replay_without_its_scene(run):
    """Without the scene: the grid's size from the OBJ, no colliders, no times."""
    from collider_cli.views.cloth import serve_replay, triangles

    prefix, frames, _ = run
    port = free_port()
    page = serve_replay(prefix, "127.0.0.1", port)
    try:
        assert page.server.get_port() == port
        assert page.status.content == "**frame 0 / 3**"
        np.testing.assert_array_equal(node(page.server, "/cloth").faces, triangles(9, 9))
        assert page.server.scene.get_handle_by_name("/colliders/0_ball") is None
        assert node(page.server, "/colliding").point_size == pytest.approx(2.5e-3)
        page.slider.value = 2
        assert page.status.content == "**frame 2 / 3**"
        assert_cloth_shows(page.server, frames[2], None)
    finally:
        page.server.stop()


def test_replay_command_serves_until_ctrl_c(world, run, capsys):
    """``collider view --replay OUT/NAME --scene FILE``, in process: it prints the URL of the
    port asked for and serves until Ctrl-C, then stops cleanly with status 0."""
    from collider_cli import main

    _, _, _, _, root = world
    prefix, _, _ = run
    port = free_port()
    status = []
    printed = interrupt_once_printed(
        lambda: status.append(main(["view", "--replay", str(prefix), "--scene",
                                    str(root / "ball.rising.toml"), "--models",
                                    str(root / "models"), "--port", str(port)])),
        "(Ctrl-C to stop)")
    assert (f"replaying 4 frames of {prefix} at http://127.0.0.1:{port}/  (Ctrl-C to stop)\n"
            in printed)
    assert status == [0]
    assert capsys.readouterr().err.endswith("view stopped\n")


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_replay_reads_the_pc2_frames(run):
    from collider_contract.point_cache import read_pc2

    prefix, frames, _ = run
    read = read_pc2(prefix.parent / "ball.rising.pc2")  # the one reader the replay calls
    assert read.shape == (4, 81, 3) and read.dtype == np.float32
    np.testing.assert_array_equal(read[3], frames[3])
    assert not read.flags.writeable  # the view cannot change the run's output


def _pc2(path, points: int, samples: int, data: bytes = b"", magic: bytes = b"POINTCACHE2\0"):
    path.write_bytes(struct.pack("<12siiffi", magic, 1, points, 0.0, 1.0, samples) + data)


def test_replay_refuses_what_it_cannot_show(run, tmp_path):
    from collider_cli.views.cloth import serve_replay

    prefix, _, _ = run
    obj = (prefix.parent / "ball.rising.obj").read_text()
    def replay(name):
        return serve_replay(tmp_path / name, "127.0.0.1", 0)

    with pytest.raises(FileNotFoundError) as err:
        replay("none")
    assert str(err.value) == (f"{tmp_path / 'none.obj'}: no such file (run `collider simulate` "
                              "first; --replay takes the output prefix, e.g. out/drape_bunny)")
    (tmp_path / "no_pc2.obj").write_text(obj)
    with pytest.raises(FileNotFoundError, match=r"no_pc2\.pc2: no such file"):
        replay("no_pc2")
    cut_bytes = 32 + 81 * 12 + 11
    cases = {  # name: (pc2 header: points, samples, data, magic), the error (read_pc2's checks)
        "empty": ((81, 0, b"", b"POINTCACHE2\0"), "holds no frames"),
        "no_points": ((0, 3, b"", b"POINTCACHE2\0"), "PC2 header is malformed (version 1, 0 points, 3 samples)"),
        "negative": ((-5, 3, b"", b"POINTCACHE2\0"), "PC2 header is malformed (version 1, -5 points, 3 samples)"),
        "no_samples": ((81, -1, b"", b"POINTCACHE2\0"),
                       "PC2 header is malformed (version 1, 81 points, -1 samples)"),
        "not_pc2": ((81, 1, bytes(81 * 12), b"POINTCACHE3\0"), "not a PC2 file (no POINTCACHE2 header)"),
        "cut": ((81, 2, bytes(81 * 12 + 11), b"POINTCACHE2\0"),
                (f"truncated: the header promises 2 frames of 81 points ({32 + 2 * 81 * 12:,} bytes), "
                 f"the file has {cut_bytes:,} bytes (1.01 frames: the file is {81 * 12 - 11} bytes short of 2)")),
    }
    for name, ((points, samples, data, magic), error) in cases.items():
        (tmp_path / f"{name}.obj").write_text(obj)
        _pc2(tmp_path / f"{name}.pc2", points, samples, data, magic)
        with pytest.raises(ValueError) as err:
            replay(name)
        assert str(err.value) == f"{tmp_path / (name + '.pc2')}: {error}"
    (tmp_path / "short.obj").write_text(obj)
    (tmp_path / "short.pc2").write_bytes(b"POINTCACHE2\0" + bytes(19))  # a cut header
    with pytest.raises(ValueError, match=r"short.pc2: not a PC2 file \(no POINTCACHE2 header\)$"):
        replay("short")


def test_replay_needs_a_cloth_grid_without_its_scene(run, tmp_path):
    from collider_cli.views.cloth import serve_replay

    frame = np.zeros((6, 3), np.float32)
    objs = {  # an OBJ the grid cannot be read from: no faces, a first quad that is not a row's
        "no_faces": "v 0 0 0\n",
        "bad_quad": "f 1 2 2 1\n",
        "not_rows": "f 1 2 6 5\nf 2 3 7 6\n",  # rows of 4: 6 vertices are not whole rows
    }
    for name, text in objs.items():
        (tmp_path / f"{name}.obj").write_text(text)
        _pc2(tmp_path / f"{name}.pc2", 6, 1, frame.tobytes())
        with pytest.raises(ValueError) as err:
            serve_replay(tmp_path / name, "127.0.0.1", 0)
        assert str(err.value) == (f"{tmp_path / (name + '.obj')}: not a cloth grid written by "
                                  "`collider simulate`")
    (tmp_path / "grid.obj").write_text("# a 3 x 2 grid\nv 0 0 0\nf 1 2 5 4\nf 2 3 6 5\n")
    from collider_cli.views.cloth import _grid_from_obj

    size = _grid_from_obj(tmp_path / "grid.obj", 6)
    assert size == (3, 2) and all(type(v) is int for v in size)
    _pc2(tmp_path / "grid.pc2", 6, 1, frame.tobytes())
    page = serve_replay(tmp_path / "grid", "127.0.0.1", 0)
    try:
        np.testing.assert_array_equal(node(page.server, "/cloth").faces,
                                      [[0, 1, 4], [1, 2, 5], [0, 4, 3], [1, 5, 4]])
    finally:
        page.server.stop()
