"""A collider's surface as a triangle mesh: its distance sampled on a grid over a box, then
marching cubes of a level set (scikit-image). The one home of this step for the evaluation's
reconstruction error and the browser views."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .progress import progress

#: ``distance(points)``: (m, 3) float64 collider-frame points -> (m,) distances, collider units.
DistanceFn = Callable[[np.ndarray], np.ndarray]


@dataclass
class Grid:
    """A distance sampled on a regular grid, collider frame.

    values : (r, r, r) float32, collider units, indexed [x, y, z]
    lo, hi : (3,) float64 corners of the box the grid spans (its first and last samples)
    """

    values: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    @property
    def spacing(self) -> tuple[float, float, float]:
        return tuple((self.hi - self.lo) / (np.array(self.values.shape) - 1))


def distance_grid(distance: DistanceFn, lo, hi, resolution: int, *, chunk_points: int = 65_536,
                  desc: str = "grid", show_progress: bool = False) -> Grid:
    """``distance`` at ``resolution``^3 points spanning the box ``lo``..``hi`` (collider frame),
    asked ``chunk_points`` at a time (bounded memory, and a progress bar that moves)."""
    if not isinstance(resolution, int) or resolution < 2:
        raise ValueError(f"resolution must be an integer >= 2, got {resolution!r}")
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    axes = [np.linspace(lo[i], hi[i], resolution) for i in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    values = np.empty(len(points), dtype=np.float32)
    with progress(len(points), desc, "pt", show_progress) as bar:
        for start in range(0, len(points), chunk_points):
            chunk = points[start:start + chunk_points]
            values[start:start + len(chunk)] = distance(chunk)
            bar.update(len(chunk))
    return Grid(values.reshape((resolution,) * 3), lo, hi)


def level_surface(grid: Grid, level: float = 0.0) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices (v, 3) float64 collider frame, faces (f, 3) int64) of ``distance == level``
    (collider units), or None when the grid does not cross that level."""
    from skimage.measure import marching_cubes

    if not grid.values.min() < level < grid.values.max():
        return None
    verts, faces, _, _ = marching_cubes(grid.values, level=level, spacing=grid.spacing)
    return verts + grid.lo, faces.astype(np.int64)
