"""Where a scene's colliders are and how they move: :class:`ColliderSpec` (a model, its placement,
its :class:`Motion` and, animated, how the scene's time maps to its animation's) and
:func:`pose_function`, its pose at any time (4x4, collider frame -> world frame, metres and
seconds)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Motion:
    """How a collider moves. kind: "static", "velocity" (constant linear and angular velocity,
    world frame, about the collider's origin) or "keyframes" (piecewise linear)."""

    kind: str = "static"
    velocity_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular_velocity_deg_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    times_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    positions_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rotations_deg: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass
class ColliderSpec:
    """A scene's collider: its model, placement and motion; for an animated model, the offset
    added to the simulation time (seconds) and a loop override (None: the model's own), and
    the command that makes the model when it is not shipped (said when it is missing); for a
    skinned model, the clip it plays (None: its first)."""

    model: str
    position_m: np.ndarray
    rotation_deg: np.ndarray  # extrinsic x, then y, then z (degrees), collider -> world
    motion: Motion
    time_offset_s: float = 0.0
    loop: bool | None = None
    make: str | None = None
    clip: str | None = None


def euler_matrix(rotation_deg: np.ndarray) -> np.ndarray:
    """(3, 3) rotation: about x, then y, then z (extrinsic), angles in degrees."""
    ax, ay, az = np.radians(rotation_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def axis_angle_matrix(rotation_vector_rad: np.ndarray) -> np.ndarray:
    """(3, 3) rotation by ``|r|`` radians about ``r / |r|`` (Rodrigues)."""
    angle = float(np.linalg.norm(rotation_vector_rad))
    if angle < 1e-15:
        return np.eye(3)
    k = np.asarray(rotation_vector_rad) / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def pose_function(spec: ColliderSpec):
    """``t -> (4, 4)`` collider -> world pose for a collider spec, or None when it never moves
    from the identity (static with no placement)."""
    base = np.eye(4)
    base[:3, :3] = euler_matrix(spec.rotation_deg)
    base[:3, 3] = spec.position_m
    motion = spec.motion
    if motion.kind == "static":
        return lambda t: base

    if motion.kind == "velocity":
        def at(t: float) -> np.ndarray:
            m = np.eye(4)
            m[:3, :3] = axis_angle_matrix(np.radians(motion.angular_velocity_deg_s) * t) @ base[:3, :3]
            m[:3, 3] = base[:3, 3] + motion.velocity_m_s * t
            return m
        return at

    def keyed(t: float) -> np.ndarray:
        # Keyframes are offsets added to the base placement, linear in time, held at the ends.
        times = motion.times_s
        position = np.array([np.interp(t, times, motion.positions_m[:, i]) for i in range(3)])
        rotation = np.array([np.interp(t, times, motion.rotations_deg[:, i]) for i in range(3)])
        m = np.eye(4)
        m[:3, :3] = euler_matrix(rotation) @ base[:3, :3]
        m[:3, 3] = base[:3, 3] + position
        return m
    return keyed
