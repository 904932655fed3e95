"""Cloth grid geometry and the spring forces on it, on (H, W, 3) arrays (no index gathers).

Vertices are stored as an (H, W, 3) float64 array, metres, world frame; vertex (column c, row r)
is ``x[r, c]`` and has flat index ``r * W + c``. Springs join grid neighbours, so each spring
family is a pair of array slices and its forces accumulate by slice arithmetic.
"""

from __future__ import annotations

import numpy as np

#: Spring families as slice offsets (dr, dc): stretch = direct neighbours, shear = diagonals,
#: bend = neighbours two apart along rows and columns.
FAMILIES = {
    "stretch": ((0, 1), (1, 0)),
    "shear": ((1, 1), (1, -1)),
    "bend": ((0, 2), (2, 0)),
}


def grid_positions(width: int, height: int, spacing_m: float, origin_m: np.ndarray,
                   axes: str) -> np.ndarray:
    """(H, W, 3) float64 rest positions: columns along the first axis of ``axes``, rows along the
    second, starting at ``origin_m`` (metres, world frame)."""
    first, second = "xyz".index(axes[0]), "xyz".index(axes[1])
    x = np.zeros((height, width, 3))
    x[:, :, first] = np.arange(width)[None, :] * spacing_m
    x[:, :, second] = np.arange(height)[:, None] * spacing_m
    return x + origin_m  # (3,), broadcast over the grid


def quad_faces(width: int, height: int) -> np.ndarray:
    """(F, 4) int64 vertex indices of the grid's quads, counter-clockwise seen from +normal."""
    r, c = np.meshgrid(np.arange(height - 1), np.arange(width - 1), indexing="ij")
    a = (r * width + c).ravel()
    return np.stack([a, a + 1, a + width + 1, a + width], axis=1)


def _pair(x: np.ndarray, dr: int, dc: int):
    """Slices (A, B) of the (H, W, ...) grid so that B[i] is A[i]'s neighbour at (+dr, +dc)."""
    h, w = x.shape[:2]
    if dc >= 0:
        return np.s_[:h - dr, :w - dc], np.s_[dr:, dc:]
    return np.s_[:h - dr, -dc:], np.s_[dr:, :w + dc]


class SpringFamily:
    """Linear springs ``f = k (|d| - L) d / |d|`` between grid neighbours at offsets ``pairs``.

    rest : lengths (metres) from the rest positions; stiffness_n_m : k in N/m
    """

    def __init__(self, name: str, rest_positions: np.ndarray, stiffness_n_m: float):
        self.name = name
        self.k = float(stiffness_n_m)
        self.slices = [_pair(rest_positions, dr, dc) for dr, dc in FAMILIES[name]]
        self.rest = [np.linalg.norm(rest_positions[b] - rest_positions[a], axis=-1)
                     for a, b in self.slices]

    def add_forces(self, x: np.ndarray, forces: np.ndarray) -> None:
        """Add this family's spring forces (N) at positions ``x`` (H, W, 3) into ``forces``."""
        for (a, b), rest in zip(self.slices, self.rest, strict=True):
            d = x[b] - x[a]
            length = np.sqrt(np.einsum("...i,...i->...", d, d))
            # f = k (|d| - L) / |d| * d, pulling a towards b when stretched.
            scale = self.k * (1.0 - rest / np.maximum(length, 1e-12))
            f = d * scale[..., None]
            forces[a] += f
            forces[b] -= f

    def energy(self, x: np.ndarray) -> float:
        """Elastic energy (J) ``sum k (|d| - L)^2 / 2`` of this family at positions ``x``."""
        total = 0.0
        for (a, b), rest in zip(self.slices, self.rest, strict=True):
            length = np.linalg.norm(x[b] - x[a], axis=-1)
            total += 0.5 * self.k * float(np.sum((length - rest) ** 2))
        return total
