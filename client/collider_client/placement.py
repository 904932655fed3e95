"""Where a collider is in a simulation and when its animation is (numpy only): a
:class:`ColliderPlacement` (a model, its pose over time, its time offset and loop), the animation
time it is asked at (:func:`animation_time`), and the world box outside which no point can touch
it (:func:`world_box`). World frame, metres, seconds."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from collider_contract import ModelInfo, Timeline, transform_points

__all__ = ["ColliderPlacement", "animation_time", "world_box"]


def world_box(info: ModelInfo, pose: np.ndarray | None, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """World-frame axis-aligned box (lo, hi) holding the model's domain box moved by ``pose``
    and grown by ``margin`` metres on every side. Outside it no point can collide."""
    corners = info.domain_corners()
    if pose is not None:
        corners = transform_points(pose, corners)
    return corners.min(axis=0) - margin, corners.max(axis=0) + margin


@dataclass
class ColliderPlacement:
    """A collider in a simulation: a model name, its pose over time and, for an animated model,
    how the simulation's time maps to the animation's.

    pose_at : function of time (s) -> (4, 4) collider -> world; or a fixed (4, 4) pose (array or
        nested lists) for a static collider; or None for the identity
    time_offset_s : an animated model is asked at the simulation time plus this (seconds)
    loop : None: the model's own loop or clamp; True / False: loop or clamp it here whatever it
        was baked with (:class:`~collider_contract.Timeline`)
    clip : a skinned model's clip (a name; None: its first), asked at the animation time; only
        for skinned models (:meth:`~collider_contract.ModelInfo.clip_timeline`)
    """

    model: str
    pose_at: Callable[[float], np.ndarray] | np.ndarray | None = None
    time_offset_s: float = 0.0
    loop: bool | None = None
    clip: str | None = None

    def __post_init__(self):
        if self.pose_at is not None and not callable(self.pose_at):
            fixed = np.asarray(self.pose_at, dtype=np.float64)
            if fixed.shape != (4, 4) or not np.isfinite(fixed).all():
                raise ValueError(f"ColliderPlacement({self.model!r}): pose must be a function of "
                                 f"time or a finite 4x4 matrix, got shape {fixed.shape}")
            self.pose_at = lambda t, _fixed=fixed: _fixed
            self.static = True
        else:
            self.static = self.pose_at is None
        offset = self.time_offset_s
        if isinstance(offset, bool) or not isinstance(offset, (int, float)) or not np.isfinite(offset):
            raise ValueError(f"ColliderPlacement({self.model!r}): time_offset_s must be a finite "
                             f"number of seconds, got {offset!r}")
        if self.loop is not None and not isinstance(self.loop, bool):
            raise ValueError(f"ColliderPlacement({self.model!r}): loop must be None, True or "
                             f"False, got {self.loop!r}")
        if self.clip is not None and (not isinstance(self.clip, str) or not self.clip):
            raise ValueError(f"ColliderPlacement({self.model!r}): clip must be None or a clip's "
                             f"name, got {self.clip!r}")

    def pose(self, t: float) -> np.ndarray:
        if self.pose_at is None:
            return np.eye(4)
        assert callable(self.pose_at)  # __post_init__ made a fixed pose a function
        return np.asarray(self.pose_at(t), dtype=np.float64)

    def pose_velocity(self, t: float, dt: float) -> np.ndarray | None:
        """The pose's time derivative at ``t`` (4x4; 1/s and m/s), the backward difference over
        ``dt``; None for a static collider."""
        if self.static:
            return None
        return (self.pose(t) - self.pose(t - dt)) / dt


def animation_time(placement: ColliderPlacement, timeline: Timeline | None,
                   t: float) -> tuple[float | None, bool]:
    """When ``placement``'s model is asked at simulation time ``t``: ``(time, held)``, the
    animation's time in seconds (None: a static model) and whether an end frame is held there
    (clamped beyond the ends: the surface's own velocity is zero). ``timeline`` is the model's
    (``ModelInfo.timeline``, or a skinned model's ``ModelInfo.clip_timeline``), the placement's
    ``loop`` overrides its loop."""
    if timeline is None:
        return None, False
    raw = t + placement.time_offset_s
    own = timeline.with_loop(placement.loop)
    local, held = own.local_time(raw), own.held(raw)
    if held and timeline.loop and local >= own.duration_s:
        # Clamped here but looping in the model, which starts over at its duration: ask it a
        # hair before (1e-12 of the animation: far below any length that matters).
        local = own.duration_s * (1.0 - 1e-12)
    return local, held
