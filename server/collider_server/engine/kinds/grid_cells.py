"""The cells of a regular grid over [-1, 1]^3, the one home of their rules: which cell holds a
point, its 8 corners (in :data:`CORNERS`' order, x in bit 0), each corner's row in a table (dense
or spatially hashed), and the interpolation weights (trilinear or smoothstep) with their
derivatives. The grid networks (:mod:`.neural_grid`, :mod:`.neural_keyframes`,
:mod:`.neural_deformed`), the voxel kind and the numba kernels (:mod:`.grid_kernels`) all read
their cells through here.

The pure arithmetic rules (:func:`high_weight`, :func:`dense_row`, :func:`hashed_row`,
:func:`trilerp`) are written once as plain Python: torch calls them on tensors (the reference
paths, CUDA), numba compiles the same functions for the CPU kernels (``*_jit`` below, with the
helpers the kernels share: :func:`axis_jit`, :func:`corner_jit`, :func:`cell_rows_jit`).

A grid of resolution ``r`` has ``r`` cells per side; corner ``(i, j, k)`` (each in ``0 .. r``) is
at ``-1 + 2 (i, j, k) / r``. Points are clamped into the cube; along a clamped axis the weights'
derivative is 0 (the interpolant does not move there).
"""

from __future__ import annotations

import math

import numpy as np

from collider_contract.pose import CORNERS

try:
    import numba
except ImportError:  # the engine still works (pure torch), only slower on a CPU
    numba = None

#: Primes of the spatial hash (Teschner et al. 2003, as in instant-NGP); the first is 1 so that
#: neighbouring cells along x land in neighbouring rows.
HASH_PRIMES = (1, 2_654_435_761, 805_459_861)
_P0, _P1, _P2 = HASH_PRIMES

__all__ = ["CORNERS", "HASH_PRIMES", "cell_corners", "dense_row", "hashed_row", "high_weight",
           "trilerp"]


def shared_rule(function):
    """Marks a rule that torch calls as it is and numba compiles (the ``*_jit`` below); returns it
    unchanged. (Decorated, so mutation testing leaves it as it is: mutmut wraps an undecorated
    function in a trampoline numba cannot compile; the torch paths' tests check the rule.)"""
    return function


@shared_rule
def high_weight(t, smooth: bool):
    """The weight of a cell's high corner along one axis at ``t`` in [0, 1] (the point's place in
    the cell) and its derivative d weight / d t: smoothstep ``t^2 (3 - 2 t)`` (C1 across cell
    faces) when ``smooth``, else linear ``t``. The low corner's weight is ``1 - weight``. Scalars
    (numba) or tensors (torch) alike."""
    if smooth:
        return t * t * (3.0 - 2.0 * t), 6.0 * t * (1.0 - t)
    return t, t * 0.0 + 1.0


@shared_rule
def dense_row(i, j, k, side):
    """The row of corner ``(i, j, k)`` in a dense table of ``side^3`` rows (``side = r + 1``)."""
    return i + side * (j + side * k)


@shared_rule
def hashed_row(i, j, k, rows):
    """The row of corner ``(i, j, k)`` in a hashed table of ``rows`` rows (a power of two)."""
    return ((i * _P0) ^ (j * _P1) ^ (k * _P2)) & (rows - 1)


@shared_rule
def trilerp(v000, v100, v010, v110, v001, v101, v011, v111, wx, wy, wz):
    """The corners' values (``vXYZ``, X, Y, Z the corner's bits) interpolated with per-axis
    weights ``w*`` (of the high corner), one axis after another (x, then y, then z), and the
    result's derivatives with respect to ``wx``, ``wy``, ``wz``: (value, d/dwx, d/dwy, d/dwz).
    Scalars (numba) or tensors (torch) alike."""
    ex00, ex10, ex01, ex11 = v100 - v000, v110 - v010, v101 - v001, v111 - v011  # along x
    e00, e10, e01, e11 = v000 + wx * ex00, v010 + wx * ex10, v001 + wx * ex01, v011 + wx * ex11
    ey0, ey1 = e10 - e00, e11 - e01  # along y, at z0 and z1
    e0, e1 = e00 + wy * ey0, e01 + wy * ey1
    gx0, gx1 = ex00 + wy * (ex10 - ex00), ex01 + wy * (ex11 - ex01)
    return (e0 + wz * (e1 - e0), gx0 + wz * (gx1 - gx0), ey0 + wz * (ey1 - ey0), e1 - e0)


def cell_corners(u, resolution, smooth: bool):
    """The cells holding normalised points ``u`` (n, 3) (torch, clamped into [-1, 1]) in grids of
    ``resolution`` (L,) cells per side (a float tensor on ``u``'s device), torch ops (the
    reference paths, CUDA).

    Returns ``ijk`` (n, L, 8, 3) int64, the corners' integer coordinates in :data:`CORNERS`'
    order; ``weight`` (n, L, 8), ``u``'s dtype; ``dweight`` (n, L, 8, 3), d weight / d u (0 along
    a clamped axis)."""
    import torch

    # [-1, 1] -> [0, r] grid coordinates of every level: (n, L, 3).
    unit = ((u.clamp(-1.0, 1.0) + 1.0) * 0.5)[:, None, :]
    position = unit * resolution[None, :, None]
    cell = position.floor().clamp_(max=resolution[None, :, None] - 1)
    w1, dw1 = high_weight(position - cell, smooth)
    dw1 = dw1 * (0.5 * resolution)[None, :, None]  # d position / d u
    # Per axis, weight of the low (0) and high (1) corner: (n, L, 3, 2).
    w = torch.stack([1.0 - w1, w1], dim=-1)
    dw = torch.stack([-dw1, dw1], dim=-1)
    corners = torch.tensor(CORNERS, device=u.device)  # a copy: CORNERS is read-only
    ox, oy, oz = corners[:, 0], corners[:, 1], corners[:, 2]
    wx, wy, wz = w[:, :, 0, ox], w[:, :, 1, oy], w[:, :, 2, oz]  # (n, L, 8)
    dweight = torch.stack([dw[:, :, 0, ox] * wy * wz, wx * dw[:, :, 1, oy] * wz,
                           wx * wy * dw[:, :, 2, oz]], dim=-1)
    # Clamped axes do not move the interpolant: their derivative is 0 (as autograd has it).
    dweight = dweight * (u.abs() <= 1.0).to(u.dtype)[:, None, None, :]
    ijk = cell.long()[:, :, None, :] + corners[None, None]
    return ijk, wx * wy * wz, dweight


if numba is not None:
    _jit = numba.njit(cache=True, fastmath=False, nogil=True)
    high_weight_jit = _jit(high_weight)
    dense_row_jit = _jit(dense_row)
    hashed_row_jit = _jit(hashed_row)
    trilerp_jit = numba.njit(cache=True, fastmath=True, nogil=True)(trilerp)

    @_jit
    def axis_jit(value, resolution, smooth):
        """Cell index, high-corner weight and its derivative d weight / d u along one axis of a
        grid of ``resolution`` cells (the scalar :func:`cell_corners`)."""
        inside = 1.0
        if value < -1.0:
            value, inside = -1.0, 0.0
        elif value > 1.0:
            value, inside = 1.0, 0.0
        position = (value + 1.0) * 0.5 * resolution
        cell = math.floor(position)
        cell = min(cell, resolution - 1)
        w, dw = high_weight_jit(position - cell, smooth)
        return np.int64(cell), w, dw * 0.5 * resolution * inside

    @_jit
    def row_jit(i, j, k, resolution, rows, dense):
        """The row of corner ``(i, j, k)`` in a level of ``resolution`` cells and ``rows`` rows."""
        if dense:
            return dense_row_jit(i, j, k, resolution + 1)
        return hashed_row_jit(i, j, k, rows)

    @_jit
    def corner_jit(corner, cx, cy, cz, wx, wy, wz, dx, dy, dz, r, rows, dense):
        """Corner ``corner`` (0..7, bits x, y, z) of the cell at (cx, cy, cz) of a level of
        resolution ``r``: its row in the level, its weight, and the weight's derivatives along u
        (from the per-axis weights ``w*`` and derivatives ``d*`` of :func:`axis_jit`)."""
        bx, by, bz = corner & 1, (corner >> 1) & 1, (corner >> 2) & 1
        ax = wx if bx else 1.0 - wx
        ay = wy if by else 1.0 - wy
        az = wz if bz else 1.0 - wz
        row = row_jit(cx + bx, cy + by, cz + bz, r, rows, dense)
        gx = (dx if bx else -dx) * ay * az
        gy = ax * (dy if by else -dy) * az
        gz = ax * ay * (dz if bz else -dz)
        return row, ax * ay * az, gx, gy, gz

    @_jit
    def cell_rows_jit(cx, cy, cz, r, rows, dense):
        """The rows of the 8 corners of cell (cx, cy, cz) in a level, in :data:`CORNERS`' order
        (the compiler shares the per-axis terms of the eight)."""
        x1, y1, z1 = cx + 1, cy + 1, cz + 1
        return (row_jit(cx, cy, cz, r, rows, dense), row_jit(x1, cy, cz, r, rows, dense),
                row_jit(cx, y1, cz, r, rows, dense), row_jit(x1, y1, cz, r, rows, dense),
                row_jit(cx, cy, z1, r, rows, dense), row_jit(x1, cy, z1, r, rows, dense),
                row_jit(cx, y1, z1, r, rows, dense), row_jit(x1, y1, z1, r, rows, dense))
