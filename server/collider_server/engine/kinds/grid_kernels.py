"""Fused CPU kernels (numba) of the multiresolution grid encoding of :mod:`.neural_grid`.

One pass per point computes, at every level, the 8 corner rows, their (smoothstep or trilinear)
weights and weight derivatives, and accumulates the features and their Jacobian: no (n, L, 8)
temporaries, which is what makes the pure-torch encoding memory-bound on a CPU (about 20 s per
1M points on 2 cores against well under 1 s here). The backward pass scatters the features' and
the Jacobian's gradients into the table, one level per thread (levels own disjoint rows, so no
two threads write the same row). The torch encoding in :mod:`.neural_grid` is the reference these
are tested against, and the path on CUDA.

Layout (shared with the torch code): ``u`` (n, 3) normalised coordinates; ``table`` (rows, F)
float32, level ``l`` at rows ``offset[l] : offset[l] + rows[l]``; a dense level of resolution r
indexes corner (i, j, k) as ``i + (r + 1) * (j + (r + 1) * k)``, a hashed level as
``(i * P0 ^ j * P1 ^ k * P2) & (rows - 1)``.
"""

from __future__ import annotations

import math

import numpy as np

try:
    import numba
except ImportError:  # the engine still works (pure torch), only slower on a CPU
    numba = None

P0, P1, P2 = 1, 2_654_435_761, 805_459_861


def available() -> bool:
    """Whether the fused kernels can run (numba is installed)."""
    return numba is not None


def set_threads(threads: int) -> None:
    """Threads of the kernels (numba's pool; at most the cores numba found)."""
    if numba is not None:
        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))


if numba is not None:
    _jit = numba.njit(cache=True, fastmath=False, nogil=True)
    _pjit = numba.njit(cache=True, fastmath=False, nogil=True, parallel=True)

    @_jit
    def _axis(value, resolution, smooth):
        """Cell index, high-corner weight and its derivative d weight / d u along one axis."""
        inside = 1.0
        if value < -1.0:
            value, inside = -1.0, 0.0
        elif value > 1.0:
            value, inside = 1.0, 0.0
        position = (value + 1.0) * 0.5 * resolution
        cell = math.floor(position)
        if cell > resolution - 1:
            cell = resolution - 1
        t = position - cell
        if smooth:
            w = t * t * (3.0 - 2.0 * t)
            dw = 6.0 * t * (1.0 - t)
        else:
            w = t
            dw = 1.0
        return np.int64(cell), w, dw * 0.5 * resolution * inside

    @_jit
    def _row(i, j, k, resolution, rows, dense):
        if dense:
            side = resolution + 1
            return i + side * (j + side * k)
        return ((i * P0) ^ (j * P1) ^ (k * P2)) & (rows - 1)

    @_jit
    def _corner(corner, cx, cy, cz, wx, wy, wz, dx, dy, dz, r, rows, dense):
        """Corner ``corner`` (0..7, bits x, y, z) of the cell at (cx, cy, cz) of a level of
        resolution ``r``: its row in the level, its trilinear (or smoothstep) weight, and the
        weight's derivatives along u (from the per-axis weights ``w*`` and derivatives ``d*``)."""
        bx, by, bz = corner & 1, (corner >> 1) & 1, (corner >> 2) & 1
        ax = wx if bx else 1.0 - wx
        ay = wy if by else 1.0 - wy
        az = wz if bz else 1.0 - wz
        row = _row(cx + bx, cy + by, cz + bz, r, rows, dense)
        gx = (dx if bx else -dx) * ay * az
        gy = ax * (dy if by else -dy) * az
        gz = ax * ay * (dz if bz else -dz)
        return row, ax * ay * az, gx, gy, gz

    @_pjit
    def encode(u, table, resolution, offset, rows, dense, smooth, want_jacobian, features, jacobian):
        """Fill ``features`` (n, L, F) and, when ``want_jacobian``, ``jacobian`` (n, L, F, 3)
        (d features / d u); both are overwritten."""
        n = u.shape[0]
        levels = resolution.shape[0]
        width = table.shape[1]
        for p in numba.prange(n):
            for level in range(levels):
                r = resolution[level]
                cx, wx, dx = _axis(u[p, 0], r, smooth)
                cy, wy, dy = _axis(u[p, 1], r, smooth)
                cz, wz, dz = _axis(u[p, 2], r, smooth)
                for f in range(width):
                    features[p, level, f] = 0.0
                    if want_jacobian:
                        jacobian[p, level, f, 0] = 0.0
                        jacobian[p, level, f, 1] = 0.0
                        jacobian[p, level, f, 2] = 0.0
                for corner in range(8):
                    row, weight, gx, gy, gz = _corner(corner, cx, cy, cz, wx, wy, wz, dx, dy, dz, r,
                                                      rows[level], dense[level])
                    row += offset[level]
                    for f in range(width):
                        v = table[row, f]
                        features[p, level, f] += weight * v
                        if want_jacobian:
                            jacobian[p, level, f, 0] += gx * v
                            jacobian[p, level, f, 1] += gy * v
                            jacobian[p, level, f, 2] += gz * v

    @_pjit
    def encode_backward(u, resolution, offset, rows, dense, smooth, grad_features, grad_jacobian,
                        has_jacobian, grad_table):
        """Add to ``grad_table`` (rows, F) the gradient of a loss whose gradients with respect to
        the features (n, L, F) and, when ``has_jacobian``, the Jacobian (n, L, F, 3) are given."""
        n = u.shape[0]
        levels = resolution.shape[0]
        width = grad_table.shape[1]
        for level in numba.prange(levels):  # one level per thread: disjoint rows, no races
            r = resolution[level]
            for p in range(n):
                cx, wx, dx = _axis(u[p, 0], r, smooth)
                cy, wy, dy = _axis(u[p, 1], r, smooth)
                cz, wz, dz = _axis(u[p, 2], r, smooth)
                for corner in range(8):
                    row, weight, gx, gy, gz = _corner(corner, cx, cy, cz, wx, wy, wz, dx, dy, dz, r,
                                                      rows[level], dense[level])
                    row += offset[level]
                    for f in range(width):
                        g = weight * grad_features[p, level, f]
                        if has_jacobian:
                            g += (gx * grad_jacobian[p, level, f, 0] + gy * grad_jacobian[p, level, f, 1]
                                  + gz * grad_jacobian[p, level, f, 2])
                        grad_table[row, f] += g

    @numba.njit(cache=True, fastmath=True, nogil=True, parallel=True)
    def network_query(u, table, resolution, offset, rows, dense, smooth, weights, biases, w_out, b_out,
                      scale, want_gradient, distance, gradient):
        """The whole network at normalised points ``u`` (n, 3), fused per point: encoding,
        ReLU MLP (``weights[k]`` (out, in), ``biases[k]`` (out,)), linear output ``w_out`` (in,),
        ``b_out``; ``distance`` (n,) = output * ``scale``; when ``want_gradient``, ``gradient``
        (n, 3) = d output / d u (the MLP backward through the ReLU masks, times the encoding's
        Jacobian). Points are processed in blocks so that the scratch vectors are allocated once
        per block, not per point. Inference only: no table gradients."""
        n = u.shape[0]
        levels = resolution.shape[0]
        width = table.shape[1]
        n_in = levels * width
        depth = len(weights)
        widest = n_in
        for k in range(depth):
            widest = max(widest, weights[k].shape[0])
        block = 256
        for b in numba.prange((n + block - 1) // block):
            feature = np.empty(n_in)
            jac = np.empty((n_in, 3))
            act = np.empty((depth, widest))
            g = np.empty(widest)
            g_next = np.empty(widest)
            for p in range(b * block, min(n, (b + 1) * block)):
                # Encoding and its Jacobian (as in ``encode``).
                for level in range(levels):
                    r = resolution[level]
                    cx, wx, dx = _axis(u[p, 0], r, smooth)
                    cy, wy, dy = _axis(u[p, 1], r, smooth)
                    cz, wz, dz = _axis(u[p, 2], r, smooth)
                    base = level * width
                    for f in range(width):
                        feature[base + f] = 0.0
                        jac[base + f, 0] = 0.0
                        jac[base + f, 1] = 0.0
                        jac[base + f, 2] = 0.0
                    for corner in range(8):
                        row, weight, gx, gy, gz = _corner(corner, cx, cy, cz, wx, wy, wz, dx, dy, dz,
                                                          r, rows[level], dense[level])
                        row += offset[level]
                        if want_gradient:
                            for f in range(width):
                                v = table[row, f]
                                feature[base + f] += weight * v
                                jac[base + f, 0] += gx * v
                                jac[base + f, 1] += gy * v
                                jac[base + f, 2] += gz * v
                        else:  # distance only: no Jacobian work
                            for f in range(width):
                                feature[base + f] += weight * table[row, f]
                # MLP forward, activations kept for the backward pass.
                for k in range(depth):
                    w = weights[k]
                    bias = biases[k]
                    for o in range(w.shape[0]):
                        s = bias[o]
                        if k == 0:
                            for i in range(w.shape[1]):
                                s += w[o, i] * feature[i]
                        else:
                            for i in range(w.shape[1]):
                                s += w[o, i] * act[k - 1, i]
                        act[k, o] = s if s > 0.0 else 0.0
                last = weights[depth - 1].shape[0]
                s = b_out
                for i in range(last):
                    s += w_out[i] * act[depth - 1, i]
                distance[p] = s * scale
                if not want_gradient:
                    continue
                # Backward: d output / d activation, layer by layer, then through the encoding.
                for i in range(last):
                    g[i] = w_out[i]
                for k in range(depth - 1, -1, -1):
                    w = weights[k]
                    for i in range(w.shape[1]):
                        g_next[i] = 0.0
                    for o in range(w.shape[0]):
                        if act[k, o] > 0.0:
                            go = g[o]
                            for i in range(w.shape[1]):
                                g_next[i] += go * w[o, i]
                    for i in range(w.shape[1]):
                        g[i] = g_next[i]
                gu0 = 0.0
                gu1 = 0.0
                gu2 = 0.0
                for i in range(n_in):
                    gu0 += g[i] * jac[i, 0]
                    gu1 += g[i] * jac[i, 1]
                    gu2 += g[i] * jac[i, 2]
                gradient[p, 0] = gu0
                gradient[p, 1] = gu1
                gradient[p, 2] = gu2
