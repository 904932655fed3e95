"""The exact collider of a deforming mesh (kind ``mesh`` with an ``animation``): at any time, the
exact signed distance to the linearly interpolated vertices (libigl AABB tree built per distinct
time and cached, :class:`~collider_server.engine.animated_meshes.ExactAtTimes`; the sign from the
fast winding number; where the mesh crosses itself at that time, distances to its union's
boundary) and the surface's velocity at each point's closest surface point: the interpolated
vertex velocities weighted by the closest point's barycentric coordinates in the mesh's triangle
it lies in (collider units per second, collider frame). Exact everywhere, no domain rule."""

from __future__ import annotations

import numpy as np

from collider_contract import Timeline

from ..animated_meshes import AnimatedMesh, ExactAtTimes
from ..collider import Collider, ColliderInfo
from ..meshes import barycentric


class AnimatedMeshCollider(Collider):
    """``tensors()``: ``frames`` (F, v, 3) float64 and ``faces`` (f, 3) int32, collider frame;
    ``info.animation`` is its :class:`~collider_contract.Timeline`."""

    kind = "mesh"
    chunk_points = 200_000
    clamps_to_domain = False
    gradient_in_one_pass = True

    def __init__(self, info: ColliderInfo, animation: AnimatedMesh):
        super().__init__(info)
        self.animation = animation
        self.exact = ExactAtTimes(animation)

    def evaluate(self, local, want_gradient):
        distance, gradient, _ = self.evaluate_at(local, want_gradient, 0.0)
        return distance, gradient

    def evaluate_at(self, local, want_gradient, time):
        exact, k, rate = self.exact.at(0.0 if time is None else time)
        distance, closest, face = exact.query(local)
        if not want_gradient:
            return distance, None, None
        gradient = exact.gradient(local, distance, closest, face)
        if rate == 0.0:
            return distance, gradient, np.zeros_like(closest)
        corners = self.animation.faces[face]  # (m, 3) vertex indices
        weights = barycentric(closest, exact.mesh.vertices[corners])
        frames = self.animation.frames
        step = frames[k + 1] - frames[k]  # (v, 3) displacement over the segment
        velocity = np.einsum("mj,mjc->mc", weights, step[corners]) * rate
        return distance, gradient, velocity

    def tensors(self):
        return {"frames": np.asarray(self.animation.frames, dtype=np.float64),
                "faces": np.asarray(self.animation.faces, dtype=np.int32)}

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        if set(tensors) != {"frames", "faces"}:
            raise ValueError(f"animated mesh model must hold 'frames' and 'faces', found {sorted(tensors)}")
        frames = np.asarray(tensors["frames"], dtype=np.float64)
        faces = np.asarray(tensors["faces"], dtype=np.int64)
        if frames.ndim != 3 or frames.shape[2] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"animated mesh arrays have wrong shapes: frames {frames.shape}, "
                             f"faces {faces.shape}")
        if len(faces) == 0:
            raise ValueError("mesh model holds no faces")
        if faces.min() < 0 or faces.max() >= frames.shape[1]:
            raise ValueError("mesh faces index vertices that do not exist")
        if not np.isfinite(frames).all():
            raise ValueError("animated mesh frames hold NaN or Inf")
        timeline = Timeline.from_dict(info.animation)
        source = info.source
        return cls(info, AnimatedMesh(frames, faces, timeline, source.get("mesh", "mesh"),
                                      source.get("sha256", ""), source.get("cache", ""),
                                      source.get("cache_sha256", "")))
