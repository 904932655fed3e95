"""The paper's acceleration-structure baseline, and APPROXIMATE by design: the nearest mesh
*vertex* (SciPy cKDTree, parallel queries) stands in for the closest surface point.

distance : |p - v| signed by the side of v's normal the point lies on; always >= the exact
    unsigned distance, off by up to about half the edge length near the surface;
normal : the area-weighted normal of the nearest vertex.

The vertices are those of the boundary every kind answers against
(:class:`~collider_server.engine.meshes.ExactSDF`): for a mesh that passes through itself, the
union's (its cut cells' corners in, the vertices buried inside the body out), so that no point
is answered by a vertex inside the body.
"""

from __future__ import annotations

import numpy as np

from ..collider import Collider, ColliderInfo
from ..meshes import ExactSDF, Mesh


def vertex_normals(mesh: Mesh) -> np.ndarray:
    """(v, 3) unit area-weighted vertex normals (outward for a consistently oriented mesh)."""
    tri = mesh.vertices[mesh.faces]
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    normals = np.zeros_like(mesh.vertices)
    for corner in range(3):
        np.add.at(normals, mesh.faces[:, corner], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


class KDTreeCollider(Collider):
    """``tensors()``: ``vertices`` (v, 3) float64 and ``normals`` (v, 3) float64."""

    kind = "kdtree"
    chunk_points = 500_000
    clamps_to_domain = False

    def __init__(self, info: ColliderInfo, vertices: np.ndarray, normals: np.ndarray):
        super().__init__(info)
        from scipy.spatial import cKDTree

        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.normals = np.asarray(normals, dtype=np.float64)
        self.tree = cKDTree(self.vertices)

    @classmethod
    def from_mesh(cls, info: ColliderInfo, mesh: Mesh) -> KDTreeCollider:
        union = ExactSDF(mesh).union
        if union is None:
            return cls(info, mesh.vertices, vertex_normals(mesh))
        boundary = Mesh(union.vertices, union.faces, mesh.name, mesh.sha256)
        kept = np.unique(union.faces)  # the mesh's buried vertices are on no kept face
        return cls(info, union.vertices[kept], vertex_normals(boundary)[kept])

    def evaluate(self, local, want_gradient):
        unsigned, index = self.tree.query(local, workers=-1)
        side = np.einsum("ij,ij->i", local - self.vertices[index], self.normals[index])
        distance = np.where(side < 0, -unsigned, unsigned)
        return distance, (self.normals[index] if want_gradient else None)

    def tensors(self):
        return {"vertices": self.vertices, "normals": self.normals}

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        if set(tensors) != {"vertices", "normals"}:
            raise ValueError(f"kdtree model must hold 'vertices' and 'normals', found {sorted(tensors)}")
        if tensors["vertices"].shape != tensors["normals"].shape or tensors["vertices"].shape[1:] != (3,):
            raise ValueError("kdtree vertices and normals must both be (v, 3)")
        if len(tensors["vertices"]) == 0:
            raise ValueError("kdtree model holds no vertices")
        return cls(info, tensors["vertices"], tensors["normals"])
