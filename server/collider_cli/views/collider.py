"""``collider view NAME``: look at a collider in the browser (viser, extra ``[view]``).

Everything is shown in the **collider frame and units** (identity pose):

- the collider's surface: marching cubes of its ``level`` set (0 = the surface itself; a level of
  eps shows the offset surface that contacts are projected to), from ``distance`` on a grid over
  its domain; with ``--mesh``, coloured by its error against the exact mesh distance in mm
  (``exact_distance(vertex) - level``: red where the collider's surface lies outside the true
  one, blue inside), with a colour bar;
- the exact mesh as a toggleable wireframe (``--mesh``) and the domain box;
- a probe: type a point or click the surface, see ``distance``, ``normal`` (an arrow),
  ``contact`` and ``collides``.

The grid and the colours are plain functions (:func:`collider_grid`, :func:`level_surface`,
:func:`error_colors`), testable without a browser; :func:`serve_collider_view` builds the scene and
returns its :class:`ColliderPage` (the server and the controls a user drives).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from collider_server.engine.collider import Collider
from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.making.surface import Grid, distance_grid, level_surface

from .page import box_edges, look_at_box, start_server

BOX_COLOR = (60, 60, 60)
WIRE_COLOR = (40, 40, 40)
PLAIN_COLOR = (170, 190, 210)
PROBE_COLOR = (250, 140, 0)


def collider_grid(collider: Collider, resolution: int, show_progress: bool = True) -> Grid:
    """``collider``'s distance on ``resolution``^3 points spanning its domain box."""
    if not 8 <= resolution <= 512:
        raise ValueError(f"--resolution must be between 8 and 512, got {resolution}")
    return distance_grid(lambda points: collider.query(points, ["distance"]).distance,
                         collider.domain_min, collider.domain_max, resolution,
                         desc=f"{collider.info.name} grid", show_progress=show_progress)


def surface_error_mm(sdf: ExactSDF, vertices: np.ndarray, level: float,
                     meters_per_unit: float) -> np.ndarray:
    """(v,) float64 mm: exact signed distance of each surface vertex minus ``level`` (0 where the
    collider's level set lies exactly at that distance from the mesh; > 0 outside)."""
    return (sdf.signed_distance(vertices) - level) * 1e3 * meters_per_unit


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


def sphere_trace(collider: Collider, origin: np.ndarray, direction: np.ndarray,
                 max_steps: int = 200) -> np.ndarray | None:
    """First point where the ray ``origin + s * direction`` (collider frame) reaches the
    collider's surface, marching by the distance itself; None when it misses the domain."""
    lo, hi = collider.domain_min, collider.domain_max
    direction = direction / np.linalg.norm(direction)
    # Start where the ray enters the domain box (slab test).
    with np.errstate(divide="ignore"):
        inv = 1.0 / direction
    t0, t1 = (lo - origin) * inv, (hi - origin) * inv
    near, far = np.minimum(t0, t1).max(), np.maximum(t0, t1).min()
    if not far > max(near, 0.0):
        return None
    s = max(near, 0.0)
    tolerance = 1e-5 * float(np.max(hi - lo))
    for _ in range(max_steps):
        p = origin + s * direction
        d = float(collider.query(p[None], ["distance"]).distance[0])
        if d < tolerance:
            return p
        s += d
        if s > far:
            return None
    return None


def probe_text(collider: Collider, point: np.ndarray, eps: float) -> tuple[str, dict]:
    """Markdown with distance / normal / contact / collides at ``point`` and the raw fields."""
    r = collider.query(point[None], ["distance", "normal", "contact", "collides"], eps=eps)
    mm = 1e3 * collider.info.meters_per_unit
    fields = {"distance": float(r.distance[0]), "normal": r.normal[0].astype(float),
              "contact": r.contact[0].astype(float), "collides": bool(r.collides[0])}
    fmt = lambda v: "(" + ", ".join(f"{x:.5g}" for x in v) + ")"  # noqa: E731
    text = (f"**probe** {fmt(point)} {collider.info.units}  \n"
            f"distance **{fields['distance'] * mm:.4g} mm**  \n"
            f"normal {fmt(fields['normal'])}  \n"
            f"contact {fmt(fields['contact'])}  \n"
            f"collides **{fields['collides']}** (eps {eps * mm:.3g} mm)")
    return text, fields


@dataclass
class ColliderPage:
    """The view of one collider: its started viser server and the controls on its page (viser
    GUI handles: a click in the browser calls their callbacks, and so can a test)."""

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


def serve_collider_view(collider: Collider, mesh: Mesh | None, *, host: str, port: int,
                        resolution: int, up: str = "+z", clip_mm: float | None = None,
                        show_progress: bool = True) -> ColliderPage:
    """Build the view of ``collider`` (``mesh`` placed in its frame, or None) and return its
    page, its server started; the caller serves until Ctrl-C."""
    grid = collider_grid(collider, resolution, show_progress)
    sdf = ExactSDF(mesh) if mesh is not None else None
    info = collider.info
    mm = 1e3 * info.meters_per_unit
    eps = info.default_eps
    server = start_server(host, port, label=f"collider {info.name} ({info.kind})")
    server.scene.set_up_direction(up)
    lo, hi = grid.lo, grid.hi
    look_at_box(server, lo, hi, up)
    scene, gui = server.scene, server.gui
    scene.add_line_segments("/domain", box_segments(lo, hi), BOX_COLOR,
                            thickness=1.5, thickness_units="screen")
    title = gui.add_markdown(f"**{info.name}**: {info.kind} collider, {info.units} "
                     f"({info.meters_per_unit:g} m per unit), collider frame; "
                     f"grid {resolution}^3 over the domain box")
    level = gui.add_slider("level (mm)", -10.0 * eps * mm, 10.0 * eps * mm, 0.05 * eps * mm, 0.0,
                           hint=f"show the surface distance == level; eps = {eps * mm:g} mm is "
                                "the offset surface contacts are projected to")
    eps_button = gui.add_button(f"level = eps ({eps * mm:g} mm)")
    status = gui.add_markdown("")
    bar = gui.add_html("") if sdf is not None else None
    show_wire = None
    if mesh is not None:
        show_wire = gui.add_checkbox("exact mesh wireframe", False)
        wire = scene.add_mesh_simple("/exact_mesh", mesh.vertices.astype(np.float32),
                                     mesh.faces.astype(np.uint32), color=WIRE_COLOR,
                                     wireframe=True, opacity=0.35, visible=False)
        show_wire.on_update(lambda _: setattr(wire, "visible", show_wire.value))
    state = {"clip": clip_mm}
    lock = threading.Lock()

    def draw_surface(_=None) -> None:
        import trimesh

        value = float(level.value) / mm
        with lock:
            surface = level_surface(grid, value)
            if surface is None:
                status.content = f"no surface at level {level.value:.3g} mm in the domain"
                return
            verts, faces = surface
            shown = trimesh.Trimesh(verts, faces, process=False)
            text = f"surface at level {level.value:.3g} mm: {len(faces):,} triangles"
            if sdf is not None:
                error = surface_error_mm(sdf, verts, value, info.meters_per_unit)
                if state["clip"] is None:  # fixed from the first surface so colours compare
                    state["clip"] = max(float(np.percentile(np.abs(error), 95)), 1e-3)
                shown.visual.vertex_colors = np.c_[error_colors(error, state["clip"]),
                                                   np.full(len(verts), 255, np.uint8)]
                bar.content = colour_bar_html(state["clip"])
                text += (f"  \nerror vs exact mesh: mean |e| {np.abs(error).mean():.3g} mm, "
                         f"max {np.abs(error).max():.3g} mm")
            else:
                shown.visual.vertex_colors = np.array([*PLAIN_COLOR, 255], np.uint8)
            scene.add_mesh_trimesh("/surface", shown)
            status.content = text

    probe_point = gui.add_vector3("probe point", tuple(0.5 * (lo + hi)), step=1e-4,
                                  hint=f"collider frame, {info.units}; or click the surface")
    probe_button = gui.add_button("query probe")
    probe_out = gui.add_markdown("click the surface or type a point")

    def probe(point: np.ndarray) -> None:
        text, fields = probe_text(collider, point, eps)
        probe_out.content = text
        arrow = float(np.max(hi - lo)) * 0.15
        scene.add_line_segments(
            "/probe/normal", np.array([[point, point + arrow * fields["normal"]]], np.float32),
            PROBE_COLOR, thickness=3.0, thickness_units="screen")
        scene.add_point_cloud("/probe/points", np.array([point, fields["contact"]], np.float32),
                              np.array([PROBE_COLOR, (20, 160, 60)], np.uint8),
                              point_size=0.01 * float(np.max(hi - lo)), point_shape="circle")

    probe_button.on_click(lambda _: probe(np.asarray(probe_point.value, np.float64)))
    eps_button.on_click(lambda _: setattr(level, "value", eps * mm))
    level.on_update(draw_surface)

    @scene.on_pointer_event("click")
    def _(event) -> None:
        hit = sphere_trace(collider, np.asarray(event.ray_origin, np.float64),
                           np.asarray(event.ray_direction, np.float64))
        if hit is None:
            probe_out.content = "the click missed the collider"
            return
        probe_point.value = tuple(hit)
        probe(hit)

    draw_surface()
    return ColliderPage(server, title, level, eps_button, status, bar, show_wire, probe_point,
                        probe_button, probe_out)
