"""Point sampling around a mesh, for training data and evaluation (all seeded, float64, the
mesh's units and frame)."""

from __future__ import annotations

import numpy as np

from ..engine.meshes import Mesh


def surface_points(mesh: Mesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform over the surface area and their unit face normals, (n, 3) each."""
    rng = np.random.default_rng(seed)
    tri = mesh.vertices[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    face = rng.choice(len(tri), size=n, p=area / area.sum())
    # Uniform barycentric coordinates by the square-root trick.
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    a, b, c = tri[face, 0], tri[face, 1], tri[face, 2]
    points = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    normals = cross[face] / np.where(area[face] > 0, area[face], 1.0)[:, None]
    return points, normals


def surface_band_points(mesh: Mesh, n: int, band: float, seed: int) -> np.ndarray:
    """``n`` points at surface samples offset along the face normal by U(-band, band): (n, 3).

    Their exact signed distance is *about* the offset; take the truth from :class:`ExactSDF`.
    """
    points, normals = surface_points(mesh, n, seed)
    offset = np.random.default_rng(seed + 1).uniform(-band, band, n)
    return points + offset[:, None] * normals


#: The bands around the surface where colliders are trained and measured, by half-width in metres:
#: +-1 mm, where collisions are decided, and +-10 mm, where a cloth simulator queries.
BANDS_M = {"band_1mm": 1e-3, "band_10mm": 1e-2}


def band_sets(mesh: Mesh, n: int, seed: int, meters_per_unit: float,
              sizes: dict[str, int] | None = None) -> dict[str, np.ndarray]:
    """Points in each band of :data:`BANDS_M` (the same names): ``n`` (or ``sizes[name]``) points
    of :func:`surface_band_points`, band ``i`` drawn from ``seed + i``; (n, 3) float64, the
    mesh's units and frame (``meters_per_unit`` converts the bands)."""
    sizes = sizes or {}
    return {name: surface_band_points(mesh, sizes.get(name, n), band / meters_per_unit, seed + i)
            for i, (name, band) in enumerate(BANDS_M.items())}


def random_times(timeline, n: int, seed: int) -> np.ndarray:
    """``n`` times (seconds, ascending) drawn uniformly over ``[0, duration_s)`` of ``timeline``
    (a :class:`~collider_contract.Timeline`): they fall between its frames (a keyframe is hit
    with probability zero), which is where keyframe grids are interpolated and err most."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"the number of random times must be a positive integer, got {n!r}")
    return np.sort(np.random.default_rng(seed).uniform(0.0, timeline.duration_s, int(n)))


def animated_band_sets(animation, times, n: int, seed: int,
                       meters_per_unit: float) -> list[tuple[float, dict[str, np.ndarray]]]:
    """:func:`band_sets` of an animated mesh at each of ``times`` (seconds): ``[(t, {band:
    points}), ...]``, ``n`` points per band per time, around the exact interpolated surface
    ``animation.mesh_at(t)`` (the truth at ``t``), time ``i`` drawn from ``seed + 10 i``;
    (n, 3) float64, the animation's units and frame."""
    return [(float(t), band_sets(animation.mesh_at(float(t)), n, seed + 10 * i, meters_per_unit))
            for i, t in enumerate(times)]


def box_points(lo, hi, n: int, seed: int) -> np.ndarray:
    """``n`` points uniform in the box ``[lo, hi]``: (n, 3)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    return lo + rng.random((n, 3)) * (hi - lo)
