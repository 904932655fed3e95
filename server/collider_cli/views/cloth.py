"""The browser view of a cloth run: live (``collider simulate --view``) or replayed from its
OBJ + PC2 output (``collider view --replay out/SCENE``: :func:`serve_replay`).

Built on viser (optional extra ``[view]``; imported only here, when a view is asked for): one
process serves the page and its web client (shipped inside the viser wheel, nothing is fetched),
and pushes the scene over a websocket. Everything drawn is in the **world frame, metres**: the
cloth, its colliding vertices (red points), and each collider's surface (marching cubes of its
zero level set, computed in the collider frame through the same client the run uses, then placed
by its pose at the shown time).
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from collider_client.sim.cloth import quad_faces
from collider_client.sim.motion import pose_function
from collider_client.sim.scene import Scene
from collider_contract import transform_points
from collider_contract.point_cache import read_pc2
from collider_server.making.surface import distance_grid, level_surface

from .page import look_at_box, start_server

CLOTH_COLOR = (70, 130, 200)
COLLIDER_COLOR = (200, 200, 190)
COLLIDING_COLOR = (230, 30, 30)


def triangles(width: int, height: int) -> np.ndarray:
    """(F, 3) uint32 triangles of the cloth grid (each quad split in two)."""
    q = quad_faces(width, height)
    return np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]).astype(np.uint32)


def collider_surface_via_client(client, info, resolution: int = 48):
    """(vertices (v, 3) float32, faces (f, 3) uint32) of a collider's zero level set in its own
    frame and units, from ``distance`` queries on a grid over its domain through ``client``;
    None when scikit-image is missing or the grid has no sign change."""
    try:
        import skimage  # noqa: F401  (the [view] extra brings it; without it: no surface)
    except ImportError:
        return None
    # The identity pose, so that the answer stays in the collider frame.
    grid = distance_grid(lambda points: np.asarray(client.query(
        info.name, points, fields=["distance"], pose=np.eye(4)).distance),
        info.domain_min, info.domain_max, resolution, chunk_points=resolution ** 3)
    surface = level_surface(grid)
    if surface is None:
        return None
    return surface[0].astype(np.float32), surface[1].astype(np.uint32)


def _pose_parts(pose: np.ndarray):
    """(wxyz, position, scale) of a 4x4 similarity (rotation, translation, uniform scale)."""
    from viser import transforms

    linear = pose[:3, :3]
    scale = float(np.cbrt(abs(np.linalg.det(linear)))) or 1.0
    return transforms.SO3.from_matrix(linear / scale).wxyz, pose[:3, 3], scale


@dataclass
class Colliders:
    """The scene's colliders drawn in the view, moved to their poses by :meth:`place`."""

    handles: list
    poses: list

    @classmethod
    def add(cls, server, scene: Scene, client, infos: dict | None) -> Colliders:
        handles, poses = [], []
        for i, spec in enumerate(scene.colliders):
            surface = None
            if client is not None and infos and spec.model in infos:
                surface = collider_surface_via_client(client, infos[spec.model])
            if surface is None:
                continue
            handles.append(server.scene.add_mesh_simple(
                f"/colliders/{i}_{spec.model}", surface[0], surface[1], color=COLLIDER_COLOR,
                side="double"))
            poses.append(pose_function(spec))
        return cls(handles, poses)

    def place(self, t: float) -> None:
        for handle, pose in zip(self.handles, self.poses):
            wxyz, position, scale = _pose_parts(pose(t))
            handle.wxyz, handle.position, handle.scale = wxyz, position, scale


class ClothView:
    """The cloth mesh, its colliding vertices and the scene's colliders in one viser scene."""

    def __init__(self, server, scene: Scene, vertices: np.ndarray, client=None, infos=None):
        c = scene.cloth
        self.server = server
        self.cloth = server.scene.add_mesh_simple(
            "/cloth", vertices.astype(np.float32), triangles(c.width, c.height),
            color=CLOTH_COLOR, side="double")
        self.colliding = server.scene.add_point_cloud(
            "/colliding", vertices[:1].astype(np.float32), COLLIDING_COLOR,
            point_size=2.5 * c.spacing_m, point_shape="circle", visible=False)
        self.colliders = Colliders.add(server, scene, client, infos)
        self.colliders.place(0.0)
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        for spec, info in ((s, (infos or {}).get(s.model)) for s in scene.colliders):
            if info is not None:  # frame the colliders too, at their start pose
                pose = pose_function(spec)(0.0)
                pts = transform_points(pose, info.domain_corners())
                lo, hi = np.minimum(lo, pts.min(axis=0)), np.maximum(hi, pts.max(axis=0))
        look_at_box(server, lo, hi)

    def show(self, vertices: np.ndarray, t: float, colliding: np.ndarray | None) -> None:
        """Show the cloth at ``vertices`` ((W*H, 3) metres, world frame), time ``t`` seconds."""
        with self.server.atomic():
            self.cloth.vertices = vertices.astype(np.float32)
            if colliding is not None and colliding.any():
                self.colliding.points = vertices[colliding].astype(np.float32)
                self.colliding.colors = np.tile(np.array(COLLIDING_COLOR, np.uint8),
                                                (int(colliding.sum()), 1))
                self.colliding.visible = True
            else:
                self.colliding.visible = False
            self.colliders.place(t)


class LiveControls:
    """Play / pause / step for a running simulation, with the frame counter and time per step.

    :meth:`on_step` is the simulator's per-step callback (``run_scene(on_step=...)``): it
    refreshes the view at most every ``refresh_s`` seconds of wall time (and on every step while
    paused, and at the last step) and blocks while the run is paused. ``clock``: wall time in
    seconds (``time.perf_counter``; a test passes its own).
    """

    def __init__(self, server, view: ClothView, total_steps: int, refresh_s: float = 0.1,
                 paused: bool = False, clock=time.perf_counter):
        self.view, self.total, self.refresh_s, self.clock = view, total_steps, refresh_s, clock
        self._running = threading.Event()
        if not paused:
            self._running.set()
        self._step_once = False
        self._wake = threading.Event()  # set by "play" and "step": the paused run looks again
        #: Set while the run is held in :meth:`on_step` by a pause (what a caller can wait on).
        self.held = threading.Event()
        self._last_step = 0
        self._last_time = self._shown = clock()
        gui = server.gui
        self.play = gui.add_button("pause" if not paused else "play")
        self.step = gui.add_button("step")
        self.status = gui.add_markdown(self._text(0, 0.0, None, 0))
        self.play.on_click(lambda _: self.toggle())
        self.step.on_click(lambda _: self.step_one())

    def toggle(self) -> None:
        if self._running.is_set():
            self._running.clear()
            self.play.label = "play"
        else:
            self._running.set()
            self.play.label = "pause"
            self._wake.set()

    def step_one(self) -> None:
        """Run exactly one more step, then stay paused."""
        if self._running.is_set():
            self.toggle()
        self._step_once = True
        self._wake.set()

    def _text(self, step: int, t: float, ms: float | None, colliding: int) -> str:
        per_step = "-" if ms is None else f"{ms:.2f} ms"
        return (f"**step {step} / {self.total}**, t = {t:.4f} s  \n"
                f"time per step: {per_step}  \ncolliding vertices: {colliding}")

    def on_step(self, sim, i: int) -> None:
        paused = not self._running.is_set()
        now = self.clock()
        if now - self._shown >= self.refresh_s or i == self.total or paused:
            ms = 1e3 * (now - self._last_time) / max(i - self._last_step, 1)
            colliding = sim.colliding
            self.view.show(sim.vertices, sim.t, colliding)
            self.status.content = self._text(i, sim.t, ms, 0 if colliding is None
                                             else int(colliding.sum()))
            self._last_step, self._last_time, self._shown = i, now, now
        if i == self.total:
            self.play.label, self.play.disabled, self.step.disabled = "finished", True, True
        if i < self.total and not self._running.is_set():
            self._wait_if_paused()
            # Time spent paused is not a step's time.
            self._last_step, self._last_time = i, self.clock()

    def _wait_if_paused(self) -> None:
        try:
            while not self._running.is_set():
                if not self._wake.is_set():  # (a "step" already given passes straight through)
                    self.held.set()
                self._wake.wait()
                self.held.clear()
                self._wake.clear()
                if self._step_once:
                    self._step_once = False
                    return
        finally:
            self.held.clear()


@dataclass
class ReplayPage:
    """The replay of a finished run: its started viser server, the cloth view and the controls
    on its page (viser GUI handles: a click in the browser calls their callbacks, and so can a
    test)."""

    server: object
    view: ClothView
    frames: np.ndarray  # (frames, W*H, 3) float32, metres, world frame
    slider: object  # the frame shown
    play: object  # play / pause
    status: object  # markdown: the frame and its time


def serve_replay(out_prefix: Path, host: str, port: int, scene: Scene | None = None, client=None,
                 infos=None) -> ReplayPage:
    """The started view of a finished run: ``out_prefix``.obj (first frame, quads) and .pc2
    (every frame), with a frame slider and play/pause; the scene's colliders when ``scene`` is
    given (placed at each frame's time)."""
    # The prefix's name plus a suffix, not with_suffix: a scene named "a.b" writes a.b.obj.
    obj, pc2, report = (out_prefix.parent / f"{out_prefix.name}{suffix}"
                        for suffix in (".obj", ".pc2", ".report.json"))
    for path in (obj, pc2):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file (run `collider simulate` first; "
                                    "--replay takes the output prefix, e.g. out/drape_bunny)")
    frames = read_pc2(pc2)  # memory-mapped: a long run's cache can be GBs
    if len(frames) == 0:
        raise ValueError(f"{pc2}: holds no frames")
    times = _frame_times(scene, len(frames), report) if scene is not None else None
    if scene is None:
        width, height = _grid_from_obj(obj, frames.shape[1])
        scene = _bare_scene(width, height)
    server = start_server(host, port)
    view = ClothView(server, scene, frames[0], client, infos)
    gui = server.gui
    slider = gui.add_slider("frame", 0, len(frames) - 1, 1, 0)
    play = gui.add_button("play")
    status = gui.add_markdown("")
    playing = threading.Event()

    def show(_=None):
        k = int(slider.value)
        t = float(times[k]) if times is not None else 0.0
        view.show(frames[k], t, None)
        when = f", t = {t:.4f} s" if times is not None else ""
        status.content = f"**frame {k} / {len(frames) - 1}**{when}"

    def toggle(_):
        if playing.is_set():
            playing.clear()
            play.label = "play"
        else:
            playing.set()
            play.label = "pause"

    slider.on_update(show)
    play.on_click(toggle)
    show()

    def player():
        while True:
            playing.wait()
            slider.value = (int(slider.value) + 1) % len(frames)  # on_update redraws
            time.sleep(1.0 / 30)  # playback pace: 30 frames per second of wall time

    threading.Thread(target=player, daemon=True).start()
    return ReplayPage(server, view, frames, slider, play, status)


def _frame_times(scene: Scene, count: int, report: Path) -> np.ndarray:
    """(count,) seconds at which a run of ``scene`` wrote its frames: frame k at step
    k * frame_every, the last one at the run's last step, which the run's report gives (a run
    of --steps that are no multiple of frame_every). A report of another run (another frame
    count: one stopped early, or an older one) is not used."""
    steps = np.arange(count) * scene.frame_every
    try:
        done = json.loads(report.read_text())
    except (OSError, ValueError):  # no report: a run stopped early ends on a whole frame
        done = {}
    if done.get("frames") == count and isinstance(done.get("steps"), int):
        steps[-1] = done["steps"]
    return steps * scene.dt_s


def _grid_from_obj(obj: Path, n: int) -> tuple[int, int]:
    """(width, height) of the cloth grid from the OBJ's first quad (a b b+1 ... rows of W)."""
    for line in obj.open():
        if line.startswith("f "):
            a, _b, _c, d = (int(v) for v in line.split()[1:5])
            width = d - a
            if width > 0 and n % width == 0:
                return width, n // width
            break
    raise ValueError(f"{obj}: not a cloth grid written by `collider simulate`")


def _bare_scene(width: int, height: int):
    """A stand-in with only the cloth's grid size, for a replay without its scene file."""
    from types import SimpleNamespace

    return SimpleNamespace(cloth=SimpleNamespace(width=width, height=height, spacing_m=1e-3),
                           colliders=[])
