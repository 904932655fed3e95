"""Mesh placement: how a mesh file's coordinates become a collider's frame and units.

One definition for every command that reads a mesh or an animation (``bake``, ``train``,
``eval``, ``bench``, ``view``, ``simulate --check-mesh``): an optional Y-up to Z-up rotation (the paper's frame), then a
uniform scale (``scale``, or ``fit_size``: the scale that makes the largest side that long), then
the unit the scaled coordinates are in. The argparse side is
:mod:`collider_cli.commands.options`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..engine.animated_meshes import AnimatedMesh
from ..engine.meshes import Mesh
from ..engine.skinning import Channel, Clip, Skeleton, Skin

#: Rotation taking a Y-up mesh to Z-up (x stays, y becomes z, z becomes -y).
Y_UP_TO_Z_UP = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)

#: Metres in one unit, for the unit names ``--units`` knows without ``--meters-per-unit``.
UNIT_METERS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "um": 1e-6, "km": 1000.0, "in": 0.0254, "ft": 0.3048}


def meters_per_unit(units: str, explicit: float | None = None) -> float:
    """Metres in one ``units`` (``explicit`` wins when given; it must be finite and > 0)."""
    if explicit is not None:
        if not (math.isfinite(explicit) and explicit > 0):
            raise ValueError(f"--meters-per-unit must be a finite number > 0, got {explicit}")
        return float(explicit)
    if units not in UNIT_METERS:
        raise ValueError(f"unknown --units {units!r}; give --meters-per-unit or one of {sorted(UNIT_METERS)}")
    return UNIT_METERS[units]


@dataclass(frozen=True)
class MeshPlacement:
    """Where a mesh file's coordinates go before a collider is made from them.

    scale : multiply the (rotated) coordinates by this; ignored when ``fit_size`` is given
    fit_size : scale so that the largest side of the box is this long (in ``units``)
    z_up : rotate a Y-up file to Z-up first (about the file's origin)
    units : unit of the placed coordinates (the collider's unit), e.g. "m", "mm"
    meters_per_unit_override : metres in one unit for units :data:`UNIT_METERS` does not know
    """

    scale: float = 1.0
    fit_size: float | None = None
    z_up: bool = False
    units: str = "m"
    meters_per_unit_override: float | None = None

    def check(self) -> None:
        """Raise ValueError naming the option when a number is not finite and > 0."""
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"--scale must be a finite number > 0, got {self.scale}")
        if self.fit_size is not None and not (math.isfinite(self.fit_size) and self.fit_size > 0):
            raise ValueError(f"--fit-size must be a finite number > 0, got {self.fit_size}")
        meters_per_unit(self.units, self.meters_per_unit_override)

    @property
    def meters_per_unit(self) -> float:
        return meters_per_unit(self.units, self.meters_per_unit_override)

    def transform(self, mesh: Mesh) -> np.ndarray:
        """(4, 4) float64 similarity from the file's coordinates to the collider frame."""
        self.check()
        rotation = Y_UP_TO_Z_UP.copy() if self.z_up else np.eye(4)
        scale = self.scale
        if self.fit_size is not None:
            # The largest side is the same before and after the axis permutation.
            scale = self.fit_size / float(np.ptp(mesh.vertices, axis=0).max())
        return np.diag([scale, scale, scale, 1.0]) @ rotation

    @staticmethod
    def z_up_of(transform) -> bool:
        """Whether the placement that made ``transform`` (a model's stored
        ``source["transform"]``, 4x4) had ``z_up``: its rotation, the uniform scale divided out,
        is :data:`Y_UP_TO_Z_UP`'s. A plain scale (``--scale``, ``--fit-size``) is not."""
        block = np.asarray(transform, dtype=np.float64)[:3, :3]
        scale = float(np.cbrt(np.linalg.det(block)))
        return scale > 0 and bool(np.allclose(block / scale, Y_UP_TO_Z_UP[:3, :3], atol=1e-9))

    def apply(self, mesh: Mesh) -> tuple[Mesh, np.ndarray]:
        """The placed mesh and the transform applied (stored in the model's ``source``)."""
        transform = self.transform(mesh)
        if np.allclose(transform, np.eye(4)):
            return mesh, np.eye(4)
        return mesh.transformed(transform), transform

    def apply_to_skin(self, skin: Skin) -> tuple[Skin, np.ndarray]:
        """``skin`` placed by one transform (``fit_size`` measures the bind pose), and that
        transform: every pose of the placed skin is the placed pose of the file's skin."""
        transform = self.transform(Mesh(skin.vertices, skin.faces))
        if np.allclose(transform, np.eye(4)):
            return skin, np.eye(4)
        return transformed_skin(skin, transform), transform

    def apply_to_animation(self, animation: AnimatedMesh) -> tuple[AnimatedMesh, np.ndarray]:
        """Every frame of ``animation`` placed by one transform (``fit_size`` measures the first
        frame), and that transform."""
        transform = self.transform(animation.frame(0))
        if np.allclose(transform, np.eye(4)):
            return animation, np.eye(4)
        return animation.transformed(transform), transform


def transformed_skin(skin: Skin, matrix: np.ndarray) -> Skin:
    """``skin`` moved by the similarity ``matrix`` (4, 4) = ``[s R | t]``: its vertices, and a
    skeleton whose every pose skins to ``matrix`` applied to the original's.

    The uniform scale ``s`` goes into the translations (rest and keyframed), so the joints'
    world transforms stay rigid (``M W S^-1`` for a world transform ``W``, ``S`` the scale):
    ``root -> M root S^-1``, a local ``L -> S L S^-1`` (its translation times ``s``), an inverse
    bind ``B -> S B M^-1``; then ``(M W S^-1)(S B M^-1) = M (W B) M^-1``. A reflection (a
    negative determinant) turns the faces over."""
    m = np.asarray(matrix, dtype=np.float64)
    scale = float(np.cbrt(np.linalg.det(m[:3, :3])))
    s_matrix, s_inverse = np.diag([scale, scale, scale, 1.0]), np.diag([1 / scale] * 3 + [1.0])
    skeleton = skin.skeleton
    placed = Skeleton(skeleton.names, skeleton.parents, skeleton.rest_translation * scale,
                      skeleton.rest_rotation, skeleton.rest_scale,
                      s_matrix @ skeleton.inverse_bind @ np.linalg.inv(m),
                      m @ skeleton.root @ s_inverse)
    clips = tuple(Clip(c.name, tuple(
        Channel(ch.joint, ch.path, ch.interpolation, ch.times,
                ch.values * scale if ch.path == "translation" else ch.values)
        for ch in c.channels), c.duration_s) for c in skin.clips)
    vertices = skin.vertices @ m[:3, :3].T + m[:3, 3]
    faces = skin.faces if scale > 0 else skin.faces[:, ::-1].copy()
    return Skin(vertices, faces, skin.joints, skin.weights, placed, clips)
