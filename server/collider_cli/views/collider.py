"""``collider view NAME``: look at a collider in the browser (viser, extra ``[view]``).

Everything is shown in the **collider frame and units** (identity pose):

- the collider's surface: marching cubes of its ``level`` set (0 = the surface itself; a level of
  eps shows the offset surface that contacts are projected to), from ``distance`` on a grid over
  its domain; with ``--mesh``, coloured by its error against the exact mesh distance in mm
  (``exact_distance(vertex) - level``: red where the collider's surface lies outside the true
  one, blue inside), with a colour bar;
- the exact mesh as a toggleable wireframe (``--mesh``) and the domain box;
- a probe: type a point or click the surface, see ``distance``, ``normal`` (an arrow),
  ``contact`` and ``collides``;
- an animated collider: a **time** slider (seconds, 0 to its duration, a quarter of a frame a
  step) and a **play** checkbox; the surface, its error against the exact mesh interpolated at
  that time (given its frames), the wireframe and the probe (with the surface's ``velocity``) all
  follow the time. Each time step's grid is computed once and kept (:class:`TimeGrids`).

The grid, the time steps, the errors, the ray and the probe's text are plain functions in
:mod:`.collider_numerics` (their names importable from here), the colours here
(:func:`error_colors`), all testable without a browser; :func:`serve_collider_view` builds the scene and
returns its :class:`ColliderPage` (the server and the controls a user drives).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np

from collider_contract import Timeline
from collider_server.engine.animated_meshes import AnimatedMesh, ExactAtTimes
from collider_server.engine.collider import Collider
from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.making.surface import level_surface

from .collider_numerics import (
    STEPS_PER_FRAME,
    TIME_GRIDS_BYTES,
    TimeGrids,
    collider_grid,
    probe_text,
    sphere_trace,
    surface_error_mm,
    time_step_s,
    time_text,
)
from .page import box_edges, look_at_box, start_server

__all__ = ["STEPS_PER_FRAME", "TIME_GRIDS_BYTES", "ColliderPage", "TimeGrids", "collider_grid", "colour_bar_html",
           "error_colors", "probe_text", "run_time", "serve_collider_view", "sphere_trace", "surface_error_mm",
           "time_step_s", "time_text"]

BOX_COLOR = (60, 60, 60)
WIRE_COLOR = (40, 40, 40)
PLAIN_COLOR = (170, 190, 210)
PROBE_COLOR = (250, 140, 0)


def error_colors(error_mm: np.ndarray, clip_mm: float) -> np.ndarray:
    """(v, 3) uint8 diverging colours: blue (-clip_mm) - white (0) - red (+clip_mm)."""
    s = np.clip(error_mm / clip_mm, -1.0, 1.0)[:, None]
    white, red, blue = np.array([245, 245, 245.]), np.array([200, 30, 30.]), np.array([30, 70, 200.])
    rgb = np.where(s >= 0, white + s * (red - white), white - s * (blue - white))
    return rgb.round().astype(np.uint8)


def colour_bar_html(clip_mm: float) -> str:
    """An HTML colour bar for :func:`error_colors` with its scale in mm."""
    stops = ", ".join(f"rgb{tuple(int(c) for c in error_colors(np.array([v]), 1.0)[0])}"
                      for v in np.linspace(-1, 1, 9))
    return (f'<div style="padding:4px 0;font-size:12px">surface error vs exact mesh (mm)'
            f'<div style="height:14px;border:1px solid #888;background:linear-gradient(to right,'
            f'{stops})"></div><div style="display:flex;justify-content:space-between">'
            f"<span>-{clip_mm:.3g} (inside)</span><span>0</span><span>+{clip_mm:.3g}</span></div></div>")


def box_segments(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(12, 2, 3) float32 edges of the box ``lo``..``hi``."""
    return box_edges(lo, hi).astype(np.float32)


@dataclass
class ColliderPage:
    """The view of one collider: its started viser server and the controls on its page (viser
    GUI handles: a click in the browser calls their callbacks, and so can a test). The time
    controls exist for an animated collider only (None for a static one)."""

    server: object
    title: object  # markdown: the collider, its units and the grid
    level: object  # slider, mm: the level set shown
    eps_button: object  # sets the level to eps
    status: object  # markdown: what the surface is
    bar: object | None  # html: the error colour bar (with a mesh)
    show_wire: object | None  # checkbox: the exact mesh's wireframe (with a mesh)
    probe_point: object  # vector3, collider frame and units
    probe_button: object
    probe_out: object  # markdown: the probe's answer
    time: object | None = None  # slider, seconds: the time shown
    play: object | None = None  # checkbox: run the time slider on in real time
    time_label: object | None = None  # markdown: the time and the frame
    grids: TimeGrids | None = None  # the animated collider's grids per time step
    players: list = field(default_factory=list)  # the threads "play" started, the latest last


def serve_collider_view(collider: Collider, mesh: Mesh | AnimatedMesh | None, *, host: str,
                        port: int, resolution: int, up: str = "+z", clip_mm: float | None = None,
                        show_progress: bool = True) -> ColliderPage:
    """Build the view of ``collider`` and return its page, its server started; the caller
    serves until Ctrl-C. ``mesh``: the exact surface placed in the collider frame (an
    :class:`AnimatedMesh` for an animated collider, run on the collider's clock), or None."""
    info = collider.info
    animated = collider.animated
    if animated and isinstance(mesh, Mesh) or not animated and isinstance(mesh, AnimatedMesh):
        raise ValueError(f"{info.name} is {'animated' if animated else 'static'}: the exact mesh "
                         f"must be {'animated' if animated else 'static'} too")
    if animated:
        grids = TimeGrids(collider, resolution, time_step_s(collider))
        grid = grids.at(0.0, show_progress)  # the page's first; later ones say "computing"
        exact = ExactAtTimes(mesh) if mesh is not None else None
    else:
        grids, grid = None, collider_grid(collider, resolution, show_progress)
        exact = ExactSDF(mesh) if mesh is not None else None
    server = start_server(host, port, label=f"collider {info.name} ({info.kind})")
    server.scene.set_up_direction(up)
    look_at_box(server, grid.lo, grid.hi, up)
    server.scene.add_line_segments("/domain", box_segments(grid.lo, grid.hi), BOX_COLOR,
                                   thickness=1.5, thickness_units="screen")
    page = _add_controls(server, collider, grids, grid, resolution, with_mesh=mesh is not None)
    view = _ColliderDrawing(page, collider, mesh, exact, grid, clip_mm)
    page.probe_button.on_click(lambda _: view.probe(np.asarray(page.probe_point.value, np.float64)))
    page.eps_button.on_click(lambda _: setattr(page.level, "value", info.default_eps * view.mm))
    page.level.on_update(view.draw_surface)
    server.scene.on_pointer_event("click")(view.clicked)
    if page.show_wire is not None:
        page.show_wire.on_update(lambda _: view.show_wire())
    if animated:
        page.time.on_update(view.time_moved)
        page.play.on_update(view.play_toggled)
    view.draw_surface()
    return page


def _add_controls(server, collider: Collider, grids: TimeGrids | None, grid, resolution: int,
                  with_mesh: bool) -> ColliderPage:
    """The page's controls, in their order on the page, unwired: its :class:`ColliderPage`."""
    info = collider.info
    gui = server.gui
    mm, eps = 1e3 * info.meters_per_unit, info.default_eps
    title = gui.add_markdown(f"**{info.name}**: {info.kind} collider, {info.units} "
                             f"({info.meters_per_unit:g} m per unit), collider frame; "
                             f"grid {resolution}^3 over the domain box")
    time_slider = play = time_label = None
    if collider.animated:
        timeline = Timeline.from_dict(info.animation)
        duration = timeline.duration_s
        time_slider = gui.add_slider("time (s)", 0.0, duration, grids.step_s, 0.0,
                                     hint=f"seconds, 0 to {duration:g}; a step is 1/"
                                          f"{STEPS_PER_FRAME} of a frame")
        play = gui.add_checkbox("play", False, hint="run the time on in real time (a time step "
                                                    "not seen before is computed first)")
        time_label = gui.add_markdown(time_text(timeline, 0.0))
    level = gui.add_slider("level (mm)", -10.0 * eps * mm, 10.0 * eps * mm, 0.05 * eps * mm, 0.0,
                           hint=f"show the surface distance == level; eps = {eps * mm:g} mm is "
                                "the offset surface contacts are projected to")
    eps_button = gui.add_button(f"level = eps ({eps * mm:g} mm)")
    status = gui.add_markdown("")
    bar = gui.add_html("") if with_mesh else None
    show_wire = gui.add_checkbox("exact mesh wireframe", False) if with_mesh else None
    probe_point = gui.add_vector3("probe point", tuple(0.5 * (grid.lo + grid.hi)), step=1e-4,
                                  hint=f"collider frame, {info.units}; or click the surface")
    probe_button = gui.add_button("query probe")
    probe_out = gui.add_markdown("click the surface or type a point")
    return ColliderPage(server, title, level, eps_button, status, bar, show_wire, probe_point,
                        probe_button, probe_out, time_slider, play, time_label, grids)


class _ColliderDrawing:
    """What the page's controls do: draw the level surface (coloured by its error against the
    exact mesh, when given) and the exact wireframe at the time shown, answer the probe, follow
    the time slider and start the player. Callbacks run in viser's threads: one draw at a time."""

    def __init__(self, page: ColliderPage, collider: Collider, mesh, exact, grid, clip_mm: float | None):
        self.page, self.collider, self.mesh, self.exact, self.grid = page, collider, mesh, exact, grid
        info = collider.info
        self.mm, self.eps = 1e3 * info.meters_per_unit, info.default_eps
        self.timeline = Timeline.from_dict(info.animation) if collider.animated else None
        self.clip, self.drawn, self.wire, self.wire_at, self.probed = clip_mm, None, None, None, False
        self.lock = threading.Lock()

    def now(self) -> float | None:
        """The time shown, seconds: the slider's value on its step (a browser rounds it)."""
        grids = self.page.grids
        return grids.step_of(float(self.page.time.value)) * grids.step_s if self.collider.animated else None

    def show_wire(self) -> None:
        if self.wire is not None:
            self.wire.visible = self.page.show_wire.value

    def draw_wire(self, t: float | None) -> None:
        mesh = self.mesh
        if mesh is None or (self.wire is not None and self.wire_at == t):
            return
        vertices = mesh.vertices_at(t) if self.collider.animated else mesh.vertices
        self.wire = self.page.server.scene.add_mesh_simple(
            "/exact_mesh", vertices.astype(np.float32), mesh.faces.astype(np.uint32), color=WIRE_COLOR,
            wireframe=True, opacity=0.35, visible=self.page.show_wire.value)
        self.wire_at = t

    def draw_surface(self, _=None) -> None:
        import trimesh

        page, animated, mm = self.page, self.collider.animated, self.mm
        with self.lock:
            # Callbacks from a dragged slider queue up: draw the slider's latest value once.
            t, value = self.now(), float(page.level.value) / mm
            if self.drawn == (t, value):
                return
            self.drawn = (t, value)
            if animated:
                page.time_label.content = time_text(self.timeline, t)
                if not page.grids.has(t):
                    page.status.content = f"computing the {page.grids.resolution}^3 grid at t = {t:.4g} s ..."
            self.draw_wire(t)
            surface = level_surface(page.grids.at(t) if animated else self.grid, value)
            if surface is None:
                page.status.content = f"no surface at level {page.level.value:.3g} mm in the domain"
                return
            verts, faces = surface
            shown = trimesh.Trimesh(verts, faces, process=False)
            text = f"surface at level {page.level.value:.3g} mm: {len(faces):,} triangles"
            if self.exact is not None:
                sdf = self.exact.at(t)[0] if animated else self.exact
                error = surface_error_mm(sdf, verts, value, self.collider.info.meters_per_unit)
                if self.clip is None:  # fixed from the first surface so colours compare
                    self.clip = max(float(np.percentile(np.abs(error), 95)), 1e-3)
                shown.visual.vertex_colors = np.c_[error_colors(error, self.clip),
                                                   np.full(len(verts), 255, np.uint8)]
                page.bar.content = colour_bar_html(self.clip)
                text += (f"  \nerror vs exact mesh: mean |e| {np.abs(error).mean():.3g} mm, "
                         f"max {np.abs(error).max():.3g} mm")
            else:
                shown.visual.vertex_colors = np.array([*PLAIN_COLOR, 255], np.uint8)
            page.server.scene.add_mesh_trimesh("/surface", shown)
            page.status.content = text

    def probe(self, point: np.ndarray) -> None:
        text, fields = probe_text(self.collider, point, self.eps, self.now())
        self.page.probe_out.content = text
        self.probed = True
        lo, hi = self.grid.lo, self.grid.hi
        arrow = float(np.max(hi - lo)) * 0.15
        scene = self.page.server.scene
        scene.add_line_segments(
            "/probe/normal", np.array([[point, point + arrow * fields["normal"]]], np.float32),
            PROBE_COLOR, thickness=3.0, thickness_units="screen")
        scene.add_point_cloud("/probe/points", np.array([point, fields["contact"]], np.float32),
                              np.array([PROBE_COLOR, (20, 160, 60)], np.uint8),
                              point_size=0.01 * float(np.max(hi - lo)), point_shape="circle")

    def clicked(self, event) -> None:
        """A click on the canvas: the ray traced to the surface at the time shown, probed there."""
        hit = sphere_trace(self.collider, np.asarray(event.ray_origin, np.float64),
                           np.asarray(event.ray_direction, np.float64), time=self.now())
        if hit is None:
            self.page.probe_out.content = "the click missed the collider"
            return
        self.page.probe_point.value = tuple(hit)
        self.probe(hit)

    def time_moved(self, _) -> None:
        self.draw_surface()
        if self.probed:  # a probe shown: answer it at the new time
            self.probe(np.asarray(self.page.probe_point.value, np.float64))

    def play_toggled(self, _) -> None:
        players, play = self.page.players, self.page.play
        if play.value and (not players or not players[-1].is_alive()):
            players.append(threading.Thread(target=run_time, args=(self.page.time, play), daemon=True))
            players[-1].start()


def run_time(time_slider, play) -> None:
    """While ``play`` is checked, move ``time_slider`` on by the wall-clock seconds elapsed
    (whole steps: at least one, at most a frame's; after its end, from 0 again). Setting the
    slider redraws in this thread: a time step computed before keeps real time, one not
    computed yet slows the play down to one frame per grid computed."""
    step = float(time_slider.step)
    steps = round(float(time_slider.max) / step) + 1  # 0 .. max
    last = time.perf_counter()
    while play.value:
        time.sleep(step)
        now = time.perf_counter()
        moved = min(max(round((now - last) / step), 1), STEPS_PER_FRAME)
        last = now
        index = (round(float(time_slider.value) / step) + moved) % steps
        time_slider.value = min(index * step, float(time_slider.max))
