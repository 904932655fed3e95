"""Make a collider from a mesh: ``voxel`` (baked grid), ``mesh`` (exact) or ``kdtree``; or from
an animated mesh: ``mesh`` (exact at any time) or ``voxel`` (keyframe grids).
(``neural`` colliders are trained, see :mod:`collider_server.making.training`.)"""

from __future__ import annotations

import numpy as np

from collider_contract import Timeline

from ..engine.animated_meshes import AnimatedMesh
from ..engine.collider import Collider, ColliderInfo
from ..engine.kinds import (
    AnimatedMeshCollider,
    AnimatedVoxelCollider,
    KDTreeCollider,
    MeshCollider,
    VoxelCollider,
)
from ..engine.kinds.voxel import MAX_RESOLUTION, MIN_RESOLUTION
from ..engine.meshes import ExactSDF, Mesh
from .progress import progress

BAKED_KINDS = ("voxel", "mesh", "kdtree")


def padded_box(mesh: Mesh | AnimatedMesh, padding: float) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's bounding box (an animation's: over every frame) grown by ``padding`` times its
    largest side on every face."""
    lo, hi = mesh.bounds
    margin = padding * float((hi - lo).max())
    return lo - margin, hi + margin


def exact_seconds_per_point(sdf: ExactSDF, lo: np.ndarray, hi: np.ndarray, resolution: int = 128,
                            max_points: int = 262_144) -> float:
    """Seconds ``sdf`` takes per point of a voxel bake of ``resolution``^3 over the box
    ``lo``..``hi`` (its units), measured now: what a bake's estimate rests on.

    Measured as the bake asks: whole x-slabs of that grid (up to 4, evenly spaced, at most
    ``max_points`` points), after a first call that builds the winding number's hierarchy (built
    once per mesh: timed with it, three probes in a row gave 73, 41 and 29 us per point, and
    scattered points cost about 1.5x the grid's neighbouring ones: a 128^3 bake estimated at 4x
    its time)."""
    import time

    axes = grid_axes(lo, hi, resolution)
    yz = _yz_plane(axes)
    # the first call builds the trees (and a self-crossing mesh's union), once per mesh
    sdf.signed_distance(np.random.default_rng(0).uniform(lo, hi, (1024, 3)))
    slabs = max(1, min(4, max_points // len(yz)))
    picked = [int((k + 0.5) * resolution / slabs) for k in range(slabs)]
    points = np.concatenate([_slab_points(axes[0][i:i + 1], yz) for i in picked])
    started = time.perf_counter()
    sdf.signed_distance(points)
    return (time.perf_counter() - started) / len(points)


def grid_axes(lo, hi, resolution: int) -> list[np.ndarray]:
    """The x, y and z sample positions of a ``resolution``^3 grid spanning ``lo``..``hi``."""
    return [np.linspace(lo[i], hi[i], resolution) for i in range(3)]


def _yz_plane(axes: list[np.ndarray]) -> np.ndarray:
    """(R^2, 2) the (y, z) of one x-slab of the grid, z fastest (the grid's memory order)."""
    return np.stack(np.meshgrid(axes[1], axes[2], indexing="ij"), axis=-1).reshape(-1, 2)


def _slab_points(xs: np.ndarray, yz: np.ndarray) -> np.ndarray:
    """(len(xs) * R^2, 3) float64: the grid points of the x-slabs at ``xs``, in memory order."""
    points = np.empty((len(xs) * len(yz), 3))
    points[:, 0] = np.repeat(xs, len(yz))
    points[:, 1:] = np.tile(yz, (len(xs), 1))
    return points


def check_bake_settings(kind: str, resolution: int, padding: float) -> None:
    """ValueError naming the setting that :func:`bake_collider` cannot bake with (checked before
    any work: a bad padding would otherwise surface only after the bake)."""
    if kind not in BAKED_KINDS:
        raise ValueError(f"cannot bake kind {kind!r}; bake one of {list(BAKED_KINDS)} (neural is trained)")
    if not (np.isfinite(padding) and padding >= 0):
        raise ValueError(f"padding must be a finite number >= 0 (fraction of the largest side), got {padding}")
    if kind == "voxel":
        check_resolution(resolution)


def check_resolution(resolution: int) -> None:
    """ValueError unless a voxel grid of ``resolution`` samples per axis can be baked."""
    if not MIN_RESOLUTION <= resolution <= MAX_RESOLUTION:
        raise ValueError(f"resolution must be in {MIN_RESOLUTION}..{MAX_RESOLUTION}, got {resolution}")


def bake_grid(sdf: ExactSDF, lo, hi, resolution: int, chunk_points: int = 262_144,
              show_progress: bool = True, desc: str | None = None) -> np.ndarray:
    """Exact signed distances at the grid corners: (R, R, R) float32, indexed [x, y, z]."""
    check_resolution(resolution)
    axes = grid_axes(lo, hi, resolution)
    total = resolution**3
    grid = np.empty(total, dtype=np.float32)
    # Walk the grid in x-slabs so no (R^3, 3) coordinate array is ever built.
    slab = max(1, chunk_points // (resolution * resolution))
    yz = _yz_plane(axes)
    with progress(total=total, desc=desc or f"bake {resolution}^3", unit="pt", enabled=show_progress) as bar:
        for i0 in range(0, resolution, slab):
            points = _slab_points(axes[0][i0 : i0 + slab], yz)
            start = i0 * resolution * resolution
            grid[start : start + len(points)] = sdf.signed_distance(points)
            bar.update(len(points))
    return grid.reshape(resolution, resolution, resolution)


def mesh_source(mesh: Mesh, transform: np.ndarray | None = None) -> dict:
    """Metadata describing the source mesh (stored in ``ColliderInfo.source``)."""
    return {
        "mesh": mesh.name,
        "sha256": mesh.sha256,
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "transform": (np.eye(4) if transform is None else np.asarray(transform)).tolist(),
    }


def bake_collider(mesh: Mesh, kind: str, name: str, *, resolution: int = 256, padding: float = 0.1,
                  units: str = "m", meters_per_unit: float = 1.0, device: str | None = None,
                  show_progress: bool = True) -> Collider:
    """Build a ``kind`` collider named ``name`` from ``mesh`` (in its own units and frame).

    resolution : voxel samples per axis (voxel only)
    padding : fraction of the largest side added around the mesh's box (the domain)
    """
    check_bake_settings(kind, resolution, padding)
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


ANIMATED_KINDS = ("mesh", "voxel")


def animation_source(animation: AnimatedMesh, transform: np.ndarray | None = None) -> dict:
    """Metadata of an animated source (``ColliderInfo.source``): the mesh's, and the vertex
    cache's file name and sha256, its frame count and rate, and a PC2 cache's header timing
    (``cache_start_frame``, ``cache_sample_rate``: recorded, not applied)."""
    source = {**mesh_source(animation.frame(0), transform), "cache": animation.cache,
              "cache_sha256": animation.cache_sha256, "frames": int(animation.timeline.frames),
              "frame_rate_hz": float(animation.timeline.frame_rate_hz)}
    if animation.cache_timing is not None:
        source["cache_start_frame"], source["cache_sample_rate"] = map(float, animation.cache_timing)
    return source


def keyframe_positions(frames: int, keyframes: int) -> np.ndarray:
    """Where ``keyframes`` grids sit in an animation of ``frames`` frames: fractional frame
    positions evenly spaced from the first frame (0) to the last (``frames - 1``)."""
    return np.linspace(0.0, frames - 1, keyframes)


def bake_animated_collider(animation: AnimatedMesh, kind: str, name: str, *, resolution: int = 128,
                           keyframes: int | None = None, padding: float = 0.1, units: str = "m",
                           meters_per_unit: float = 1.0, device: str | None = None,
                           show_progress: bool = True, grids: dict | None = None) -> Collider:
    """An animated ``kind`` collider named ``name`` from ``animation`` (its units and frame).

    kind : "mesh" (the frames themselves: exact at any time) or "voxel" (keyframe grids)
    resolution : voxel samples per axis; keyframes : voxel grids, evenly spaced over the
        animation from its first frame to its last (:func:`keyframe_positions`; None: one per
        frame)
    padding : fraction of the largest side added around the box of every frame (the domain)
    grids : voxel: grids already baked of this animation at this resolution and padding, by
        frame position; those found are not baked again and those baked are added (5, 13 and
        25 keyframes of 25 frames bake 25 grids, not 43)
    """
    if kind not in ANIMATED_KINDS:
        raise ValueError(f"cannot animate kind {kind!r}; animated kinds are {list(ANIMATED_KINDS)}")
    if not (np.isfinite(padding) and padding >= 0):
        raise ValueError(f"padding must be a finite number >= 0 (fraction of the largest side), got {padding}")
    timeline = animation.timeline
    lo, hi = padded_box(animation, padding)
    info = ColliderInfo(
        name=name, kind=kind, domain_min=lo.tolist(), domain_max=hi.tolist(), units=units,
        meters_per_unit=meters_per_unit, source=animation_source(animation),
        settings={"padding": padding}, animation=timeline.to_dict())
    if kind == "mesh":
        return AnimatedMeshCollider(info, animation)
    keyframes = timeline.frames if keyframes is None else keyframes
    if isinstance(keyframes, bool) or not isinstance(keyframes, int) or keyframes < 2:
        raise ValueError(f"--keyframes must be an integer >= 2, got {keyframes!r}")
    if not MIN_RESOLUTION <= resolution <= MAX_RESOLUTION:
        raise ValueError(f"resolution must be in {MIN_RESOLUTION}..{MAX_RESOLUTION}, got {resolution}")
    info.settings.update(resolution=resolution, keyframes=keyframes)
    # The keyframes' own timeline: the same duration, loop and speed bound, K frames.
    keyed = Timeline(keyframes, (keyframes - 1) / timeline.duration_s, timeline.loop,
                     timeline.max_surface_speed)
    info.animation = keyed.to_dict()
    baked = {} if grids is None else grids
    stack = np.empty((keyframes, resolution, resolution, resolution), dtype=np.float32)
    for i, position in enumerate(keyframe_positions(timeline.frames, keyframes)):
        position = float(position)
        if position not in baked:
            baked[position] = bake_grid(ExactSDF(animation.at_frame(position)), lo, hi, resolution,
                                        show_progress=show_progress,
                                        desc=f"bake keyframe {i + 1}/{keyframes} {resolution}^3")
        stack[i] = baked[position]
    return AnimatedVoxelCollider(info, stack, device)
