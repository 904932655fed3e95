"""Collision response a simulator calls after its own integration step (numpy only).

All arrays are world frame, metres (velocities in m/s). ``mask`` arrays select the colliding
points (``collides`` from a query, or ``distance < eps``).

- :func:`project_to_contacts` moves colliding points onto their contact points;
- :func:`respond_velocities` removes the normal velocity into the collider (times ``1 +
  restitution``) and applies Coulomb friction to the tangential part, relative to the velocity
  of the collider's surface (moving and animated colliders);
- :func:`collider_velocity` is a rigidly moving collider's velocity, from two successive poses;
- :class:`CollisionHook` puts them together with the SDK: positions and velocities in, responded
  positions and velocities out. It asks each collider at its animation time with its pose's
  velocity, and uses the surface ``velocity`` the service answers. It is what an adapter for
  another simulator calls.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from collider_contract import ModelInfo, SceneCollider, Timeline, transform_points

__all__ = [
    "ColliderPlacement",
    "CollisionHook",
    "HookStats",
    "TunnellingError",
    "animation_time",
    "collider_velocity",
    "project_to_contacts",
    "respond_velocities",
    "world_box",
]


def project_to_contacts(positions: np.ndarray, contact: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``positions`` with the rows in ``mask`` replaced by ``contact`` (a new array).

    positions, contact : (n, 3) float, world frame, metres; mask : (n,) bool
    """
    out = np.array(positions, dtype=np.result_type(positions, np.float32), copy=True)
    out[mask] = contact[mask]
    return out


def respond_velocities(velocities: np.ndarray, normal: np.ndarray, mask: np.ndarray,
                       friction: float = 0.0, restitution: float = 0.0,
                       collider_velocity: np.ndarray | None = None) -> np.ndarray:
    """Velocities after contact with a collider (a new array).

    velocities : (n, 3) float, m/s, world frame; normal : (n, 3) unit outward normal, world frame
    mask : (n,) bool, the points in contact
    friction : Coulomb coefficient mu >= 0; restitution : 0 (inelastic) .. 1 (elastic)
    collider_velocity : (n, 3) or (3,) m/s, velocity of the collider's surface at the points
        (None = static)

    Per point in contact, with ``u`` the velocity relative to the collider and ``u_n = u . n``:
    when ``u_n < 0`` (approaching), the normal part becomes ``-restitution * u_n``, a change of
    ``dv_n = -(1 + restitution) u_n``; the tangential part ``u_t`` sticks (becomes 0) when
    ``|u_t| <= mu dv_n`` and otherwise shrinks by ``mu dv_n`` (sliding). Separating points keep
    their velocity.
    """
    if friction < 0:
        raise ValueError(f"friction must be >= 0, got {friction}")
    if not 0.0 <= restitution <= 1.0:
        raise ValueError(f"restitution must be in [0, 1], got {restitution}")
    out = np.array(velocities, dtype=np.float64, copy=True)
    index = np.flatnonzero(mask)
    if not len(index):
        return out
    n = np.asarray(normal, dtype=np.float64)[index]
    base = 0.0 if collider_velocity is None else np.broadcast_to(
        np.asarray(collider_velocity, dtype=np.float64), out.shape)[index]
    u = out[index] - base
    u_n = np.einsum("ij,ij->i", u, n)
    approaching = u_n < 0
    u_t = u - u_n[:, None] * n
    dv_n = np.where(approaching, -(1.0 + restitution) * u_n, 0.0)
    t_len = np.linalg.norm(u_t, axis=1)
    # Coulomb: the friction impulse is bounded by mu times the normal impulse.
    shrink = np.where(t_len > friction * dv_n,
                      1.0 - friction * dv_n / np.where(t_len > 0, t_len, 1.0), 0.0)
    new_n = np.where(approaching, -restitution * u_n, u_n)
    new_t = np.where(approaching[:, None], u_t * shrink[:, None], u_t)
    out[index] = base + new_t + new_n[:, None] * n
    return out


def collider_velocity(pose_before: np.ndarray, pose_after: np.ndarray, points: np.ndarray,
                      dt: float) -> np.ndarray:
    """Velocity (n, 3) m/s of the collider's material at world ``points`` (taken at
    ``pose_after``), from its poses (4x4, collider -> world) ``dt`` seconds apart."""
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt}")
    points = np.asarray(points, dtype=np.float64)
    # Carry each point back with the collider: where was that material point one step ago?
    relative = np.asarray(pose_before, dtype=np.float64) @ np.linalg.inv(
        np.asarray(pose_after, dtype=np.float64))
    before = transform_points(relative, points)
    return (points - before) / dt


def world_box(info: ModelInfo, pose: np.ndarray | None, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """World-frame axis-aligned box (lo, hi) holding the model's domain box moved by ``pose``
    and grown by ``margin`` metres on every side. Outside it no point can collide."""
    corners = info.domain_corners()
    if pose is not None:
        corners = transform_points(pose, corners)
    return corners.min(axis=0) - margin, corners.max(axis=0) + margin


def _unit_rows(vectors: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length; zero rows stay zero."""
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return vectors / np.where(length > 0, length, 1.0)


@dataclass
class ColliderPlacement:
    """A collider in a simulation: a model name, its pose over time and, for an animated model,
    how the simulation's time maps to the animation's.

    pose_at : function of time (s) -> (4, 4) collider -> world; or a fixed (4, 4) pose (array or
        nested lists) for a static collider; or None for the identity
    time_offset_s : an animated model is asked at the simulation time plus this (seconds)
    loop : None: the model's own loop or clamp; True / False: loop or clamp it here whatever it
        was baked with (:class:`~collider_contract.Timeline`)
    """

    model: str
    pose_at: Callable[[float], np.ndarray] | np.ndarray | None = None
    time_offset_s: float = 0.0
    loop: bool | None = None

    def __post_init__(self):
        if self.pose_at is not None and not callable(self.pose_at):
            fixed = np.asarray(self.pose_at, dtype=np.float64)
            if fixed.shape != (4, 4) or not np.isfinite(fixed).all():
                raise ValueError(f"ColliderPlacement({self.model!r}): pose must be a function of "
                                 f"time or a finite 4x4 matrix, got shape {fixed.shape}")
            self.pose_at = lambda t, _fixed=fixed: _fixed
            self.static = True
        else:
            self.static = self.pose_at is None
        offset = self.time_offset_s
        if isinstance(offset, bool) or not isinstance(offset, (int, float)) or not np.isfinite(offset):
            raise ValueError(f"ColliderPlacement({self.model!r}): time_offset_s must be a finite "
                             f"number of seconds, got {offset!r}")
        if self.loop is not None and not isinstance(self.loop, bool):
            raise ValueError(f"ColliderPlacement({self.model!r}): loop must be None, True or "
                             f"False, got {self.loop!r}")

    def pose(self, t: float) -> np.ndarray:
        if self.pose_at is None:
            return np.eye(4)
        assert callable(self.pose_at)  # __post_init__ made a fixed pose a function
        return np.asarray(self.pose_at(t), dtype=np.float64)

    def pose_velocity(self, t: float, dt: float) -> np.ndarray | None:
        """The pose's time derivative at ``t`` (4x4; 1/s and m/s), the backward difference over
        ``dt``; None for a static collider."""
        if self.static:
            return None
        return (self.pose(t) - self.pose(t - dt)) / dt


def animation_time(placement: ColliderPlacement, timeline: Timeline | None,
                   t: float) -> tuple[float | None, bool]:
    """When ``placement``'s model is asked at simulation time ``t``: ``(time, held)``, the
    animation's time in seconds (None: a static model) and whether an end frame is held there
    (clamped beyond the ends: the surface's own velocity is zero). ``timeline`` is the model's
    (``ModelInfo.timeline``), the placement's ``loop`` overrides its loop."""
    if timeline is None:
        return None, False
    raw = t + placement.time_offset_s
    own = timeline.with_loop(placement.loop)
    local, held = own.local_time(raw), own.held(raw)
    if held and timeline.loop and local >= own.duration_s:
        # Clamped here but looping in the model, which starts over at its duration: ask it a
        # hair before (1e-12 of the animation: far below any length that matters).
        local = own.duration_s * (1.0 - 1e-12)
    return local, held


class TunnellingError(ValueError):
    """A step too long for the collision offset: a point could have passed through a thin
    feature between two queries (speed x dt >= eps relative to the collider)."""


@dataclass
class HookStats:
    """What the hook did over its calls (times in seconds)."""

    calls: int = 0
    points_total: int = 0
    points_sent: int = 0
    queries: int = 0
    colliding_last: int = 0
    colliding_max: int = 0
    deepest_penetration_m: float = 0.0  # most negative signed distance seen (<= 0): the worst penetration
    query_s: float = 0.0
    response_s: float = 0.0
    fields: list[str] = field(default_factory=list)


class CollisionHook:
    """Collide points with one or more colliders through the SDK; numpy in, numpy out.

    client : a :class:`collider_client.Client` (remote or embedded)
    colliders : :class:`ColliderPlacement` list
    eps : collision offset, metres (points closer than eps to a surface are pushed out to eps)
    friction : Coulomb coefficient; ``None`` = no velocity response: colliding points take the
        velocity of the collider's surface (inelastic and sticky), which needs no normals
    restitution : 0..1, used with friction
    cull : send only the points inside a collider's inflated box (True); False sends every point
        (for benchmarks that show what culling saves)
    only_colliding : ask for ``contact``, ``normal`` and ``velocity`` of the colliding points
        only (the service then does the gradient work for those alone; the response never uses
        the others'). False asks for them at every point sent (for benchmarks that show the
        saving)
    check_step : raise :class:`TunnellingError` when a point near a collider moves ``eps`` or
        more relative to it in one step (the limit below which nothing tunnels; see
        :meth:`substeps`)

    Call :meth:`apply` after each integration step (or substep). Only points inside a collider's
    inflated world box are sent, and only the fields the response needs are asked for: the
    surface ``velocity`` when a collider moves or is animated. Each collider is asked at its
    animation time (:func:`animation_time`) with its pose's velocity (the backward difference of
    its pose over the step); the service answers the velocity of the surface at each contact,
    its frame's motion plus its own deformation, and the response is relative to it.
    """

    def __init__(self, client, colliders: Sequence[ColliderPlacement], eps: float = 1e-3,
                 friction: float | None = None, restitution: float = 0.0,
                 infos: dict[str, ModelInfo] | None = None, cull: bool = True,
                 only_colliding: bool = True, check_step: bool = True):
        if not eps > 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        if not colliders:
            raise ValueError("CollisionHook needs at least one collider")
        self.client = client
        self.colliders = list(colliders)
        self.eps = float(eps)
        self.friction = friction
        self.restitution = float(restitution)
        self.cull = cull
        self.check_step = check_step
        self.only_colliding = bool(only_colliding)
        if infos is None:
            infos = {m.name: m for m in client.list_models()}
        missing = sorted({c.model for c in self.colliders} - set(infos))
        if missing:
            raise ValueError(f"unknown model(s) {missing}; available: {sorted(infos)}")
        self.infos = infos
        #: Per collider, its model's timeline (None: static).
        self.timelines = [infos[c.model].timeline for c in self.colliders]
        for placement, timeline in zip(self.colliders, self.timelines):
            if timeline is None and (placement.time_offset_s or placement.loop is not None):
                raise ValueError(f"ColliderPlacement({placement.model!r}): time_offset_s and "
                                 "loop apply to animated models; this one is static")
        #: Whether a collider moves or deforms: its surface's velocity is asked for, and a point
        #: caught part-way through a step is checked again at the step's later checks.
        self.moving = any(not c.static or line is not None
                          for c, line in zip(self.colliders, self.timelines))
        moving = self.moving
        # distance gives the penetration; contact moves them out; collides (one byte a point)
        # decides who collides, exactly as the service decided whose contact and normal to
        # compute; velocity (a moving or animated collider) is what a contact moves with; normal
        # only when velocities are corrected along it.
        self.fields = (["distance", "contact", "collides"] + (["velocity"] if moving else [])
                       + (["normal"] if friction is not None else []))
        self.stats = HookStats(fields=list(self.fields))

    #: Most collision substeps of one step (see :meth:`substeps`); beyond, TunnellingError.
    max_substeps = 64

    def collider_moves(self, poses: list, t: float, dt: float) -> list[float]:
        """Per collider, the largest displacement (m) of any point of its surface over the step
        from ``t - dt`` to ``t``: its domain box's corners under the two poses (a rigid motion
        moves a box's points at most as far as its corners), plus, animated, its fastest
        surface point's own travel (``max_surface_speed`` times the pose's scale and ``dt``);
        0 for static colliders."""
        moves = []
        for placement, pose, timeline in zip(self.colliders, poses, self.timelines):
            move = 0.0
            if not placement.static:
                corners = self.infos[placement.model].domain_corners()
                moved = transform_points(pose, corners) - transform_points(placement.pose(t - dt), corners)
                move = float(np.linalg.norm(moved, axis=1).max())
            if timeline is not None:
                scale = float(np.cbrt(abs(np.linalg.det(pose[:3, :3]))))
                move += timeline.max_surface_speed * scale * dt
            moves.append(move)
        return moves

    def substeps(self, velocities: np.ndarray, index: np.ndarray, moves: list[float], t: float,
                 dt: float) -> int:
        """How many collision checks the step needs along the points' paths so that nothing
        tunnels: ``floor(relative displacement / eps) + 1``.

        Why eps: a point at least eps outside (where every point is after a step: colliding
        ones are moved to eps) that moves less than eps relative to the surface cannot reach the
        far side of anything, however thin, without first landing within eps, where it is
        caught. The relative displacement is bounded by the point's own plus the collider's
        (:meth:`collider_moves`: its frame's motion and its surface's deformation).
        Raises :class:`TunnellingError` beyond :attr:`max_substeps`."""
        speed = np.linalg.norm(np.asarray(velocities, dtype=np.float64)[index], axis=1)
        own = float(speed.max(initial=0.0)) * dt
        box = max(moves, default=0.0)
        if not np.isfinite(own + box):
            raise TunnellingError(f"at t = {t:.6g} s a point near a collider has a non-finite velocity")
        count = int(np.floor((own + box) / self.eps)) + 1
        if count > self.max_substeps:
            raise TunnellingError(
                f"at t = {t:.6g} s a point near a collider moved {1e3 * (own + box):.3g} mm "
                f"relative to it in one step ({1e3 * own:.3g} mm itself at {own / dt:.3g} m/s, "
                f"{1e3 * box:.3g} mm the collider's surface): more than {self.max_substeps} x "
                f"eps = {1e3 * self.eps:.3g} mm, it could pass through a thin feature unseen. "
                "Keep speed x dt below eps: lower dt or raise eps")
        return count

    def apply(self, positions: np.ndarray, velocities: np.ndarray, t: float, dt: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Respond to contacts at time ``t`` (seconds: the poses and animation times at ``t``;
        ``dt`` for the colliders' velocities).

        positions : (n, 3) float, metres, world frame, after the step; velocities : (n, 3) float,
            m/s, the step's (positions moved by about velocities * dt during it)
        Returns ``(positions, velocities, mask)`` with new arrays for the first two and ``mask``
        (n,) bool of the points that were in contact.

        A step in which a point moves ``eps`` or more relative to a collider's surface is
        checked at :meth:`substeps` times along the paths (``check_step``), each at its own
        time; a point caught part-way is responded there and moves on with its responded
        velocity, so it cannot pass through a feature thinner than its step. When a collider
        moves or deforms, a caught point is checked again at the later times (a surface that
        keeps pushing keeps it outside), so a surface moving faster than eps per step does not
        leave it inside either.
        """
        started = time.perf_counter()
        positions = np.asarray(positions)
        n = len(positions)
        poses = [c.pose(t) for c in self.colliders]
        moves = self.collider_moves(poses, t, dt) if self.check_step else [0.0] * len(poses)
        sweep = np.asarray(velocities, dtype=np.float64) * dt if self.check_step else None
        index = np.flatnonzero(self._near(positions, poses, self.eps + 1e-9, sweep, moves))
        self.stats.calls += 1
        self.stats.points_total += n
        mask = np.zeros(n, dtype=bool)
        self.stats.colliding_last = 0
        if not len(index):
            self.stats.response_s += time.perf_counter() - started
            return positions, velocities, mask
        count = self.substeps(velocities, index, moves, t, dt) if self.check_step else 1
        positions = np.array(positions, copy=True)
        velocities = np.array(velocities, dtype=np.float64, copy=True)
        since = np.zeros(n)  # seconds into the step at which each point's velocity was last set
        query_s = 0.0
        for j in range(1, count + 1):
            back = 1.0 - j / count  # fraction of the step after this check
            t_j = t - back * dt
            poses_j = poses if j == count else [c.pose(t_j) for c in self.colliders]
            # Where each point is at t_j on its path (positions hold where it ends the step).
            points = positions[index] - back * velocities[index] * dt
            hit, q = self._respond(points, index, positions, velocities, since, poses_j, t_j, dt,
                                   (1.0 - back) * dt, back * dt)
            query_s += q
            mask[index[hit]] = True  # _respond wrote their positions and velocities
            if not self.moving:  # a still surface cannot catch up with a responded point
                index = index[~hit]
                if not len(index):
                    break
        self.stats.colliding_last = int(mask.sum())
        self.stats.colliding_max = max(self.stats.colliding_max, self.stats.colliding_last)
        self.stats.response_s += (time.perf_counter() - started) - query_s
        return positions, velocities, mask

    def _near(self, positions, poses, margin: float, sweep, moves: list[float]) -> np.ndarray:
        """(n,) bool: points inside some collider's world box grown by ``margin`` plus the
        collider's own move over the step (``moves``, m; all points when culling is off); with
        ``sweep`` (n, 3) displacements (None: none), points whose path from ``positions - sweep``
        to ``positions`` may meet such a box."""
        n = len(positions)
        if not self.cull:
            return np.ones(n, dtype=bool)
        near = np.zeros(n, dtype=bool)
        for k, (placement, pose) in enumerate(zip(self.colliders, poses)):
            grow = margin + moves[k]
            lo, hi = world_box(self.infos[placement.model], pose, grow)
            if sweep is None:
                near |= np.all((positions >= lo) & (positions <= hi), axis=1)
            else:  # the path's own box overlaps the collider's box
                start = positions - sweep
                near |= np.all((np.maximum(positions, start) >= lo)
                               & (np.minimum(positions, start) <= hi), axis=1)
        return near

    def _query(self, points, poses, t: float, dt: float):
        """The SDK call at ``t``: each collider at its animation time with its pose's velocity.
        Returns ``(result, which collider per point or None, held per collider)``."""
        times = [animation_time(c, line, t) for c, line in zip(self.colliders, self.timelines)]
        rates = [c.pose_velocity(t, dt) for c in self.colliders]
        if len(self.colliders) == 1:
            placement = self.colliders[0]
            result = self.client.query(
                placement.model, points, fields=self.fields, pose=poses[0], eps=self.eps,
                only_colliding=self.only_colliding, time=times[0][0], pose_velocity=rates[0])
            return result, None, [times[0][1]]
        result = self.client.scene_query(
            [SceneCollider(c.model, p, at, rate) for c, p, (at, _), rate in
             zip(self.colliders, poses, times, rates)],
            points, fields=self.fields, eps=self.eps, only_colliding=self.only_colliding)
        return result, np.asarray(result.collider), [held for _, held in times]

    def _respond(self, points, index, positions, velocities, since, poses, t: float, dt: float,
                 travelled_s: float, remaining_s: float):
        """Query ``points`` (the rows ``index`` at time ``t``, ``travelled_s`` into the step and
        ``remaining_s`` before its end), and for those within eps write the contact, moved on
        with the responded velocity for ``remaining_s``, and that velocity into ``positions`` /
        ``velocities`` (in place; ``since`` records when).
        Returns ``(hit (len(index),) bool, seconds spent in the query)``."""
        q0 = time.perf_counter()
        result, which, held = self._query(points, poses, t, dt)
        spent = time.perf_counter() - q0
        self.stats.query_s += spent
        self.stats.queries += 1
        self.stats.points_sent += len(index)
        hit = np.asarray(result.collides, dtype=bool)
        local_index = np.flatnonzero(hit)
        if not len(local_index):
            return hit, spent
        deepest = float(np.min(result.distance[local_index]))
        self.stats.deepest_penetration_m = min(self.stats.deepest_penetration_m, deepest)
        contact = np.asarray(result.contact, dtype=np.float64)[local_index]
        # The surface's velocity at the contacts (world frame, m/s): the service's answer.
        if result.velocity is not None:
            v_col = np.asarray(result.velocity, dtype=np.float64)[local_index]
        else:
            v_col = np.zeros((len(local_index), 3))
        for k, placement in enumerate(self.colliders):
            if held[k]:  # an end frame held here (a scene's clamp on a looping model): frame only
                rows = slice(None) if which is None else (which[local_index] == k)
                v_col[rows] = 0.0 if placement.static else collider_velocity(
                    placement.pose(t - dt), poses[k], contact[rows], dt)
        rows = index[local_index]
        v_before = velocities[rows]
        if self.friction is None:
            v_after = v_col
        else:
            normal = np.asarray(result.normal)[local_index]
            v_after = respond_velocities(v_before, normal, np.ones(len(local_index), bool),
                                         self.friction, self.restitution, v_col)
        velocities[rows] = v_after
        # The step already moved the point along the surface with its old velocity since that
        # was set; the response changed the velocity, so take the tangential part of the
        # change back from that stretch too: a contact that sticks does not creep (it slid
        # g sin(theta) dt^2 per step on a slope). The normal part is the projection's job.
        normal = _unit_rows(contact - points[local_index])
        change = (v_after - v_before) * (travelled_s - since[rows])[:, None]
        change -= np.einsum("ij,ij->i", change, normal)[:, None] * normal
        positions[rows] = contact + change + v_after * remaining_s
        since[rows] = travelled_s
        return hit, spent
