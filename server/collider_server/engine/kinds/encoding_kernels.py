"""The fused CPU encoding kernels (numba) of the grid networks, for training: the features and
their Jacobian at every level of keyframe tables (:func:`encode_keyframes`; a static network's one
table is K = 1) and the backward pass that scatters gradients into the tables. The torch encoding in
:mod:`.neural_grid` is their reference. Part of the kernels :mod:`.grid_kernels` gathers; the
cells' rules are :mod:`.grid_cells`'."""

from __future__ import annotations

from .grid_cells import numba

if numba is not None:
    from .grid_cells import axis_jit, corner_jit

    _pjit = numba.njit(cache=True, fastmath=False, nogil=True, parallel=True)

    @_pjit
    def encode_keyframes(u, key, frac, tables, resolution, offset, rows, dense, smooth, want_jacobian,
                         features, jacobian):
        """The encoding of keyframe tables (K, rows, F), each point at its own time: the features
        of point p are ``(1 - frac[p])`` times those of table ``key[p]`` plus ``frac[p]`` times
        those of table ``key[p] + 1`` (only table ``key[p]`` is read where ``frac[p]`` is 0),
        its Jacobian d features / d u likewise. ``features`` (n, L, F) and, when
        ``want_jacobian``, ``jacobian`` (n, L, F, 3) are overwritten."""
        n = u.shape[0]
        levels = resolution.shape[0]
        width = tables.shape[2]
        for p in numba.prange(n):
            k = key[p]
            b = frac[p]
            a = 1.0 - b
            for level in range(levels):
                r = resolution[level]
                cx, wx, dx = axis_jit(u[p, 0], r, smooth)
                cy, wy, dy = axis_jit(u[p, 1], r, smooth)
                cz, wz, dz = axis_jit(u[p, 2], r, smooth)
                for f in range(width):
                    features[p, level, f] = 0.0
                    if want_jacobian:
                        jacobian[p, level, f, 0] = 0.0
                        jacobian[p, level, f, 1] = 0.0
                        jacobian[p, level, f, 2] = 0.0
                for corner in range(8):
                    row, weight, gx, gy, gz = corner_jit(corner, cx, cy, cz, wx, wy, wz, dx, dy, dz, r,
                                                         rows[level], dense[level])
                    row += offset[level]
                    for f in range(width):
                        v = tables[k, row, f]
                        if b != 0.0:
                            v = a * v + b * tables[k + 1, row, f]
                        features[p, level, f] += weight * v
                        if want_jacobian:
                            jacobian[p, level, f, 0] += gx * v
                            jacobian[p, level, f, 1] += gy * v
                            jacobian[p, level, f, 2] += gz * v

    @_pjit
    def encode_keyframes_backward(u, key, frac, resolution, offset, rows, dense, smooth, grad_features,
                                  grad_jacobian, has_jacobian, grad_tables):
        """The backward pass of :func:`encode_keyframes`: adds to ``grad_tables`` (K, rows, F) the
        gradient of a loss whose gradients with respect to the features (n, L, F) and, when
        ``has_jacobian``, the Jacobian (n, L, F, 3) are given; one level per thread (a level's
        rows are disjoint from every other level's in every keyframe table: no races)."""
        n = u.shape[0]
        levels = resolution.shape[0]
        width = grad_tables.shape[2]
        for level in numba.prange(levels):
            r = resolution[level]
            for p in range(n):
                k = key[p]
                b = frac[p]
                a = 1.0 - b
                cx, wx, dx = axis_jit(u[p, 0], r, smooth)
                cy, wy, dy = axis_jit(u[p, 1], r, smooth)
                cz, wz, dz = axis_jit(u[p, 2], r, smooth)
                for corner in range(8):
                    row, weight, gx, gy, gz = corner_jit(corner, cx, cy, cz, wx, wy, wz, dx, dy, dz, r,
                                                         rows[level], dense[level])
                    row += offset[level]
                    for f in range(width):
                        g = weight * grad_features[p, level, f]
                        if has_jacobian:
                            g += (gx * grad_jacobian[p, level, f, 0] + gy * grad_jacobian[p, level, f, 1]
                                  + gz * grad_jacobian[p, level, f, 2])
                        grad_tables[k, row, f] += a * g
                        if b != 0.0:
                            grad_tables[k + 1, row, f] += b * g
