"""The Verlet cloth simulator, its step assembled from the effects a scene declares.

State: positions ``x`` and previous positions ``x_prev``, (H, W, 3) float64, metres, world frame.
One step (dt seconds)::

    a      = sum of the declared accelerations (gravity, wind, springs / mass)
    x_new  = x + (1 - damping * dt) (x - x_prev) + a dt^2      (explicit Verlet)
    pins   : pinned vertices stay at their rest positions
    collide: points in a collider's inflated box are queried; colliding ones move to their
             contact point and get the response velocity (see collider_client.response)

An effect that is not declared adds no code to the step: the step is a list of callables built
once from the scene (:attr:`Simulator.effects` names them, in order).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..response import ColliderPlacement, CollisionHook
from .cloth import SpringFamily, grid_positions
from .motion import pose_function
from .scene import Scene


@dataclass
class Timings:
    """Seconds spent, summed over the run."""

    integration_s: float = 0.0
    collision_s: float = 0.0  # client side: box culling and the response
    query_s: float = 0.0      # the SDK calls: engine in process, or HTTP round trip + server


@dataclass
class RunReport:
    scene: str
    backend: str
    vertices: int
    steps: int
    dt_s: float
    frames: int
    effects: list[str]
    fields: list[str]
    wall_s: float
    timings: Timings
    points_total: int = 0
    points_sent: int = 0
    queries: int = 0
    colliding_max: int = 0
    colliding_last: int = 0
    deepest_penetration_m: float = 0.0
    false_contacts: int = 0  # HookStats.false_contacts: answers deeper than a vertex could have gone
    per_frame_colliding: list[int] = field(default_factory=list)
    exact_check: dict | None = None
    steps_planned: int | None = None  # the run's step count; ``steps`` is what ran
    interrupted: bool = False  # Ctrl-C or SIGTERM ended the run after ``steps`` steps

    def per_step_ms(self) -> dict[str, float]:
        s = max(self.steps, 1)
        t = self.timings
        return {"total": 1e3 * self.wall_s / s, "integration": 1e3 * t.integration_s / s,
                "collision": 1e3 * t.collision_s / s, "query": 1e3 * t.query_s / s}

    def text(self) -> str:
        ms = self.per_step_ms()
        planned = self.steps if self.steps_planned is None else self.steps_planned
        lines = [
            f"scene            {self.scene}  ({self.backend} backend)",
            (f"cloth            {self.vertices} vertices, {self.steps} steps of {self.dt_s:g} s, "
            f"{self.frames} frames written"),
            f"effects          {', '.join(self.effects)}",
            f"fields asked     {', '.join(self.fields) or 'none (no collisions)'}",
            (f"time per step    {ms['total']:.3f} ms = integration {ms['integration']:.3f} + "
            f"collision {ms['collision']:.3f} + query (engine/transport) {ms['query']:.3f} ms"),
            (f"points sent      {self.points_sent} of {self.points_total} "
            f"({100.0 * self.points_sent / max(self.points_total, 1):.1f} %) in {self.queries} queries"),
            f"colliding        max {self.colliding_max}, at the end {self.colliding_last} vertices",
            (f"deepest penetration (reported by the collider, before projection) "
            f"{1e3 * max(0.0, -self.deepest_penetration_m):.3f} mm"),
        ]
        if self.false_contacts:
            lines.append(f"false contacts   {self.false_contacts} answered deeper than their vertex could have "
                         "gone in its step (the collider's error): not responded, each vertex went on as if "
                         "unanswered")
        if self.exact_check:
            lines.append(f"exact check      {exact_check_text(self.exact_check)}")
        if self.interrupted:
            lines.insert(0, f"INTERRUPTED      after {self.steps:,} of {planned:,} steps "
                            f"(t = {self.steps * self.dt_s:.4g} s); every figure covers the steps that ran")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "timings"}
        d["timings_s"] = self.timings.__dict__.copy()
        d["time_per_step_ms"] = self.per_step_ms()
        return d


def exact_check_text(check: dict) -> str:
    """:func:`collider_server.making.evaluation.penetration`'s figures in words: the deepest
    vertex inside the exact meshes (per collider when several), the closest approach, and over
    how many frames; and, measured every step (``SurfaceCrossings``), how many vertices crossed
    into them during a step."""
    per_model = check.get("by_model") or {}
    text = f"deepest vertex {1e3 * check['max_depth_m']:.3f} mm inside the exact mesh"
    if len(per_model) > 1:
        text += " (" + ", ".join(f"{name} {1e3 * depth:.3f} mm" for name, depth in per_model.items()) + ")"
    closest = check.get("min_distance_m")
    if closest is not None and closest != float("inf"):
        where = "outside" if closest >= 0 else "inside"
        text += f", closest approach {1e3 * abs(closest):.3f} mm {where}"
    text += f", over {check['frames']} frames" if "frames" in check else ""
    if "crossed_points" in check:  # measured every step (collider simulate --check-mesh)
        text += (f"; {check['crossed_points']:,} vertices crossed into it during a step "
                 f"({check['inside_at_end']:,} of them inside at the end; deepest at a step "
                 f"{1e3 * check['max_depth_at_a_step_m']:.3f} mm)")
    return text


class SimulationError(ValueError):
    """The run left the physically meaningful states: a non-finite position, or a vertex that
    moved more than the cloth's own size in one step (a blow-up). Raised at the first such step."""


class Simulator:
    """A cloth from ``scene``; ``client`` (a :class:`collider_client.Client`) answers collisions
    and is only used when the scene declares ``[effects.collisions]``."""

    def __init__(self, scene: Scene, client=None, model_infos: dict | None = None):
        self.scene = scene
        c = scene.cloth
        self.rest = grid_positions(c.width, c.height, c.spacing_m, c.origin_m, c.axes)
        #: A vertex moving farther than this in one step (the cloth's rest diagonal) is a blow-up.
        self.runaway_m = float(np.hypot(c.width - 1, c.height - 1) * c.spacing_m)
        self.steps_done = 0
        self.x = self.rest.copy()
        self.x_prev = self.rest.copy()
        self.dt = scene.dt_s
        self.t = 0.0
        self.mass_kg = c.density_kg_m2 * c.spacing_m ** 2
        self.timings = Timings()
        self.effects: list[str] = []
        self._accel = np.zeros(3)
        fx = scene.effects
        if "gravity" in fx:
            self._accel = self._accel + fx["gravity"]["acceleration_m_s2"]
            self.effects.append("gravity")
        self.springs = [SpringFamily(n, self.rest, fx[n]["stiffness_n_m"])
                        for n in ("stretch", "shear", "bend") if n in fx]
        self.effects += [s.name for s in self.springs]
        self.wind = fx.get("wind")
        if self.wind:
            self.effects.append("wind")
        self.damping = fx["damping"]["coefficient_1_s"] if "damping" in fx else 0.0
        if "damping" in fx:
            self.effects.append("damping")
        self.pinned = self._pinned(fx.get("pins"))
        if self.pinned is not None:
            self.effects.append("pins")
        self.hook = None
        self.colliding: np.ndarray | None = None  # set by step() when collisions run
        if "collisions" in fx:
            if client is None:
                raise ValueError(f"{scene.path}: the scene has colliders; a client is needed")
            # A still collider's pose as a matrix: the hook then knows it does not move.
            placements = [ColliderPlacement(
                spec.model, pose_function(spec)(0.0) if spec.motion.kind == "static" else pose_function(spec),
                spec.time_offset_s, spec.loop, spec.clip) for spec in scene.colliders]
            friction = fx.get("friction")
            # Without friction the hook keeps the collider's velocity (restitution has no use).
            response = {} if friction is None else {"friction": friction["coefficient"],
                                                    "restitution": friction["restitution"]}
            self.hook = CollisionHook(client, placements, eps=fx["collisions"]["eps_m"],
                                      infos=model_infos, **response)
            self.effects.append("collisions")
            if friction is not None:
                self.effects.append("friction")

    def _check_state(self, x_new: np.ndarray, x: np.ndarray) -> None:
        """Stop at the first non-finite or runaway state, naming the step and what to change."""
        step = np.abs(x_new - x).max()  # NaN propagates: caught below
        if np.isfinite(step) and step <= self.runaway_m:
            return
        what = ("a position became non-finite" if not np.isfinite(step) else
                f"a vertex moved {step:.3g} m in one step, more than the cloth's size "
                f"({self.runaway_m:.3g} m)")
        raise SimulationError(
            f"{self.scene.path}: the cloth blew up at step {self.steps_done} (t = "
            f"{self.t + self.dt:.6g} s): {what}; lower scene.dt_s, the spring stiffness, the "
            "damping or the wind drag")

    def _pinned(self, pins):
        if pins is None:
            return None
        w, h = self.scene.cloth.width, self.scene.cloth.height
        corner = {"bottom-left": (0, 0), "bottom-right": (w - 1, 0),
                  "top-left": (0, h - 1), "top-right": (w - 1, h - 1)}
        cells = {corner[c] for c in pins["corners"]} | {tuple(v) for v in pins["vertices"]}
        cols, rows = zip(*sorted(cells))
        return np.asarray(rows), np.asarray(cols)

    def energy(self) -> dict[str, float]:
        """The cloth's mechanical energy now, joules: ``kinetic`` (from the last step's
        velocity ``(x - x_prev) / dt``), ``gravity`` (potential, zero at the world origin), and
        ``springs`` (``k (|d| - L)^2 / 2`` summed over the declared families), and ``total``.
        With only dissipative effects (damping, friction, inelastic contact) the total does not
        grow; a blow-up shows as it growing without bound."""
        velocity = (self.x - self.x_prev) / self.dt
        kinetic = 0.5 * self.mass_kg * float(np.sum(velocity * velocity))
        gravity = -self.mass_kg * float(np.sum(self.x * self._accel))
        springs = sum(family.energy(self.x) for family in self.springs)
        return {"kinetic": kinetic, "gravity": gravity, "springs": springs,
                "total": kinetic + gravity + springs}

    @property
    def vertices(self) -> np.ndarray:
        """(W*H, 3) float64 current positions, metres, world frame (flat index r * W + c)."""
        return self.x.reshape(-1, 3)

    def step(self) -> None:
        """Advance one ``dt``: integrate the declared forces, then collide (if declared)."""
        t0 = time.perf_counter()
        x, dt = self.x, self.dt
        velocity_dt = x - self.x_prev  # velocity * dt
        if self.springs or self.wind:
            forces = np.zeros_like(x)
            for family in self.springs:
                family.add_forces(x, forces)
            accel = forces / self.mass_kg + self._accel
            if self.wind:
                # Linear drag towards the wind velocity: a = drag (w - v).
                accel += self.wind["drag_1_s"] * (self.wind["velocity_m_s"] - velocity_dt / dt)
        else:
            accel = self._accel
        keep = 1.0 - self.damping * dt  # 1 without damping
        x_new = x + keep * velocity_dt + accel * (dt * dt)
        if self.pinned is not None:
            x_new[self.pinned] = self.rest[self.pinned]
        self.steps_done += 1
        self._check_state(x_new, x)
        self.t += dt
        t1 = time.perf_counter()
        self.timings.integration_s += t1 - t0
        if self.hook is not None:
            flat = x_new.reshape(-1, 3)
            velocity = (flat - x.reshape(-1, 3)) / dt
            query_before = self.hook.stats.query_s
            positions, velocity, mask = self.hook.apply(flat, velocity, self.t, dt)
            self.colliding = mask  # (W*H,) bool of the last step, for viewers
            if mask.any():
                positions = positions.reshape(x.shape)
                velocity = velocity.reshape(x.shape)
                if self.pinned is not None:
                    positions[self.pinned] = self.rest[self.pinned]
                    velocity[self.pinned] = 0.0
                # Verlet keeps velocity as x - x_prev: encode the responded velocity there.
                self.x_prev = positions - velocity * dt
                self.x = positions
            else:
                self.x_prev, self.x = x, x_new
            spent = time.perf_counter() - t1
            query = self.hook.stats.query_s - query_before
            self.timings.query_s += query
            self.timings.collision_s += spent - query
        else:
            self.x_prev, self.x = x, x_new
