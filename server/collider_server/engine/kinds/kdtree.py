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

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..collider import Collider, ColliderInfo
from ..meshes import ExactSDF, Mesh

#: Points below which a query runs in the calling thread (threads cost more than they save).
POINTS_PER_THREAD = 16_384


def nearest_vertices(tree, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n,) distance to and (n,) index of the nearest vertex of ``tree`` (a SciPy cKDTree) for
    (n, 3) ``points``, in parallel on every core.

    The threads are this function's, each holding what it reads and writes, not SciPy's
    (``workers=-1``): an interrupt (Ctrl-C, SIGTERM) raised while SciPy waits for its threads
    left them running on memory the unwinding freed, and the process died of a segmentation
    fault (`collider bench` stopped during the kdtree's accuracy)."""
    threads = min(os.cpu_count() or 1, len(points) // POINTS_PER_THREAD)
    if threads <= 1:
        return tree.query(points)
    chunks = np.array_split(points, threads)
    with ThreadPoolExecutor(threads) as pool:
        found = list(pool.map(tree.query, chunks))
    return np.concatenate([d for d, _ in found]), np.concatenate([i for _, i in found])


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
        unsigned, index = nearest_vertices(self.tree, local)
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
