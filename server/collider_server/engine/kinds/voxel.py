"""A dense grid of signed distances sampled from the exact SDF, read by trilinear interpolation.

The grid holds ``R^3`` samples at the corners ``domain_min + i * spacing`` (i = 0..R-1 per axis)
of a padded box. The distance is the trilinear interpolant and the normal its analytic gradient,
so distance and normal are consistent with each other (the gradient is piecewise bilinear and
jumps across cell faces, the price of trilinear interpolation).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from ..collider import Collider, ColliderInfo
from ..devices import resolve_device
from .grid_cells import trilerp

MIN_RESOLUTION, MAX_RESOLUTION = 8, 1024


class VoxelCollider(Collider):
    """Trilinear signed-distance grid. ``tensors()["grid"]``: (R, R, R) float32, [x, y, z]."""

    kind = "voxel"
    #: On a CPU, small blocks: their temporaries stay in the cache and are not mapped anew. 1M
    #: points (the bunny at 128^3, benchmarks/chunk_points.py) in one block took 1.3-1.5x the time
    #: of blocks of 65,536 on 1 thread, 1.2-1.4x on 2; 1.1-1.2x where freed memory is held (as
    #: `collider serve` does). On a GPU, large blocks fill it.
    chunk_points = 65_536
    GPU_CHUNK_POINTS: ClassVar[int] = 1_048_576

    def __init__(self, info: ColliderInfo, grid: np.ndarray, device: str | None = None):
        super().__init__(info)
        import torch

        grid = np.asarray(grid, dtype=np.float32)
        if grid.ndim != 3 or min(grid.shape) < 2:
            raise ValueError(f"voxel grid must be 3-D with at least 2 samples per axis, got {grid.shape}")
        self._torch = torch
        self._device = resolve_device(device)
        if self._device != "cpu":
            self.chunk_points = self.GPU_CHUNK_POINTS
        self._shape = grid.shape
        self._grid = torch.as_tensor(grid, device=self._device).reshape(-1)
        self._spacing = (self.domain_max - self.domain_min) / (np.asarray(grid.shape) - 1)
        self._strides = (grid.shape[1] * grid.shape[2], grid.shape[2], 1)

    @property
    def device(self) -> str:
        return self._device

    @property
    def resolution(self) -> tuple[int, int, int]:
        return tuple(self._shape)

    def evaluate(self, local, want_gradient):
        index, t = self._cells(local)
        distance, gradient = self._trilinear(self._grid, index, t, want_gradient)
        return distance, gradient

    def _cells(self, local):
        """The cell of each collider-frame point: the flat index of its lowest corner and its
        position in the cell, (m, 3) in [0, 1] (torch tensors on the grid's device)."""
        torch = self._torch
        dev = self._device
        # Grid coordinates in float64 (exact for far-away domains), then float32 on the device.
        coords = (local - self.domain_min) / self._spacing
        coords = torch.as_tensor(coords, dtype=torch.float32, device=dev)
        upper = torch.tensor([s - 2 for s in self._shape], device=dev)
        base = torch.minimum(coords.floor().clamp_min(0).long(), upper)
        t = (coords - base).clamp(0.0, 1.0)
        sx, sy, sz = self._strides
        return base[:, 0] * sx + base[:, 1] * sy + base[:, 2] * sz, t

    def _trilinear(self, g, index, t, want_gradient):
        """The trilinear interpolant of the flat grid ``g`` in the cells :meth:`_cells` found:
        ``(distance (m,), gradient (m, 3) or None)``, float64 numpy, collider units."""
        sx, sy, sz = self._strides
        # Corner values c{ijk}, i/j/k = offset along x/y/z.
        c000, c100, c010, c110 = g[index], g[index + sx], g[index + sy], g[index + sx + sy]
        c001, c101, c011, c111 = g[index + sz], g[index + sx + sz], g[index + sy + sz], g[index + sx + sy + sz]
        distance, dx, dy, dz = trilerp(c000, c100, c010, c110, c001, c101, c011, c111, t[:, 0], t[:, 1], t[:, 2])
        if not want_gradient:
            return distance.double().cpu().numpy(), None
        # d/dt per unit of grid coordinate, over the spacing: per unit of length.
        gradient = self._torch.stack([dx, dy, dz], dim=1).double().cpu().numpy() / self._spacing
        return distance.double().cpu().numpy(), gradient

    def tensors(self):
        return {"grid": self._grid.reshape(self._shape).cpu().numpy()}

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        if set(tensors) != {"grid"}:
            raise ValueError(f"voxel model must hold exactly one tensor 'grid', found {sorted(tensors)}")
        return cls(info, tensors["grid"], device)
