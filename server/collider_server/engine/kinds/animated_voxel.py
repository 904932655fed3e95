"""Keyframe grids of a deforming shape (kind ``voxel`` with an ``animation``): one grid of exact
signed distances per keyframe, read by trilinear interpolation in space and linear
interpolation in time.

At time t between keyframes k and k + 1 (fraction u): ``f = (1 - u) f_k + u f_{k+1}``, its
gradient likewise, and ``df/dt = (f_{k+1} - f_k) * rate``. The surface's velocity is its normal
speed ``-df/dt`` along the unit normal (the velocity of the level set, for a gradient of unit
length); an implicit surface does not say how its points slide along it, so the tangential part
is zero.
"""

from __future__ import annotations

import numpy as np

from collider_contract import Timeline

from ..collider import ColliderInfo
from .voxel import VoxelCollider


def normal_velocity(gradient: np.ndarray, dfdt: np.ndarray) -> np.ndarray:
    """The velocity (m, 3) of an SDF's surface from its gradient (m, 3) and time derivative
    ``dfdt`` (m,) (collider units per second): the normal speed ``-df/dt`` along the unit normal,
    no tangential part (zero where the gradient vanishes)."""
    length = np.linalg.norm(gradient, axis=1, keepdims=True)
    normal = gradient / np.where(length > 0, length, 1.0)
    return -np.asarray(dfdt)[:, None] * normal


class AnimatedVoxelCollider(VoxelCollider):
    """``tensors()["grids"]``: (K, R, R, R) float32, one grid per keyframe, [x, y, z];
    ``info.animation`` is the keyframes' :class:`~collider_contract.Timeline`."""

    def __init__(self, info: ColliderInfo, grids: np.ndarray, device: str | None = None):
        grids = np.asarray(grids, dtype=np.float32)
        if grids.ndim != 4:
            raise ValueError(f"voxel keyframe grids must be (K, R, R, R), got {list(grids.shape)}")
        self.timeline = Timeline.from_dict(info.animation)
        if len(grids) != self.timeline.frames:
            raise ValueError(f"{len(grids)} keyframe grids, but the animation has "
                             f"{self.timeline.frames} frames")
        super().__init__(info, grids[0], device)
        self._grids = self._torch.as_tensor(grids, device=self._device).reshape(len(grids), -1)
        self._grid = self._grids[0]  # :meth:`evaluate` (the first frame) reads keyframe 0

    @property
    def keyframes(self) -> int:
        return int(self._grids.shape[0])

    def evaluate_at(self, local, want_gradient, time):
        k, u, rate = self.timeline.locate(0.0 if time is None else time)
        index, t = self._cells(local)
        d0, g0 = self._trilinear(self._grids[k], index, t, want_gradient)
        d1, g1 = self._trilinear(self._grids[k + 1], index, t, want_gradient)
        distance = d0 + u * (d1 - d0)
        if not want_gradient:
            return distance, None, None
        gradient = g0 + u * (g1 - g0)
        return distance, gradient, normal_velocity(gradient, (d1 - d0) * rate)

    def tensors(self):
        return {"grids": self._grids.reshape(-1, *self._shape).cpu().numpy()}

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        if set(tensors) != {"grids"}:
            raise ValueError(f"animated voxel model must hold exactly one tensor 'grids', found "
                             f"{sorted(tensors)}")
        return cls(info, tensors["grids"], device)
