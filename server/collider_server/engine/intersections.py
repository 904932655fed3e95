"""Where a triangle mesh passes through itself: the pairs of faces that cross and the segment each
pair has in common (numpy, float64, the mesh's units and frame).

The one home of the self-intersection test: the mesh check counts the pairs
(:mod:`collider_server.making.mesh_check`) and the union's boundary cuts faces along the segments
(:mod:`collider_server.engine.union`). Own code, so the project's MIT licence holds (libigl's
exact test is in its GPL-licensed CGAL module).

Candidates: pairs of faces whose bounding boxes overlap, found by hashing each box into a uniform
grid (cells of the median face size) and pairing the faces that share a cell. Test:
Moller's interval test on every candidate at once: the signed distances of each triangle's
corners to the other's plane, the segment each triangle has on the line the two planes share,
and the overlap of the two segments. Corners within ``1e-12`` of the mesh's size of a plane count
as on it. Faces that share an edge (by position, so vertices split along texture seams count as
shared) are never a crossing, nor a pair that meets only at its shared corner; coplanar pairs
cross when their interiors overlap (a separating-axis test in their plane).

Where numba is installed, :mod:`.intersection_kernels` finds the candidates of meshes up to
20,000 faces and drops those the test would drop first; these numpy functions stay the reference
and decide every pair (the same answer either way).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Corners closer than this times the mesh's bounding-box diagonal to a plane lie on it, and
#: segments shorter than it are points.
RELATIVE_TOLERANCE = 1e-12

#: Candidate pairs tested per numpy pass (bounds the temporary arrays: about 1 KB per pair).
CHUNK_PAIRS = 200_000


@dataclass(frozen=True)
class SelfIntersections:
    """Faces of one mesh that cross each other.

    pairs : (m, 2) int64 face indices, the smaller first, each pair once
    segments : (m, 2, 3) float64, the two ends of the segment the pair has in common (mesh
        units and frame); zeros for a coplanar pair (their common part is a polygon)
    coplanar : (m,) bool, the pair lies in one plane and their interiors overlap
    """

    pairs: np.ndarray
    segments: np.ndarray
    coplanar: np.ndarray

    def __len__(self) -> int:
        return len(self.pairs)


def self_intersections(vertices: np.ndarray, faces: np.ndarray, fast: bool = True) -> SelfIntersections:
    """The pairs of ``faces`` (f, 3) int of ``vertices`` (v, 3) float64 that cross: their
    interiors meet along a segment of positive length, or (coplanar) over a positive area, in
    (i, j) order. Pairs that only touch (at a point, or along a shared edge) are left out.
    Zero-area faces cross nothing. ``fast``: the broad phase and the first test's pre-filter in
    numba where it is installed (:mod:`.intersection_kernels`; the same answer, 5 to 10 times
    sooner); False: numpy only (the reference)."""
    from . import intersection_kernels as kernels

    fast = fast and kernels.numba is not None
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    empty = SelfIntersections(np.zeros((0, 2), np.int64), np.zeros((0, 2, 3)), np.zeros(0, bool))
    if len(faces) < 2:
        return empty
    tri = vertices[faces]  # (f, 3, 3)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normals, axis=1)
    lo, hi = face_boxes(tri)
    scale = diagonal(lo, hi)
    tol = RELATIVE_TOLERANCE * max(scale, 1e-300)
    area_ok = length > tol * tol
    unit = normals / np.where(area_ok, length, 1.0)[:, None]
    if fast and len(faces) <= kernels.SWEEP_MAX_BOXES:
        candidates = kernels.box_pairs(lo, hi)
    else:
        candidates = overlapping_boxes(lo, hi)
        candidates = candidates[np.lexsort((candidates[:, 1], candidates[:, 0]))]
    candidates = candidates[area_ok[candidates[:, 0]] & area_ok[candidates[:, 1]]]
    if fast:  # most candidates are neighbours touching at a corner: drop them before numpy
        candidates = candidates[kernels.may_cross(tri, unit, candidates, tol)]
    found = []
    for start in range(0, len(candidates), CHUNK_PAIRS):
        pairs = candidates[start : start + CHUNK_PAIRS]
        hit, segment, coplanar = crossings(tri[pairs[:, 0]], tri[pairs[:, 1]], unit[pairs[:, 0]],
                                           unit[pairs[:, 1]], tol)
        found.append((pairs[hit], segment[hit], coplanar[hit]))
    if not found:
        return empty
    pairs, segments, coplanar = (np.concatenate(a) for a in zip(*found))
    return SelfIntersections(pairs, segments, coplanar)


def face_boxes(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle's bounding box: ``(lo, hi)``, (f, 3) float64 each, of triangles ``tri``
    (f, 3, 3): ``tri.min(axis=1)`` and ``tri.max(axis=1)``, corner by corner (numpy reduces
    an axis of three slowly: 2 ms against 0.3 for the arm's 5k faces, at every pose of a
    skinned kind)."""
    lo = np.minimum(np.minimum(tri[:, 0], tri[:, 1]), tri[:, 2])
    hi = np.maximum(np.maximum(tri[:, 0], tri[:, 1]), tri[:, 2])
    return lo, hi


def extent(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(3,) float64: the size along each axis of the box holding the boxes ``lo``, ``hi``
    (n, 3): ``hi.max(axis=0) - lo.min(axis=0)``, the columns made contiguous first (numpy
    reduces the rows of an (n, 3) array some 30 times slower)."""
    return np.ascontiguousarray(hi.T).max(axis=1) - np.ascontiguousarray(lo.T).min(axis=1)


def diagonal(lo: np.ndarray, hi: np.ndarray) -> float:
    """The diagonal of the box holding the boxes ``lo``, ``hi`` (n, 3) (a mesh's faces',
    :func:`face_boxes`): the size :data:`RELATIVE_TOLERANCE` is relative to."""
    return float(np.linalg.norm(extent(lo, hi)))


def overlapping_boxes(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(m, 2) int64 pairs ``i < j`` of the boxes ``lo``, ``hi`` (n, 3) float64 that overlap
    (touching counts), each once: the boxes hashed into a uniform grid, the pairs of each cell,
    then the exact box test."""
    n = len(lo)
    if n < 2:
        return np.zeros((0, 2), np.int64)
    extent = hi - lo
    size = float(np.median(extent.max(axis=1)))
    span = float((hi.max(axis=0) - lo.min(axis=0)).max())
    cell = size if size > 0 else max(span, 1e-300)
    origin = lo.min(axis=0)
    while True:  # coarser cells until the boxes cover few enough of them (huge faces)
        first = np.floor((lo - origin) / cell).astype(np.int64)
        last = np.floor((hi - origin) / cell).astype(np.int64)
        dims = last - first + 1
        counts = dims.prod(axis=1)
        if counts.sum() <= 16 * n + 4096:
            break
        cell *= 2.0
    box = np.repeat(np.arange(n), counts)
    offset = np.arange(len(box)) - np.repeat(np.cumsum(counts) - counts, counts)
    d = dims[box]
    index = first[box] + np.stack([offset % d[:, 0], (offset // d[:, 0]) % d[:, 1],
                                   offset // (d[:, 0] * d[:, 1])], axis=1)
    size3 = last.max(axis=0) + 1
    key = (index[:, 2] * size3[1] + index[:, 1]) * size3[0] + index[:, 0]
    order = np.argsort(key, kind="stable")
    key, box, index = key[order], box[order], index[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ends = np.r_[starts[1:], len(key)]
    group_end = np.repeat(ends, ends - starts)
    after = group_end - np.arange(len(key)) - 1  # entries after each one in its cell
    i = np.repeat(np.arange(len(key)), after)
    j = i + 1 + (np.arange(len(i)) - np.repeat(np.cumsum(after) - after, after))
    a, b = box[i], box[j]
    # Axis by axis, the boxes' overlap and (so that no pair comes twice) whether this cell is
    # the one of the overlap's low corner: the pair shares every cell of that overlap.
    for axis in range(3):
        low, high, start = (np.ascontiguousarray(x[:, axis]) for x in (lo, hi, first))
        keep = ((low[a] <= high[b]) & (low[b] <= high[a])
                & (np.maximum(start[a], start[b]) == index[i, axis]))
        a, b, i = a[keep], b[keep], i[keep]
    return np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)


def crossings(a: np.ndarray, b: np.ndarray, na: np.ndarray, nb: np.ndarray, tol: float):
    """Moller's test on triangle pairs ``a``, ``b`` (m, 3, 3) with unit normals ``na``, ``nb``
    (m, 3): ``(hit (m,) bool, segment (m, 2, 3), coplanar (m,) bool)``, hit where the two
    interiors meet along more than a point (segment: its two ends) or, coplanar, over a
    positive area (segment: zeros). Corners at the same position in both count as shared: a pair sharing two
    never hits, one sharing one hits only beyond that corner."""
    da = np.einsum("mkc,mc->mk", a - b[:, :1], nb)  # a's corners to b's plane
    db = np.einsum("mkc,mc->mk", b - a[:, :1], na)
    hit = np.zeros(len(a), dtype=bool)
    segment = np.zeros((len(a), 2, 3))
    coplanar = np.zeros(len(a), dtype=bool)
    # Only a triangle with corners on both sides of the other's plane, or an edge in it, can
    # meet it in more than a point (most candidates are neighbours that touch at a corner).
    maybe = np.flatnonzero(_straddles(da, tol) & _straddles(db, tol))
    if not len(maybe):
        return hit, segment, coplanar
    a, b, na, nb, da, db = a[maybe], b[maybe], na[maybe], nb[maybe], da[maybe], db[maybe]
    same = (a[:, :, None, :] == b[:, None, :, :]).all(axis=3)  # (m, 3, 3) corner of a == corner of b
    shared_a, shared_b = same.any(axis=2), same.any(axis=1)
    edge_shared = shared_a.sum(axis=1) >= 2
    da[shared_a] = 0.0
    db[shared_b] = 0.0
    sa = np.where(np.abs(da) <= tol, 0, np.sign(da)).astype(np.int8)
    sb = np.where(np.abs(db) <= tol, 0, np.sign(db)).astype(np.int8)
    flat = (sa == 0).all(1) & (sb == 0).all(1)
    found = np.zeros(len(a), dtype=bool)
    ends = np.zeros((len(a), 2, 3))
    test = ~flat & ~edge_shared & _straddles(da, tol) & _straddles(db, tol)
    if test.any():
        direction = np.cross(na[test], nb[test])
        direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
        lo_a, hi_a, pa_lo, pa_hi = _on_line(a[test], da[test], sa[test], direction)
        lo_b, hi_b, pb_lo, pb_hi = _on_line(b[test], db[test], sb[test], direction)
        lo = np.maximum(lo_a, lo_b)
        hi = np.minimum(hi_a, hi_b)
        start = np.where((lo_a >= lo_b)[:, None], pa_lo, pb_lo)
        end = np.where((hi_a <= hi_b)[:, None], pa_hi, pb_hi)
        found[test] = hi - lo > tol
        ends[test] = np.stack([start, end], axis=1)
    flat &= ~edge_shared
    if flat.any():
        found[flat] = _coplanar_overlap(a[flat], b[flat], na[flat], tol)
    hit[maybe], segment[maybe], coplanar[maybe] = found, ends, flat & found
    return hit, segment, coplanar


def _straddles(d: np.ndarray, tol: float) -> np.ndarray:
    """(m,) bool: a triangle whose corners are ``d`` (m, 3) from a plane has corners on both
    sides of it, or at least two in it."""
    d0, d1, d2 = d[:, 0], d[:, 1], d[:, 2]
    high = np.maximum(np.maximum(d0, d1), d2)
    low = np.minimum(np.minimum(d0, d1), d2)
    zeros = (np.abs(d0) <= tol).astype(np.int8) + (np.abs(d1) <= tol) + (np.abs(d2) <= tol)
    return ((high > tol) & (low < -tol)) | (zeros >= 2)


def _on_line(tri, d, s, direction):
    """The segment a triangle (m, 3, 3) has in the other's plane (its corners' distances ``d``
    and signs ``s`` (m, 3)), as positions along ``direction`` (m, 3) (lo, hi (m,)) and its two
    end points (m, 3)."""
    points, valid = [], []
    for k in range(3):
        points.append(tri[:, k])
        valid.append(s[:, k] == 0)
    for k in range(3):
        i, j = k, (k + 1) % 3
        crossing = (s[:, i].astype(np.int16) * s[:, j]) < 0
        u = d[:, i] / np.where(crossing, d[:, i] - d[:, j], 1.0)
        points.append(tri[:, i] + u[:, None] * (tri[:, j] - tri[:, i]))
        valid.append(crossing)
    points = np.stack(points, axis=1)  # (m, 6, 3)
    valid = np.stack(valid, axis=1)
    t = np.einsum("mkc,mc->mk", points, direction)
    rows = np.arange(len(t))
    low = np.argmin(np.where(valid, t, np.inf), axis=1)
    high = np.argmax(np.where(valid, t, -np.inf), axis=1)
    lo = np.where(valid.any(1), t[rows, low], np.inf)
    hi = np.where(valid.any(1), t[rows, high], -np.inf)
    return lo, hi, points[rows, low], points[rows, high]


def _coplanar_overlap(a, b, normal, tol):
    """(m,) bool: coplanar triangles ``a``, ``b`` (m, 3, 3) overlap over a positive area (no
    separating axis among their six edge normals, in the plane their ``normal`` (m, 3) is
    least oblique to)."""
    axis = np.argmax(np.abs(normal), axis=1)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis][:, None, :]  # drop the normal's largest coordinate
    pa, pb = np.take_along_axis(a, keep, axis=2), np.take_along_axis(b, keep, axis=2)
    separated = np.zeros(len(a), dtype=bool)
    for tri in (pa, pb):
        for k in range(3):
            edge = tri[:, (k + 1) % 3] - tri[:, k]
            across = np.stack([-edge[:, 1], edge[:, 0]], axis=1)
            across /= np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-300)
            on_a = np.einsum("mkc,mc->mk", pa, across)
            on_b = np.einsum("mkc,mc->mk", pb, across)
            separated |= (on_a.max(1) <= on_b.min(1) + tol) | (on_b.max(1) <= on_a.min(1) + tol)
    return ~separated
