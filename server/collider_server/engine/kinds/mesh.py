"""The exact collider: queries on the triangle mesh itself (libigl AABB tree, float64), the sign
from the fast winding number so open meshes get a correct inside; where the mesh crosses itself
or buries a part, distances to its union's boundary (:class:`~collider_server.engine.meshes.ExactSDF`).
Exact everywhere, so points outside the domain box need no special rule; slower per point than
the voxel and neural kinds."""

from __future__ import annotations

import numpy as np

from ..collider import Collider, ColliderInfo
from ..meshes import ExactSDF, Mesh


class MeshCollider(Collider):
    """``tensors()``: ``vertices`` (v, 3) float64 and ``faces`` (f, 3) int32, collider frame."""

    kind = "mesh"
    chunk_points = 200_000
    clamps_to_domain = False
    gradient_in_one_pass = True

    def __init__(self, info: ColliderInfo, mesh: Mesh):
        super().__init__(info)
        self.mesh = mesh
        self.exact = ExactSDF(mesh)

    def evaluate(self, local, want_gradient):
        distance, closest, face = self.exact.query(local)
        if not want_gradient:
            return distance, None
        return distance, self.exact.gradient(local, distance, closest, face)

    def tensors(self):
        return {
            "vertices": np.asarray(self.mesh.vertices, dtype=np.float64),
            "faces": np.asarray(self.mesh.faces, dtype=np.int32),
        }

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        if set(tensors) != {"vertices", "faces"}:
            raise ValueError(f"mesh model must hold 'vertices' and 'faces', found {sorted(tensors)}")
        vertices = np.asarray(tensors["vertices"], dtype=np.float64)
        faces = np.asarray(tensors["faces"], dtype=np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"mesh arrays have wrong shapes: vertices {vertices.shape}, faces {faces.shape}")
        if len(faces) == 0:
            raise ValueError("mesh model holds no faces")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError("mesh faces index vertices that do not exist")
        return cls(info, Mesh(vertices, faces, info.source.get("mesh", "mesh")))
