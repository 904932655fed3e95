"""Collision response a simulator calls after its own integration step (numpy only).

All arrays are world frame, metres (velocities in m/s). ``mask`` arrays select the colliding
points (``collides`` from a query, or ``distance < eps``).

- :func:`project_to_contacts` moves colliding points onto their contact points;
- :func:`respond_velocities` removes the normal velocity into the collider (times ``1 +
  restitution``) and applies Coulomb friction to the tangential part, relative to the collider's
  own velocity (moving colliders);
- :func:`collider_velocity` is that velocity, from two successive poses;
- :class:`CollisionHook` puts them together with the SDK: positions and velocities in, responded
  positions and velocities out. It is what an adapter for another simulator calls.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from collider_contract import ModelInfo, transform_points

__all__ = [
    "project_to_contacts",
    "respond_velocities",
    "collider_velocity",
    "world_box",
    "ColliderPlacement",
    "CollisionHook",
    "HookStats",
    "TunnellingError",
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
    """A collider in a simulation: a model name and its pose over time.

    pose_at : function of time (s) -> (4, 4) collider -> world; or a fixed (4, 4) pose (array or
        nested lists) for a static collider; or None for the identity
    """

    model: str
    pose_at: Callable[[float], np.ndarray] | np.ndarray | None = None

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

    def pose(self, t: float) -> np.ndarray:
        return np.eye(4) if self.pose_at is None else np.asarray(self.pose_at(t), dtype=np.float64)


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
    deepest_m: float = 0.0  # most negative signed distance seen (<= 0): the worst penetration
    query_s: float = 0.0
    response_s: float = 0.0
    fields: list[str] = field(default_factory=list)


class CollisionHook:
    """Collide points with one or more colliders through the SDK; numpy in, numpy out.

    client : a :class:`collider_client.Client` (remote or embedded)
    colliders : :class:`ColliderPlacement` list
    eps : collision offset, metres (points closer than eps to a surface are pushed out to eps)
    friction : Coulomb coefficient; ``None`` = no velocity response: colliding points take the
        collider's velocity (inelastic and sticky), which needs no normals from the service
    restitution : 0..1, used with friction
    cull : send only the points inside a collider's inflated box (True); False sends every point
        (for benchmarks that show what culling saves)
    only_colliding : ask for ``contact`` and ``normal`` of the colliding points only (the
        service then does the gradient work for those alone; the response never uses the
        others'). False asks for them at every point sent (for benchmarks that show the saving)
    check_step : raise :class:`TunnellingError` when a point near a collider moves ``eps`` or
        more relative to it in one step (the limit below which nothing tunnels; see
        :meth:`substeps`)

    Call :meth:`apply` after each integration step (or substep). Only points inside a collider's
    inflated world box are sent, and only the fields the response needs are asked for.
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
        # distance gives the penetration; contact moves them out; normal only when velocities are
        # corrected along it; collides (one byte a point) decides who collides, exactly as the
        # service decided whose contact and normal to compute.
        self.fields = ["distance", "contact", "collides"] + (["normal"] if friction is not None else [])
        self.stats = HookStats(fields=list(self.fields))

    #: Most collision substeps of one step (see :meth:`substeps`); beyond, TunnellingError.
    max_substeps = 64

    def collider_moves(self, poses: list, t: float, dt: float) -> list[float]:
        """Per collider, the largest displacement (m) of any point of its domain box over the
        step from ``t - dt`` to ``t`` (a rigid motion moves a box's points at most as far as its
        corners); 0 for static colliders."""
        moves = []
        for placement, pose in zip(self.colliders, poses):
            if placement.static:
                moves.append(0.0)
                continue
            corners = self.infos[placement.model].domain_corners()
            moved = transform_points(pose, corners) - transform_points(placement.pose(t - dt), corners)
            moves.append(float(np.linalg.norm(moved, axis=1).max()))
        return moves

    def substeps(self, velocities: np.ndarray, index: np.ndarray, moves: list[float], t: float,
                 dt: float) -> int:
        """How many collision checks the step needs along the points' paths so that nothing
        tunnels: ``floor(relative displacement / eps) + 1``.

        Why eps: a point at least eps outside (where every point is after a step: colliding
        ones are moved to eps) that moves less than eps cannot reach the far side of anything,
        however thin, without first landing within eps, where it is caught. The relative
        displacement is bounded by the point's own plus the collider's (:meth:`collider_moves`).
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
                f"{1e3 * box:.3g} mm the collider): more than {self.max_substeps} x eps = "
                f"{1e3 * self.eps:.3g} mm, it could pass through a thin feature unseen. Keep "
                "speed x dt below eps: lower dt or raise eps")
        return count

    def apply(self, positions: np.ndarray, velocities: np.ndarray, t: float, dt: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Respond to contacts at time ``t`` (the poses at ``t``; ``dt`` for collider velocity).

        positions : (n, 3) float, metres, world frame, after the step; velocities : (n, 3) float,
            m/s, the step's (positions moved by about velocities * dt during it)
        Returns ``(positions, velocities, mask)`` with new arrays for the first two and ``mask``
        (n,) bool of the points that were in contact.

        A step in which a point moves ``eps`` or more relative to a collider is checked at
        :meth:`substeps` times along the paths (``check_step``); a point caught part-way is
        responded there and moves on with its responded velocity for the rest of the step, so
        it cannot pass through a feature thinner than its step.
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
        end_positions = positions.copy()
        query_s = 0.0
        for j in range(1, count + 1):
            back = 1.0 - j / count  # fraction of the step after this check
            t_j = t - back * dt
            poses_j = poses if j == count else [c.pose(t_j) for c in self.colliders]
            points = end_positions[index] - back * velocities[index] * dt
            hit, q = self._respond(points, index, positions, velocities, poses_j, t_j, dt,
                                   (1.0 - back) * dt, back * dt)
            query_s += q
            mask[index[hit]] = True  # _respond wrote their positions and velocities
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

    def _respond(self, points, index, positions, velocities, poses, t: float, dt: float,
                 travelled_s: float, remaining_s: float):
        """Query ``points`` (the rows ``index`` at time ``t``, ``travelled_s`` into the step and
        ``remaining_s`` before its end), and for those within eps write the contact, moved on
        with the responded velocity for ``remaining_s``, and that velocity into ``positions`` /
        ``velocities`` (in place).
        Returns ``(hit (len(index),) bool, seconds spent in the query)``."""
        q0 = time.perf_counter()
        if len(self.colliders) == 1:
            result = self.client.query(self.colliders[0].model, points, fields=self.fields,
                                       pose=poses[0], eps=self.eps, only_colliding=self.only_colliding)
            which = None
        else:
            result = self.client.scene_query(
                [(c.model, p) for c, p in zip(self.colliders, poses)], points,
                fields=self.fields, eps=self.eps, only_colliding=self.only_colliding)
            which = np.asarray(result.collider)
        spent = time.perf_counter() - q0
        self.stats.query_s += spent
        self.stats.queries += 1
        self.stats.points_sent += len(index)
        hit = np.asarray(result.collides, dtype=bool)
        local_index = np.flatnonzero(hit)
        if not len(local_index):
            return hit, spent
        self.stats.deepest_m = min(self.stats.deepest_m, float(np.min(result.distance[local_index])))
        contact = np.asarray(result.contact)[local_index]
        # Collider velocity at the contact points, per collider (zero for static ones).
        v_col = np.zeros((len(local_index), 3))
        for k, (placement, pose) in enumerate(zip(self.colliders, poses)):
            if placement.static:
                continue
            rows = slice(None) if which is None else (which[local_index] == k)
            previous = placement.pose(t - dt)
            if not np.array_equal(previous, pose):
                v_col[rows] = collider_velocity(previous, pose, contact[rows], dt)
        rows = index[local_index]
        v_before = velocities[rows]
        if self.friction is None:
            v_after = v_col
        else:
            normal = np.asarray(result.normal)[local_index]
            v_after = respond_velocities(v_before, normal, np.ones(len(local_index), bool),
                                         self.friction, self.restitution, v_col)
        velocities[rows] = v_after
        # The step already moved the point along the surface with its old velocity; the response
        # changed that velocity, so take the tangential part of the change back from this step's
        # displacement too: a contact that sticks does not creep (it slid g sin(theta) dt^2 per
        # step on a slope). The normal part is the projection's job.
        normal = _unit_rows(contact - points[local_index])
        change = (v_after - v_before) * travelled_s
        change -= np.einsum("ij,ij->i", change, normal)[:, None] * normal
        positions[rows] = contact + change + v_after * remaining_s
        return hit, spent
