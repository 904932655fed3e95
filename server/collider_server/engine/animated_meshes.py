"""Triangle meshes that move and deform with a fixed topology, and their exact signed distance at
any time.

An :class:`AnimatedMesh` is F frames of vertex positions over one set of faces, run in time by a
:class:`~collider_contract.Timeline` (frame k at ``k / frame_rate_hz`` seconds; loop or clamp
beyond the ends). Between two frames the surface is the linear interpolation of the vertex
positions: the ground truth at any time ``t``, and what the ``mesh`` kind answers. Its units
and frame are its own (the collider frame once placed).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from collider_contract import Timeline
from collider_contract.animation import segment_at

from .kept import Kept
from .meshes import ExactSDF, Mesh, edge_index


@dataclass(frozen=True)
class AnimatedMesh:
    """Frames of a deforming mesh.

    frames : (F, v, 3) float64 vertex positions per frame, its units and frame
    faces : (f, 3) int64 indices into the vertices (the same at every frame)
    timeline : when the frames are (rate, loop or clamp)
    name : the mesh file's stem; sha256 : the mesh file's digest ("" for a generated one)
    cache, cache_sha256 : the vertex cache's file name (a PC2 file or an OBJ pattern) and digest
    cache_timing : a PC2 cache's header: (start frame, sample rate), recorded, not applied (the
        frames play at ``timeline.frame_rate_hz``; docs/animation.md); None for other sources
    """

    frames: np.ndarray
    faces: np.ndarray
    timeline: Timeline
    name: str = "animation"
    sha256: str = ""
    cache: str = ""
    cache_sha256: str = ""
    cache_timing: tuple[float, float] | None = None

    def __post_init__(self):
        frames = np.asarray(self.frames)
        if frames.ndim != 3 or frames.shape[2] != 3:
            raise ValueError(f"frames must be (F, v, 3), got {list(frames.shape)}")
        if len(frames) != self.timeline.frames:
            raise ValueError(f"{len(frames)} frames, but the timeline has {self.timeline.frames}")

    @property
    def vertex_count(self) -> int:
        return int(self.frames.shape[1])

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64: min and max corner over every frame (of the vertices faces use)."""
        used = self.frames[:, np.unique(self.faces)]
        return np.stack([used.min(axis=(0, 1)), used.max(axis=(0, 1))])

    def frame(self, k: int) -> Mesh:
        """Frame ``k`` as a static :class:`Mesh`."""
        return Mesh(self.frames[k], self.faces, self.name, self.sha256)

    def at_frame(self, position: float) -> Mesh:
        """The surface at a fractional frame ``position`` in ``[0, F - 1]`` (frame k at k),
        whatever the timeline's loop rule (a looping animation's last frame included)."""
        k, u = segment_at(position, len(self.frames))
        return Mesh(interpolate(self.frames[k], self.frames[k + 1], u), self.faces, self.name,
                    self.sha256)

    def vertices_at(self, t: float) -> np.ndarray:
        """(v, 3) float64 vertex positions at ``t`` seconds (the timeline's rule)."""
        k, u, _ = self.timeline.locate(t)
        return interpolate(self.frames[k], self.frames[k + 1], u)

    def mesh_at(self, t: float) -> Mesh:
        """The interpolated surface at ``t`` as a static :class:`Mesh`."""
        return Mesh(self.vertices_at(t), self.faces, self.name, self.sha256)

    def transformed(self, matrix: np.ndarray) -> AnimatedMesh:
        """Every frame moved by the 4x4 similarity ``matrix`` (faces flipped by a reflection)."""
        m = np.asarray(matrix, dtype=np.float64)
        frames = self.frames @ m[:3, :3].T + m[:3, 3]
        faces = self.faces if np.linalg.det(m[:3, :3]) > 0 else self.faces[:, ::-1].copy()
        scale = abs(np.linalg.det(m[:3, :3])) ** (1.0 / 3.0)
        timeline = Timeline(self.timeline.frames, self.timeline.frame_rate_hz, self.timeline.loop,
                            self.timeline.max_surface_speed * scale)
        return AnimatedMesh(frames, faces, timeline, self.name, self.sha256, self.cache,
                            self.cache_sha256, self.cache_timing)


def max_surface_speed(frames: np.ndarray, frame_rate_hz: float) -> float:
    """The fastest vertex of ``frames`` (F, v, 3) played at ``frame_rate_hz``, units per second:
    no point of the surface (a convex combination of vertices) moves faster."""
    steps = np.linalg.norm(np.diff(frames, axis=0), axis=2)  # (F - 1, v)
    return float(steps.max(initial=0.0) * frame_rate_hz)


def interpolate(a: np.ndarray, b: np.ndarray, u: float) -> np.ndarray:
    """``(1 - u) a + u b``, exactly ``a`` at 0 and ``b`` at 1."""
    if u == 0.0:
        return np.array(a, dtype=np.float64)
    if u == 1.0:
        return np.array(b, dtype=np.float64)
    return a + u * (b - a)


class ExactAtTimes:
    """The exact SDF of an :class:`AnimatedMesh` at any time: one :class:`ExactSDF` (libigl's
    AABB tree over the interpolated vertices) per distinct (segment, fraction), the latest
    ``keep`` kept (a simulator asks the same few times over and over; a batch of requests at one
    time builds it once). Thread-safe: the service evaluates in several threads.

    ``builds`` counts the trees built and ``build_s`` the seconds they took (measured; the
    self-intersection test and, where the mesh crosses itself at that time, its union included)."""

    def __init__(self, animation: AnimatedMesh, keep: int = 4):
        self.animation = animation
        self._edges = edge_index(np.asarray(animation.faces, dtype=np.int64))  # the same every frame
        self._cache: Kept[ExactSDF] = Kept(keep)
        self._lock = threading.Lock()  # the build counts
        self.builds = 0
        self.build_s = 0.0

    def at(self, t: float) -> tuple[ExactSDF, int, float]:
        """``(exact SDF at t, segment k, rate)`` (see :meth:`Timeline.locate`)."""
        import time

        k, u, rate = self.animation.timeline.locate(t)

        def build() -> ExactSDF:
            started = time.perf_counter()
            frames = self.animation.frames
            exact = ExactSDF(Mesh(interpolate(frames[k], frames[k + 1], u), self.animation.faces,
                                  self.animation.name), self._edges)
            exact.union  # noqa: B018 -- its tree (and, where the mesh crosses itself then, its union), built now
            spent = time.perf_counter() - started
            with self._lock:
                self.builds += 1
                self.build_s += spent
            return exact

        return self._cache.get((k, u), build), k, rate
