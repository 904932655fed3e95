"""Penetration of simulated frames measured against exact mesh SDFs (needs the engine extras)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .scene import Scene, pose_function


def exact_penetration(scene: Scene, frames: list, meshes: dict[str, Path],
                      transforms: dict[str, np.ndarray] | None = None) -> dict:
    """Deepest penetration (metres, >= 0) of any vertex in any frame into each collider's exact
    mesh (``meshes``: model name -> mesh file), at the frame's pose.

    transforms : model name -> (4, 4) placing the mesh file in the collider frame: the model's
        ``source.transform`` (the scale / Z-up it was made with, see
        :class:`collider_server.making.placement.MeshPlacement`); absent: the file is in that frame

    Returns ``{"max_depth_m": ..., "min_distance_m": ..., "frames": ..., "by_model": {model:
    depth_m}}``; ``min_distance_m`` is the smallest signed distance of any vertex (negative:
    inside), which shows how close the cloth came (about eps when it rests on the collider).
    """
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.mesh_files import load_mesh

    by_model = {}
    closest = float("inf")
    for spec in scene.colliders:
        if spec.model not in meshes:
            continue
        mesh = load_mesh(meshes[spec.model])
        transform = (transforms or {}).get(spec.model)
        if transform is not None and not np.allclose(transform, np.eye(4)):
            mesh = mesh.transformed(transform)
        sdf = ExactSDF(mesh)
        pose_at = pose_function(spec)
        worst = 0.0
        for t, vertices in frames:
            pose = pose_at(t)
            local = (vertices - pose[:3, 3]) @ pose[:3, :3]  # float64: the pose is
            distance = sdf.query(local)[0]
            worst = max(worst, float(-distance.min()))
            closest = min(closest, float(distance.min()))
        by_model[spec.model] = max(by_model.get(spec.model, 0.0), worst)
    unknown = sorted(set(meshes) - {s.model for s in scene.colliders})
    if unknown:
        raise ValueError(f"--check-mesh names model(s) {unknown} that the scene does not use")
    return {"max_depth_m": max(by_model.values(), default=0.0), "min_distance_m": closest,
            "frames": len(frames),
            "by_model": by_model}
