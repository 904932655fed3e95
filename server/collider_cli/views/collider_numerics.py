"""The numbers behind ``collider view NAME`` (:mod:`.collider`), testable without a browser: the
distance grid over a collider's domain (:func:`collider_grid`), an animated collider's time steps
and their kept grids (:class:`TimeGrids`), the surface's error against the exact mesh
(:func:`surface_error_mm`), a ray traced to the surface (:func:`sphere_trace`) and what the probe
shows (:func:`probe_text`). Collider frame and units."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

import numpy as np

from collider_contract import Timeline
from collider_server.engine.collider import Collider
from collider_server.engine.meshes import ExactSDF
from collider_server.making.surface import Grid, distance_grid

#: Time slider steps per frame of an animated collider.
STEPS_PER_FRAME = 4
#: Memory the kept grids of an animated collider's time steps may take (bytes).
TIME_GRIDS_BYTES = 512 * 2 ** 20


def collider_grid(collider: Collider, resolution: int, show_progress: bool = True,
                  time: float | None = None) -> Grid:
    """``collider``'s distance on ``resolution``^3 points spanning its domain box, at ``time``
    seconds (an animated collider; a static one ignores it)."""
    if not 8 <= resolution <= 512:
        raise ValueError(f"--resolution must be between 8 and 512, got {resolution}")
    at = "" if time is None else f" t={time:.4g}s"
    return distance_grid(lambda points: collider.query(points, ["distance"], time=time).distance,
                         collider.domain_min, collider.domain_max, resolution,
                         desc=f"{collider.info.name} grid{at}", show_progress=show_progress)


def time_step_s(collider: Collider) -> float:
    """The time slider's step, seconds: a quarter of the shortest frame interval the collider
    knows (its own frames, or the animation it was made from when that has more)."""
    rate = max(collider.info.animation["frame_rate_hz"],
               float(collider.info.source.get("frame_rate_hz", 0.0)))
    return 1.0 / (STEPS_PER_FRAME * rate)


def time_text(timeline: Timeline, t: float) -> str:
    """Markdown: the time and where it falls among the collider's frames (frame k is at
    k / frame_rate_hz seconds; between two frames, the fraction)."""
    k, u, _ = timeline.locate(t)
    ends = "loops" if timeline.loop else "clamps"
    return (f"**t = {t:.4g} s**: frame {k + u:.2f} of 0..{timeline.frames - 1} "
            f"({timeline.frame_rate_hz:g} fps, {timeline.duration_s:g} s, {ends})")


class TimeGrids:
    """An animated collider's distance grids at the time slider's steps (step ``i`` at
    ``i * step_s`` seconds): each computed on first use and kept, the least recently used
    dropped beyond ``budget_bytes``. Thread-safe: one grid is computed at a time.

    ``computed`` counts the grids computed and ``compute_s`` the seconds they took."""

    def __init__(self, collider: Collider, resolution: int, step_s: float,
                 budget_bytes: int = TIME_GRIDS_BYTES):
        self.collider, self.resolution, self.step_s = collider, resolution, step_s
        self.keep = max(2, budget_bytes // (4 * resolution ** 3))
        self._grids: OrderedDict[int, Grid] = OrderedDict()
        self._lock = threading.Lock()
        self.computed = 0
        self.compute_s = 0.0

    def step_of(self, t: float) -> int:
        return int(round(t / self.step_s))

    def has(self, t: float) -> bool:
        return self.step_of(t) in self._grids

    def at(self, t: float, show_progress: bool = False) -> Grid:
        """The grid at the step nearest ``t`` seconds (``show_progress``: a progress bar on
        stderr while it is computed)."""
        step = self.step_of(t)
        with self._lock:
            grid = self._grids.get(step)
            if grid is None:
                started = time.perf_counter()
                grid = collider_grid(self.collider, self.resolution, show_progress,
                                     time=step * self.step_s)
                self.computed += 1
                self.compute_s += time.perf_counter() - started
                self._grids[step] = grid
                while len(self._grids) > self.keep:
                    self._grids.popitem(last=False)
            self._grids.move_to_end(step)
            return grid


def surface_error_mm(sdf: ExactSDF, vertices: np.ndarray, level: float,
                     meters_per_unit: float) -> np.ndarray:
    """(v,) float64 mm: exact signed distance of each surface vertex minus ``level`` (0 where the
    collider's level set lies exactly at that distance from the mesh; > 0 outside)."""
    return (sdf.signed_distance(vertices) - level) * 1e3 * meters_per_unit


def sphere_trace(collider: Collider, origin: np.ndarray, direction: np.ndarray,
                 max_steps: int = 200, time: float | None = None) -> np.ndarray | None:
    """First point where the ray ``origin + s * direction`` (collider frame) reaches the
    collider's surface (at ``time`` seconds, an animated collider), marching by the distance
    itself; None when it misses the domain."""
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
        d = float(collider.query(p[None], ["distance"], time=time).distance[0])
        if d < tolerance:
            return p
        s += d
        if s > far:
            return None
    return None


def probe_text(collider: Collider, point: np.ndarray, eps: float,
               time: float | None = None) -> tuple[str, dict]:
    """Markdown with distance / normal / contact / collides at ``point`` (collider frame and
    units) and the raw fields; an animated collider is asked at ``time`` seconds and also says
    the surface's ``velocity`` there (collider units per second)."""
    names = ["distance", "normal", "contact", "collides"] + (["velocity"] if collider.animated else [])
    r = collider.query(point[None], names, eps=eps, time=time)
    mm = 1e3 * collider.info.meters_per_unit
    fields = {"distance": float(r.distance[0]), "normal": r.normal[0].astype(float),
              "contact": r.contact[0].astype(float), "collides": bool(r.collides[0])}
    fmt = lambda v: "(" + ", ".join(f"{x:.5g}" for x in v) + ")"
    units = collider.info.units
    at = f" at t = {time:.4g} s" if collider.animated else ""
    text = (f"**probe** {fmt(point)} {units}{at}  \n"
            f"distance **{fields['distance'] * mm:.4g} mm**  \n"
            f"normal {fmt(fields['normal'])}  \n"
            f"contact {fmt(fields['contact'])}  \n"
            f"collides **{fields['collides']}** (eps {eps * mm:.3g} mm)")
    if collider.animated:
        fields["velocity"] = r.velocity[0].astype(float)
        speed = float(np.linalg.norm(fields["velocity"])) * mm
        text += f"  \nvelocity {fmt(fields['velocity'])} {units}/s ({speed:.4g} mm/s)"
    return text, fields
