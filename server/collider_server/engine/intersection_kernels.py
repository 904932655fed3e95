"""The self-intersection finder's fast paths (numba, CPU): the broad phase of meshes up to
:data:`SWEEP_MAX_BOXES` faces (pairs of overlapping face boxes, sweep and prune) and a pre-filter that drops the candidates Moller's test would drop
first. :mod:`.intersections` calls them when numba is present; its numpy functions
(:func:`~.intersections.overlapping_boxes`, :func:`~.intersections.crossings`) stay the reference
and decide every answer: the broad phase finds the same set of pairs, and the pre-filter keeps a
superset of what the test keeps (a margin of half the tolerance covers its rounding), so a
mesh's crossings are the same with or without numba.
"""

from __future__ import annotations

import numpy as np

try:
    import numba
except ImportError:  # the finder still works (numpy), only slower
    numba = None

#: Faces up to which the sweep beats the numpy grid (:func:`~.intersections.overlapping_boxes`):
#: 2x sooner on the 8k-face walker, 1.3x slower on the 69k-face bunny (one slab holds too many).
SWEEP_MAX_BOXES = 20_000

if numba is not None:
    _jit = numba.njit(cache=True, fastmath=False, nogil=True)

    @_jit
    def _sweep(lo, hi, axis, order):
        """(2 m,) int64: the pairs i < j of boxes ``lo``, ``hi`` (n, 3) float64 that overlap
        (touching counts), found by a sweep along ``axis`` over the boxes in ``order`` (sorted by
        their low end on it), each once, in no particular order, flat (i, j, i, j, ...). The sorts
        are numpy's (:func:`box_pairs`), and the array flat, because numba compiles its sorts
        and 2-D slices slowly (~15 s of CPU against ~1 s without)."""
        n = lo.shape[0]
        out = np.empty(32 * n + 32, np.int64)
        m = 0
        for s in range(n):
            i = order[s]
            end = hi[i, axis]
            for t in range(s + 1, n):
                j = order[t]
                if lo[j, axis] > end:
                    break
                if (lo[i, 0] <= hi[j, 0] and lo[j, 0] <= hi[i, 0] and lo[i, 1] <= hi[j, 1]
                        and lo[j, 1] <= hi[i, 1] and lo[i, 2] <= hi[j, 2] and lo[j, 2] <= hi[i, 2]):
                    if 2 * m == out.shape[0]:
                        grown = np.empty(4 * m, np.int64)
                        for c in range(2 * m):
                            grown[c] = out[c]
                        out = grown
                    out[2 * m] = min(i, j)
                    out[2 * m + 1] = max(i, j)
                    m += 1
        return out[:2 * m]

    @_jit
    def _straddle(d0, d1, d2, tol, slack):
        """Whether a triangle whose corners are ``d0``, ``d1``, ``d2`` from a plane may have
        corners on both sides of it or two in it (:func:`~.intersections._straddles` with the
        tolerance widened by ``slack`` both ways: never False where that one is True)."""
        high = max(max(d0, d1), d2)
        low = min(min(d0, d1), d2)
        zeros = ((abs(d0) <= tol + slack) + (abs(d1) <= tol + slack) + (abs(d2) <= tol + slack))
        return (high > tol - slack and low < -tol + slack) or zeros >= 2

    @_jit
    def _may_cross(tri, unit, pairs, tol, slack):
        """(m,) bool per candidate pair (m, 2) of triangles ``tri`` (f, 3, 3) with unit normals
        ``unit`` (f, 3): each triangle may straddle the other's plane, before and after the
        corners the two share (same position) are put on it, they share fewer than two corners,
        and (sharing one) their segments do not leave it on opposite sides (Moller's tests, as
        :func:`~.intersections.crossings` makes them, with margins)."""
        m = pairs.shape[0]
        keep = np.zeros(m, np.bool_)
        da = np.empty(3)
        db = np.empty(3)
        for p in range(m):
            a = pairs[p, 0]
            b = pairs[p, 1]
            for k in range(3):
                da[k] = ((tri[a, k, 0] - tri[b, 0, 0]) * unit[b, 0] + (tri[a, k, 1] - tri[b, 0, 1]) * unit[b, 1]
                         + (tri[a, k, 2] - tri[b, 0, 2]) * unit[b, 2])
                db[k] = ((tri[b, k, 0] - tri[a, 0, 0]) * unit[a, 0] + (tri[b, k, 1] - tri[a, 0, 1]) * unit[a, 1]
                         + (tri[b, k, 2] - tri[a, 0, 2]) * unit[a, 2])
            if not (_straddle(da[0], da[1], da[2], tol, slack) and _straddle(db[0], db[1], db[2], tol, slack)):
                continue
            shared = 0  # corners of a at a corner of b
            ka = kb = -1
            for i in range(3):
                on_b = False
                for j in range(3):
                    if (tri[a, i, 0] == tri[b, j, 0] and tri[a, i, 1] == tri[b, j, 1]
                            and tri[a, i, 2] == tri[b, j, 2]):
                        on_b = True
                        da[i] = 0.0
                        db[j] = 0.0
                        ka = i
                        kb = j
                shared += on_b
            if shared >= 2:
                continue
            if not (_straddle(da[0], da[1], da[2], tol, slack) and _straddle(db[0], db[1], db[2], tol, slack)):
                continue
            if shared == 1 and _apart_at_corner(tri, unit, a, b, ka, kb, da, db, tol, slack):
                continue
            keep[p] = True
        return keep

    @_jit
    def _beyond_corner(tri, t, k, d, direction, tol, slack):
        """Triangle ``t`` with its corner ``k`` on the other's plane (the shared one) and its
        distances ``d`` (3,) to that plane: +1 or -1, the side along ``direction`` on which its
        segment in that plane leaves the corner, where the other two corners lie clearly on either
        side of the plane (the segment ends on the edge between them) or one clearly in it and one
        clearly off it (the segment ends at the first); 0 in other cases or too close to tell."""
        i = (k + 1) % 3
        j = (k + 2) % 3
        low = tol - slack
        high = tol + slack
        if abs(d[i]) > high and abs(d[j]) > high and d[i] * d[j] < 0.0:
            u = d[i] / (d[i] - d[j])
        elif abs(d[i]) <= low and abs(d[j]) > high:
            u = 0.0
        elif abs(d[j]) <= low and abs(d[i]) > high:
            u = 1.0
        else:
            return 0
        along = 0.0
        norm = 0.0
        for c in range(3):
            x = tri[t, i, c] + u * (tri[t, j, c] - tri[t, i, c]) - tri[t, k, c]
            along += x * direction[c]
            norm += direction[c] * direction[c]
        if abs(along) <= 1e3 * high * norm ** 0.5:
            return 0
        return 1 if along > 0.0 else -1

    @_jit
    def _apart_at_corner(tri, unit, a, b, ka, kb, da, db, tol, slack):
        """Two triangles sharing one corner (``ka`` of ``a``, ``kb`` of ``b``) that meet in that
        corner only: both lie clearly in one plane and an edge separates them clearly (the
        coplanar test's axes), or each crosses the other's plane through the corner and their
        segments on the planes' common line leave it on opposite sides."""
        if abs(da[0]) <= tol - slack and abs(da[1]) <= tol - slack and abs(da[2]) <= tol - slack \
                and abs(db[0]) <= tol - slack and abs(db[1]) <= tol - slack and abs(db[2]) <= tol - slack:
            return _separated_in_plane(tri, unit, a, b, tol - slack)
        direction = np.empty(3)
        direction[0] = unit[a, 1] * unit[b, 2] - unit[a, 2] * unit[b, 1]
        direction[1] = unit[a, 2] * unit[b, 0] - unit[a, 0] * unit[b, 2]
        direction[2] = unit[a, 0] * unit[b, 1] - unit[a, 1] * unit[b, 0]
        side_a = _beyond_corner(tri, a, ka, da, direction, tol, slack)
        side_b = _beyond_corner(tri, b, kb, db, direction, tol, slack)
        return side_a * side_b < 0

    @_jit
    def _separated_in_plane(tri, unit, a, b, gap):
        """Coplanar triangles ``a``, ``b``: one of their six edge normals, in the plane of the two
        coordinates ``a``'s normal is least oblique to, separates them by more than ``-gap``
        (:func:`~.intersections._coplanar_overlap`'s axes and rule, with ``gap`` below its
        tolerance)."""
        drop = 0
        for c in range(1, 3):
            if abs(unit[a, c]) > abs(unit[a, drop]):
                drop = c
        x = 1 if drop == 0 else 0
        y = 1 if drop == 2 else 2
        for owner in (a, b):
            for k in range(3):
                ex = tri[owner, (k + 1) % 3, x] - tri[owner, k, x]
                ey = tri[owner, (k + 1) % 3, y] - tri[owner, k, y]
                length = max((ex * ex + ey * ey) ** 0.5, 1e-300)
                nx = -ey / length
                ny = ex / length
                lo_a = hi_a = tri[a, 0, x] * nx + tri[a, 0, y] * ny
                lo_b = hi_b = tri[b, 0, x] * nx + tri[b, 0, y] * ny
                for c in range(1, 3):
                    va = tri[a, c, x] * nx + tri[a, c, y] * ny
                    vb = tri[b, c, x] * nx + tri[b, c, y] * ny
                    lo_a = min(lo_a, va)
                    hi_a = max(hi_a, va)
                    lo_b = min(lo_b, vb)
                    hi_b = max(hi_b, vb)
                if hi_a <= lo_b + gap or hi_b <= lo_a + gap:
                    return True
        return False

def box_pairs(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(m, 2) int64 pairs ``i < j`` of the boxes ``lo``, ``hi`` (n, 3) float64 that overlap
    (touching counts): the set :func:`~.intersections.overlapping_boxes` finds, in (i, j) order."""
    if len(lo) < 2:
        return np.zeros((0, 2), np.int64)
    lo = np.ascontiguousarray(lo, dtype=np.float64)
    hi = np.ascontiguousarray(hi, dtype=np.float64)
    from .intersections import extent

    axis = int(np.argmax(extent(lo, hi)))  # the longest: thinnest slabs
    n = len(lo)
    found = _sweep(lo, hi, axis, np.argsort(lo[:, axis], kind="stable")).reshape(-1, 2)
    key = np.sort(found[:, 0] * n + found[:, 1])
    return np.stack([key // n, key % n], axis=1)


def may_cross(tri: np.ndarray, unit: np.ndarray, pairs: np.ndarray, tol: float) -> np.ndarray:
    """(m,) bool: the candidate ``pairs`` (m, 2) of triangles ``tri`` (f, 3, 3) float64 with unit
    normals ``unit`` (f, 3) that Moller's test must look at (each straddles the other's plane,
    ``tol`` as in :func:`~.intersections.crossings`, widened by half of it for rounding)."""
    return _may_cross(np.ascontiguousarray(tri), np.ascontiguousarray(unit), np.ascontiguousarray(pairs),
                      tol, 0.5 * tol)
