"""Rigid poses: validation and the moves between the world frame and a collider's frame.

A pose is a 4x4 matrix ``T`` that maps collider-frame coordinates to world coordinates:
``p_world = T @ [p_collider, 1]``. Its upper-left block is ``s * R`` with ``R`` a rotation
(orthonormal, determinant +1) and ``s > 0`` an optional uniform scale. Reflections, shears and
non-uniform scales are rejected: they do not preserve distances, so no signed distance could be
reported for them.

All transforms run in float64 so that a collider far from the origin loses no precision.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ORTHONORMAL_TOLERANCE = 1e-5


class PoseError(ValueError):
    """A pose that is not a finite 4x4 rigid (optionally uniformly scaled) transform."""


@dataclass(frozen=True)
class Pose:
    """A validated collider pose: collider frame to world frame.

    rotation : (3, 3) float64, orthonormal, det +1
    translation : (3,) float64, world units
    scale : float, > 0, collider units to world units (1 for a rigid pose)
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0

    @property
    def is_identity(self) -> bool:
        return (
            self.scale == 1.0
            and np.array_equal(self.rotation, np.eye(3))
            and not self.translation.any()
        )

    def matrix(self) -> np.ndarray:
        """The pose as a (4, 4) float64 matrix."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """World-frame points (n, 3) to collider-frame points (n, 3) float64: ``T^-1 p``."""
        local = np.asarray(points, dtype=np.float64) - self.translation
        local = local @ self.rotation  # row-vector form of R^T (p - t)
        if self.scale != 1.0:
            local /= self.scale
        return local

    def to_world_directions(self, vectors: np.ndarray) -> np.ndarray:
        """Collider-frame directions (n, 3) rotated into the world frame (no translation)."""
        return vectors @ self.rotation.T


IDENTITY = Pose(np.eye(3), np.zeros(3), 1.0)


def as_pose(pose: "Pose | np.ndarray | list | None") -> Pose:
    """Validate ``pose`` (a 4x4 array-like, a :class:`Pose` or ``None`` for identity).

    Raises :class:`PoseError` naming what is wrong: shape, non-finite entries, a bottom row other
    than ``[0, 0, 0, 1]``, a non-orthonormal or reflecting rotation, or a non-uniform scale.
    """
    if pose is None:
        return IDENTITY
    if isinstance(pose, Pose):
        return pose
    try:
        m = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PoseError(f"pose must be a 4x4 matrix of numbers: {exc}") from None
    if m.shape != (4, 4):
        raise PoseError(f"pose must be a 4x4 matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise PoseError("pose contains NaN or Inf")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise PoseError(f"pose bottom row must be [0, 0, 0, 1], got {m[3].tolist()}")
    block = m[:3, :3]
    gram = block.T @ block
    scale_sq = float(np.trace(gram) / 3.0)
    if scale_sq <= 1e-24:
        raise PoseError("pose rotation block is zero (scale 0)")
    if not np.allclose(gram / scale_sq, np.eye(3), atol=ORTHONORMAL_TOLERANCE):
        raise PoseError(
            "pose is not rigid: its 3x3 block is not a rotation times a uniform scale "
            "(shear or non-uniform scale)"
        )
    if np.linalg.det(block) <= 0:
        raise PoseError("pose is a reflection (negative determinant); only rotations are allowed")
    scale = float(np.sqrt(scale_sq))
    if abs(scale - 1.0) < ORTHONORMAL_TOLERANCE:
        scale = 1.0
    rotation = block / scale
    # Re-orthonormalise so tiny float noise in the caller's matrix does not bend normals.
    u, _, vt = np.linalg.svd(rotation)
    rotation = u @ vt
    return Pose(rotation, m[:3, 3].copy(), scale)
