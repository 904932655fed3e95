"""Rigid poses: validation and the moves between the world frame and a collider's frame.

A pose is a 4x4 matrix ``T`` that maps collider-frame coordinates to world coordinates:
``p_world = T @ [p_collider, 1]``. Its upper-left block is ``s * R`` with ``R`` a rotation
(orthonormal, determinant +1) and ``s > 0`` an optional uniform scale. Reflections, shears and
non-uniform scales are rejected: they do not preserve distances, so no signed distance could be
reported for them.

All transforms run in float64 so that a collider far from the origin loses no precision.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

ORTHONORMAL_TOLERANCE = 1e-5
#: The coordinate range, world units (metres for the shipped models): query points (checked by
#: :func:`collider_contract.queries.check_points`: the first bad row named) and pose translations
#: (checked here: :class:`PoseError`, row and column named) beyond +-MAX_COORDINATE_M, an ``eps``
#: beyond it (:func:`collider_contract.queries.check_eps`), or any of them non-finite, are refused
#: with a ValueError saying which (the service answers 422). Inside it every answer is finite in float32: no Infinity, NaN or
#: zero normal. Why 1e6: a million model sizes away from any real collider, yet far from where
#: float32 overflows (3.4e38; squared distances overflow near 1e19). float32 points resolve only
#: 6 cm at 1e6: far scenes should send float64 points (poses are always float64).
MAX_COORDINATE_M = 1e6
#: A pose's uniform scale must lie in [1 / MAX_SCALE, MAX_SCALE]: beyond it distances in world
#: units could overflow float32 even for points inside the coordinate range.
MAX_SCALE = 1e6


class PoseError(ValueError):
    """A pose that is not a finite 4x4 rigid (optionally uniformly scaled) transform."""


@dataclass(frozen=True)
class Pose:
    """A validated collider pose: collider frame to world frame.

    rotation : (3, 3) float64, orthonormal, det +1
    translation : (3,) float64, world units
    scale : float, > 0, collider units to world units (1 for a rigid pose)
    source : (4, 4) float64, the matrix as the caller gave it (None for :data:`IDENTITY`): what
        travels on the wire, so that a server validating it gets this very pose, bit for bit
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0
    source: np.ndarray | None = field(default=None, compare=False, repr=False)

    @functools.cached_property  # (a frozen dataclass still has a __dict__ to cache in)
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
        if self.is_identity:  # the common case of a service query: a copy, no arithmetic
            return np.array(points, dtype=np.float64)
        local = rotate_rows(np.asarray(points, dtype=np.float64) - self.translation,
                            self.rotation.T)  # R^T (p - t)
        if self.scale != 1.0:
            local /= self.scale
        return local

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Collider-frame points (n, 3) to world-frame points (n, 3) float64: ``T p``."""
        if self.is_identity:
            return np.array(points, dtype=np.float64)
        return rotate_rows(np.asarray(points, dtype=np.float64) * self.scale, self.rotation) + self.translation

    def to_world_directions(self, vectors: np.ndarray) -> np.ndarray:
        """Collider-frame directions (n, 3) rotated into the world frame (no translation)."""
        if self.is_identity:
            return np.asarray(vectors)
        return rotate_rows(vectors, self.rotation)


def rotate_rows(vectors: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``vectors @ matrix.T`` for (n, 3) rows and a (3, 3) float64 ``matrix``, computed
    element-wise in a fixed order, so that each row's result is bit-identical whatever the batch
    around it (a BLAS matrix product picks its kernel by the batch's shape and may differ in the
    last bit)."""
    vectors = np.asarray(vectors)
    return (vectors[:, 0:1] * matrix[:, 0] + vectors[:, 1:2] * matrix[:, 1]
            + vectors[:, 2:] * matrix[:, 2])


IDENTITY = Pose(np.eye(3), np.zeros(3), 1.0)


#: The 8 corners of a box or cell as 0/1 offsets along x, y, z, (8, 3) int64: corner ``k`` takes
#: the high side on axis x if bit 0 of k is set, y if bit 1, z if bit 2. The one corner order of
#: the project (:func:`box_corners`, the grid networks' cells and their kernels).
CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=np.int64)
CORNERS.flags.writeable = False


def box_corners(lo, hi) -> np.ndarray:
    """(8, 3) float64: the corners of the axis-aligned box ``lo``..``hi`` in :data:`CORNERS`'
    order (corner ``k`` takes ``hi`` on axis x if bit 0 of k is set, y if bit 1, z if bit 2)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    return np.where(CORNERS == 1, hi, lo)


def transform_points(matrix, points) -> np.ndarray:
    """``points`` (n, 3) moved by a 4x4 ``matrix`` (any affine map, unvalidated: a mesh placement,
    a pose not yet checked): ``R p + t`` per row, float64."""
    m = np.asarray(matrix, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]


def as_pose(pose: Pose | np.ndarray | list | None) -> Pose:
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
        bad = [int(i) for i in np.argwhere(~np.isfinite(m))[0]]
        raise PoseError(f"pose contains NaN or Inf (first at row {bad[0]}, column {bad[1]})")
    far = np.abs(m[:3, 3]) > MAX_COORDINATE_M
    if far.any():
        raise PoseError(f"pose translation {m[:3, 3].tolist()} is outside the coordinate range "
                        f"+-{MAX_COORDINATE_M:g} (world units; row {int(np.argmax(far))}, column 3)")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise PoseError(f"pose bottom row must be [0, 0, 0, 1], got {m[3].tolist()}")
    block = m[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # entries near 1e300: refused just below
        gram = block.T @ block
    scale_sq = float(np.trace(gram) / 3.0)
    if not np.isfinite(scale_sq):
        raise PoseError(f"pose scale is outside [{1.0 / MAX_SCALE:g}, {MAX_SCALE:g}]: its 3x3 "
                        f"block has an entry of {np.abs(block).max():g}")
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
    if not 1.0 / MAX_SCALE <= scale <= MAX_SCALE:
        raise PoseError(f"pose scale {scale:g} is outside [{1.0 / MAX_SCALE:g}, {MAX_SCALE:g}]")
    if abs(scale - 1.0) < ORTHONORMAL_TOLERANCE:
        scale = 1.0
    rotation = block / scale
    # Re-orthonormalise so tiny float noise in the caller's matrix does not bend normals.
    u, _, vt = np.linalg.svd(rotation)
    rotation = u @ vt
    return Pose(rotation, m[:3, 3].copy(), scale, source=m.copy())
