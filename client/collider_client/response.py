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

from ._models import ModelInfo

__all__ = [
    "project_to_contacts",
    "respond_velocities",
    "collider_velocity",
    "world_box",
    "ColliderPlacement",
    "CollisionHook",
    "HookStats",
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
    before = points @ relative[:3, :3].T + relative[:3, 3]
    return (points - before) / dt


def world_box(info: ModelInfo, pose: np.ndarray | None, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """World-frame axis-aligned box (lo, hi) holding the model's domain box moved by ``pose``
    and grown by ``margin`` metres on every side. Outside it no point can collide."""
    lo, hi = np.asarray(info.domain_min, float), np.asarray(info.domain_max, float)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    if pose is not None:
        pose = np.asarray(pose, dtype=np.float64)
        corners = corners @ pose[:3, :3].T + pose[:3, 3]
    return corners.min(axis=0) - margin, corners.max(axis=0) + margin


@dataclass
class ColliderPlacement:
    """A collider in a simulation: a model name and its pose over time.

    pose_at : function of time (s) -> (4, 4) collider -> world, or None for a static identity pose
    """

    model: str
    pose_at: Callable[[float], np.ndarray] | None = None

    def pose(self, t: float) -> np.ndarray:
        return np.eye(4) if self.pose_at is None else np.asarray(self.pose_at(t), dtype=np.float64)


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

    Call :meth:`apply` after each integration step (or substep). Only points inside a collider's
    inflated world box are sent, and only the fields the response needs are asked for.
    """

    def __init__(self, client, colliders: Sequence[ColliderPlacement], eps: float = 1e-3,
                 friction: float | None = None, restitution: float = 0.0,
                 infos: dict[str, ModelInfo] | None = None, cull: bool = True,
                 only_colliding: bool = True):
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

    def apply(self, positions: np.ndarray, velocities: np.ndarray, t: float, dt: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Respond to contacts at time ``t`` (the poses at ``t``; ``dt`` for collider velocity).

        positions : (n, 3) float, metres, world frame; velocities : (n, 3) float, m/s
        Returns ``(positions, velocities, mask)`` with new arrays for the first two and ``mask``
        (n,) bool of the points that were in contact.
        """
        started = time.perf_counter()
        positions = np.asarray(positions)
        n = len(positions)
        poses = [c.pose(t) for c in self.colliders]
        margin = self.eps + 1e-9
        near = np.full(n, not self.cull)
        for placement, pose in zip(self.colliders, poses) if self.cull else ():
            lo, hi = world_box(self.infos[placement.model], pose, margin)
            near |= np.all((positions >= lo) & (positions <= hi), axis=1)
        index = np.flatnonzero(near)
        self.stats.calls += 1
        self.stats.points_total += n
        mask = np.zeros(n, dtype=bool)
        if not len(index):
            self.stats.colliding_last = 0
            self.stats.response_s += time.perf_counter() - started
            return positions, velocities, mask
        points = positions[index]
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
        q1 = time.perf_counter()
        self.stats.query_s += q1 - q0
        self.stats.queries += 1
        self.stats.points_sent += len(index)
        hit = np.asarray(result.collides, dtype=bool)
        local_index = np.flatnonzero(hit)
        mask[index[local_index]] = True
        positions = np.array(positions, copy=True)
        velocities = np.array(velocities, dtype=np.float64, copy=True)
        if len(local_index):
            self.stats.deepest_m = min(self.stats.deepest_m,
                                       float(np.min(result.distance[local_index])))
            contact = np.asarray(result.contact)[local_index]
            # Collider velocity at the contact points, per collider (zero for static ones).
            v_col = np.zeros((len(local_index), 3))
            for k, (placement, pose) in enumerate(zip(self.colliders, poses)):
                if placement.pose_at is None:
                    continue
                rows = slice(None) if which is None else (which[local_index] == k)
                before = placement.pose(t - dt)
                if not np.array_equal(before, pose):
                    v_col[rows] = collider_velocity(before, pose, contact[rows], dt)
            positions[index[local_index]] = contact
            if self.friction is None:
                velocities[index[local_index]] = v_col
            else:
                normal = np.asarray(result.normal)[local_index]
                velocities[index[local_index]] = respond_velocities(
                    velocities[index[local_index]], normal, np.ones(len(local_index), bool),
                    self.friction, self.restitution, v_col)
        self.stats.colliding_last = len(local_index)
        self.stats.colliding_max = max(self.stats.colliding_max, len(local_index))
        self.stats.response_s += (time.perf_counter() - started) - (q1 - q0)
        return positions, velocities, mask
