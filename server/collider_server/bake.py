"""Make a collider from a mesh: ``voxel`` (baked grid), ``mesh`` (exact) or ``kdtree``.
(``neural`` colliders are trained, see :mod:`collider_server.training`.)"""

from __future__ import annotations

import numpy as np

from .collider import Collider, ColliderInfo
from .kinds import KDTreeCollider, MeshCollider, VoxelCollider
from .kinds.voxel import bake_grid, padded_box
from .meshes import ExactSDF, Mesh

BAKED_KINDS = ("voxel", "mesh", "kdtree")


def mesh_source(mesh: Mesh, transform: np.ndarray | None = None) -> dict:
    """Metadata describing the source mesh (stored in ``ColliderInfo.source``)."""
    return {
        "mesh": mesh.name,
        "sha256": mesh.sha256,
        "vertices": int(len(mesh.vertices)),
        "faces": int(len(mesh.faces)),
        "transform": (np.eye(4) if transform is None else np.asarray(transform)).tolist(),
    }


def bake_collider(mesh: Mesh, kind: str, name: str, *, resolution: int = 256, padding: float = 0.1,
                  units: str = "m", meters_per_unit: float = 1.0, device: str | None = None,
                  show_progress: bool = True) -> Collider:
    """Build a ``kind`` collider named ``name`` from ``mesh`` (in its own units and frame).

    resolution : voxel samples per axis (voxel only)
    padding : fraction of the largest side added around the mesh's box (the domain)
    """
    if kind not in BAKED_KINDS:
        raise ValueError(f"cannot bake kind {kind!r}; bake one of {list(BAKED_KINDS)} (neural is trained)")
    # Checked before any work: a bad padding would otherwise surface only after the bake.
    if not (np.isfinite(padding) and padding >= 0):
        raise ValueError(f"padding must be a finite number >= 0 (fraction of the largest side), got {padding}")
    lo, hi = padded_box(mesh, padding)
    info = ColliderInfo(
        name=name, kind=kind, domain_min=lo.tolist(), domain_max=hi.tolist(), units=units,
        meters_per_unit=meters_per_unit, source=mesh_source(mesh),
        settings={"padding": padding}, approximate=(kind == "kdtree"),
    )
    if kind == "mesh":
        return MeshCollider(info, mesh)
    if kind == "kdtree":
        return KDTreeCollider.from_mesh(info, mesh)
    info.settings["resolution"] = resolution
    grid = bake_grid(ExactSDF(mesh), lo, hi, resolution, show_progress=show_progress)
    return VoxelCollider(info, grid, device)
