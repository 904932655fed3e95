"""Collision response physics (numpy only), what a simulator applies after its own integration
step; world frame, metres, velocities in m/s; ``mask`` arrays select the colliding points:

- :func:`project_to_contacts` moves colliding points onto their contact points;
- :func:`respond_velocities` removes the normal velocity into the collider (times ``1 +
  restitution``) and applies Coulomb friction to the tangential part, relative to the velocity
  of the collider's surface (moving and animated colliders);
- :func:`collider_velocity` is a rigidly moving collider's velocity, from two successive poses.
"""

from __future__ import annotations

import numpy as np

from collider_contract import transform_points

__all__ = ["collider_velocity", "project_to_contacts", "respond_velocities"]


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


def unit_rows(vectors: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length; zero rows stay zero."""
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return vectors / np.where(length > 0, length, 1.0)
