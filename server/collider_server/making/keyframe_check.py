"""Whether a voxel collider's keyframes hold an animation's thin parts.

Between two keyframes an animated voxel collider blends their grids linearly. A part of
thickness ``h`` that moves ``d`` along its normal from one keyframe to the next keeps ``h - d``
of its thickness halfway between them (the blend of the two distances is ``d/2 - h/2`` at the
part's middle), and none once ``d >= h``: a 4 mm plate moving 5 cm between keyframes is gone at
mid-segment and a cloth falls through it while the collider reports nothing inside. This module
measures, per segment between keyframes, how far the surface moves along its normal against how
thin it is there, and the fewest evenly spaced keyframes under which no part moves more than
:data:`HELD_FRACTION` of its thickness (more than the frames when a part moves more than that in
one frame: grids at interpolated times). The exact kind (``mesh``) has no such limit.

Thickness is measured once, on the first frame (its units), at the centroids of up to
:data:`SAMPLED_FACES` faces: twice the deepest point of the exact SDF along the face's inward
normal (the largest ball centred on that ray; a face's centroid, not a vertex, whose averaged
normal at a corner points out through the side), sampled at geometric steps and refined around the deepest (it errs low,
by a few percent: the check warns early rather than late).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from ..engine.animated_meshes import AnimatedMesh
from ..engine.meshes import ExactSDF, Mesh
from .bake import keyframe_positions

#: A part may move at most this fraction of its thickness between two keyframes (it then keeps
#: at least half of it halfway between them).
HELD_FRACTION = 0.5
#: Faces whose thickness and motion are measured (a fixed random pick, seed 0, when more).
SAMPLED_FACES = 2048
#: The most keyframes the check suggests (above it, the exact kind).
MAX_KEYFRAMES = 1024
#: Depths sampled along each inward normal, geometrically from 1e-4 to 1 of the mesh's size.
DEPTH_STEPS = 32


@dataclass(frozen=True)
class Segment:
    """The worst sampled face between keyframes at frame positions ``start`` and ``end``:
    ``moved`` its displacement along its normal and ``thickness`` the part's there (the
    animation's units), ``ratio`` their quotient."""

    start: float
    end: float
    moved: float
    thickness: float

    @property
    def ratio(self) -> float:
        return self.moved / self.thickness


@dataclass(frozen=True)
class KeyframeCheck:
    """What :func:`check_keyframes` measured: the worst segment of ``keyframes`` keyframes over
    ``frames`` frames (None: no sampled part moves), how many segments move a part more than
    :data:`HELD_FRACTION` of its thickness, and ``needed``, the fewest keyframes under which none
    does (up to one per frame; beyond, a count that does, with keyframes between frames; None:
    not within :data:`MAX_KEYFRAMES`)."""

    frames: int
    keyframes: int
    worst: Segment | None
    failing: int
    needed: int | None

    @property
    def holds(self) -> bool:
        return self.failing == 0

    def warning(self, meters_per_unit: float = 1.0) -> str | None:
        """One line for the person baking, or None when every segment holds."""
        if self.holds:
            return None
        w, mm = self.worst, 1000.0 * meters_per_unit
        kept = max(w.thickness - w.moved, 0.0) * mm
        if self.needed is None:
            fix = f"not even {MAX_KEYFRAMES} keyframes hold it: the exact kind (--kind mesh) does"
        elif self.needed > self.frames:
            fix = (f"--keyframes {self.needed} holds it (more grids than the {self.frames} frames: grids at "
                   "interpolated times), as does the exact kind (--kind mesh)")
        else:
            fix = f"--keyframes {self.needed} holds it"
        return (f"warning: {self.failing} of {self.keyframes - 1} keyframe segments move a part more than "
                f"half its thickness: between frames {w.start:g} and {w.end:g} a part {w.thickness * mm:.3g} mm "
                f"thin moves {w.moved * mm:.3g} mm along its normal, and halfway the blended grids keep "
                f"{kept:.3g} mm of it (a cloth there falls through it); {fix}")


def face_normals(mesh: Mesh) -> np.ndarray:
    """(f, 3) float64 outward unit normals of the faces (zero for a degenerate face)."""
    v, f = mesh.vertices, mesh.faces
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


def local_thickness(mesh: Mesh, faces: np.ndarray, sdf: ExactSDF | None = None) -> np.ndarray:
    """(m,) float64: the thickness of ``mesh`` at the centroids of its ``faces`` (indices), its
    units: twice the deepest exact signed distance along each inward face normal (module
    docstring)."""
    sdf = sdf or ExactSDF(mesh)
    size = float(np.ptp(mesh.vertices, axis=0).max())
    depths = np.geomspace(1e-4 * size, size, DEPTH_STEPS)  # (s,)
    start = mesh.vertices[mesh.faces[faces]].mean(axis=1)
    normal = face_normals(mesh)[faces]

    def deepest(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """At depths ``t`` (m, s) along each inward normal: the deepest inside distance (m,)
        and its column."""
        points = start[:, None, :] - t[:, :, None] * normal[:, None, :]  # (m, s, 3)
        inside = -sdf.signed_distance(points.reshape(-1, 3)).reshape(t.shape)
        return inside.max(axis=1), inside.argmax(axis=1)

    coarse = np.broadcast_to(depths, (len(faces), DEPTH_STEPS))
    _, j = deepest(coarse)
    # Refined between the coarse steps either side of the deepest one (the coarse steps are
    # 1.33x apart: alone they would miss the middle of a part by up to a quarter of it).
    low, high = depths[np.maximum(j - 1, 0)], depths[np.minimum(j + 1, DEPTH_STEPS - 1)]
    fine = low[:, None] + (high - low)[:, None] * np.linspace(0.0, 1.0, 17)[None, :]
    depth, _ = deepest(fine)
    return 2.0 * np.maximum(depth, 0.0)


def check_keyframes(animation: AnimatedMesh, keyframes: int) -> KeyframeCheck:
    """Per segment between ``keyframes`` evenly spaced keyframes of ``animation``, the largest
    displacement of a sampled face's centroid along its first-frame normal against the thickness
    there; and the fewest keyframes that hold every part (module docstring)."""
    faces = animation.faces
    pick = (np.arange(len(faces)) if len(faces) <= SAMPLED_FACES else
            np.sort(np.random.default_rng(0).choice(len(faces), SAMPLED_FACES, replace=False)))
    first = animation.frame(0)
    thickness = local_thickness(first, pick)
    normals = face_normals(first)[pick]
    corners = faces[pick]  # (m, 3) vertex indices
    # Parts whose thickness cannot be measured (an inward ray that finds no inside: an open or
    # flat surface) are left out rather than called infinitely thin.
    measured = thickness > 0
    frames = animation.timeline.frames

    def segments(count: int) -> list[Segment]:
        positions = keyframe_positions(frames, count)
        at = [animation.at_frame(float(p)).vertices[corners].mean(axis=1) for p in positions]
        out = []
        for (a, b), (x0, x1) in zip(pairwise(positions), pairwise(at)):
            moved = np.abs(np.einsum("ij,ij->i", x1 - x0, normals))
            ratio = np.where(measured, moved / np.where(measured, thickness, 1.0), 0.0)
            i = int(np.argmax(ratio))
            out.append(Segment(float(a), float(b), float(moved[i]), float(thickness[i])))
        return out

    def failing(parts: list[Segment]) -> int:
        return sum(s.thickness > 0 and s.ratio > HELD_FRACTION for s in parts)

    own = segments(keyframes)
    worst = max(own, key=lambda s: s.ratio if s.thickness > 0 else 0.0, default=None)
    needed = keyframes
    if failing(own):
        needed = next((count for count in range(keyframes + 1, frames + 1)
                       if not failing(segments(count))), None)
    if needed is None:
        # Faster than one grid per frame holds: keyframes between frames (their grids at
        # interpolated times). Within a frame the motion is linear, so keyframes 1/n of a frame
        # apart move a part 1/n of its worst per-frame ratio: enough of them hold it.
        per_frame = max(s.ratio for s in segments(frames) if s.thickness > 0)
        count = int(np.ceil((frames - 1) * per_frame / HELD_FRACTION)) + 1
        if count <= MAX_KEYFRAMES and not failing(segments(count)):
            needed = count
    return KeyframeCheck(frames, keyframes, worst, failing(own), needed)
