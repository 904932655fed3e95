"""The fused CPU warp kernel (numba) of the deformed network (:mod:`.neural_deformed`): the rest
point, its Jacobian and the material velocity at each query point. The torch warp in
:mod:`.neural_deformed` is its reference. Part of the kernels :mod:`.grid_kernels` gathers; the
cells' rules are :mod:`.grid_cells`'."""

from __future__ import annotations

from .grid_cells import numba

if numba is not None:
    from .grid_cells import axis_jit, cell_rows_jit, trilerp_jit

    _pjit = numba.njit(cache=True, fastmath=False, nogil=True, parallel=True)

    @_pjit
    def warp(u, field, dfield, resolution, want_velocity, rest, jacobian, velocity):
        """The deformed network's warp (:mod:`.neural_deformed`) at normalised points ``u``
        (n, 3): the trilinear field (nodes, 3) of ``resolution`` cells per side gives the rest
        point ``rest = u + W(u)`` (n, 3) and ``jacobian = d rest / d u`` (n, 3, 3, row: the rest
        point's component); when ``want_velocity``, ``velocity`` (n, 3) = ``-jacobian^-1 dW(u)``
        with ``dfield`` the field's time derivative: the material point's velocity (normalised
        units per second). Outputs overwritten."""
        n = u.shape[0]
        for p in numba.prange(n):
            cx, wx, dx = axis_jit(u[p, 0], resolution, False)
            cy, wy, dy = axis_jit(u[p, 1], resolution, False)
            cz, wz, dz = axis_jit(u[p, 2], resolution, False)
            c0, c1, c2, c3, c4, c5, c6, c7 = cell_rows_jit(cx, cy, cz, resolution, 0, True)
            o0, j00, j01, j02 = trilerp_jit(field[c0, 0], field[c1, 0], field[c2, 0], field[c3, 0],
                                         field[c4, 0], field[c5, 0], field[c6, 0], field[c7, 0], wx, wy, wz)
            o1, j10, j11, j12 = trilerp_jit(field[c0, 1], field[c1, 1], field[c2, 1], field[c3, 1],
                                         field[c4, 1], field[c5, 1], field[c6, 1], field[c7, 1], wx, wy, wz)
            o2, j20, j21, j22 = trilerp_jit(field[c0, 2], field[c1, 2], field[c2, 2], field[c3, 2],
                                         field[c4, 2], field[c5, 2], field[c6, 2], field[c7, 2], wx, wy, wz)
            # d/dw to d/du: the weights' derivatives along each axis
            j00, j01, j02 = j00 * dx, j01 * dy, j02 * dz
            j10, j11, j12 = j10 * dx, j11 * dy, j12 * dz
            j20, j21, j22 = j20 * dx, j21 * dy, j22 * dz
            r0 = r1 = r2 = 0.0
            if want_velocity:
                r0 = trilerp_jit(dfield[c0, 0], dfield[c1, 0], dfield[c2, 0], dfield[c3, 0],
                              dfield[c4, 0], dfield[c5, 0], dfield[c6, 0], dfield[c7, 0], wx, wy, wz)[0]
                r1 = trilerp_jit(dfield[c0, 1], dfield[c1, 1], dfield[c2, 1], dfield[c3, 1],
                              dfield[c4, 1], dfield[c5, 1], dfield[c6, 1], dfield[c7, 1], wx, wy, wz)[0]
                r2 = trilerp_jit(dfield[c0, 2], dfield[c1, 2], dfield[c2, 2], dfield[c3, 2],
                              dfield[c4, 2], dfield[c5, 2], dfield[c6, 2], dfield[c7, 2], wx, wy, wz)[0]
            rest[p, 0] = u[p, 0] + o0
            rest[p, 1] = u[p, 1] + o1
            rest[p, 2] = u[p, 2] + o2
            j00 += 1.0
            j11 += 1.0
            j22 += 1.0
            jacobian[p, 0, 0], jacobian[p, 0, 1], jacobian[p, 0, 2] = j00, j01, j02
            jacobian[p, 1, 0], jacobian[p, 1, 1], jacobian[p, 1, 2] = j10, j11, j12
            jacobian[p, 2, 0], jacobian[p, 2, 1], jacobian[p, 2, 2] = j20, j21, j22
            if want_velocity:
                # -J^-1 r by Cramer's rule (J is near the identity: a smooth fitted deformation).
                c00, c01, c02 = j11 * j22 - j12 * j21, j02 * j21 - j01 * j22, j01 * j12 - j02 * j11
                c10, c11, c12 = j12 * j20 - j10 * j22, j00 * j22 - j02 * j20, j02 * j10 - j00 * j12
                c20, c21, c22 = j10 * j21 - j11 * j20, j01 * j20 - j00 * j21, j00 * j11 - j01 * j10
                det = j00 * c00 + j01 * c10 + j02 * c20
                if det == 0.0:
                    det = 1e-30
                velocity[p, 0] = -(c00 * r0 + c01 * r1 + c02 * r2) / det
                velocity[p, 1] = -(c10 * r0 + c11 * r1 + c12 * r2) / det
                velocity[p, 2] = -(c20 * r0 + c21 * r1 + c22 * r2) / det
