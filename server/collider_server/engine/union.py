"""The boundary of the region a self-overlapping triangle mesh encloses: where the generalised
winding number exceeds 1/2 (numpy, float64, the mesh's units and frame).

A mesh that passes through itself (a linear-blend skin folding hip into thigh, two closed boxes
written as one mesh) encloses its overlap twice: points there have a winding number near 2, and
the faces buried inside the body are nearer to them than the body's surface. The exact SDF
(:class:`~collider_server.engine.meshes.ExactSDF`) measures distance, closest point and normal to
the boundary this module builds, so that a contact lands outside the body.

How: the faces that cross others (:func:`~collider_server.engine.intersections.self_intersections`)
are cut, in their plane, by the full lines of their intersection segments (and, for a face lying
in another's plane over a shared area, by that face's edge lines) into convex cells; no
intersection curve runs through a cell, so the winding number just off it is the same all over
each side. A cell is kept when the winding number just behind it (against its normal) exceeds
1/2 and just in front of it does not, tested a small step off its centroid on both sides (the
winding number of the original mesh jumps by exactly 1 across a face, along its normal, so a
kept cell's normal already points outside: nothing is flipped). The faces that cross nothing form
regions (connected through shared edges) that no curve crosses: each is kept or dropped whole by
the same test at its largest faces (the majority), which drops a piece buried in another. Kept
cells are fan-triangulated (T-junctions along the cuts are harmless to distance queries).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .intersections import RELATIVE_TOLERANCE, SelfIntersections, self_intersections

#: Faces tested per region of faces that cross nothing (its largest); the majority decides.
REGION_SAMPLES = 3


@dataclass(frozen=True)
class UnionSurface:
    """The union's boundary where it is not the mesh itself.

    vertices : (n, 3) float64, the mesh's vertices first, then the corners of the cut cells
    faces : (k, 3) int64 triangles into ``vertices``, wound as the faces they come from
    source : (k,) int64, the mesh's face each triangle lies in (a subset of it, in its plane, so
        that barycentric coordinates in the source face map a point of the union to the mesh)
    crossing_pairs : pairs of the mesh's faces that cross
    cut_faces : faces cut into cells; dropped_faces : faces left out whole (buried)
    """

    vertices: np.ndarray
    faces: np.ndarray
    source: np.ndarray
    crossing_pairs: int
    cut_faces: int
    dropped_faces: int


def union_surface(vertices: np.ndarray, faces: np.ndarray, winding, edges: np.ndarray,
                  crossings: SelfIntersections | None = None) -> UnionSurface | None:
    """The boundary of ``{winding > 1/2}`` of the mesh ``vertices`` (v, 3) float64 and ``faces``
    (f, 3) int64, or None when it is the mesh itself (nothing crosses and no piece is buried,
    or nothing would be left). ``winding(points (m, 3)) -> (m,)``: the mesh's generalised
    winding number; ``edges``: :func:`~collider_server.engine.meshes.edge_index` of the faces;
    ``crossings``: the mesh's :func:`self_intersections` when the caller has them."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if crossings is None:
        crossings = self_intersections(vertices, faces)
    tri = vertices[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(normals, axis=1)
    unit = normals / np.where(double_area > 0, double_area, 1.0)[:, None]
    scale = float(np.linalg.norm(tri.max(axis=(0, 1)) - tri.min(axis=(0, 1))))
    cut = np.zeros(len(faces), dtype=bool)
    cut[crossings.pairs.reshape(-1)] = True

    # Regions: faces that cross nothing, connected through their edges.
    whole = np.flatnonzero(~cut)
    n_edges = int(edges.max()) + 1 if len(edges) else 0
    rows = np.repeat(whole, 3)
    cols = len(faces) + edges[whole].reshape(-1)
    size = len(faces) + n_edges
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(size, size))
    labels = connected_components(graph, directed=False)[1][whole]
    regions, labels = np.unique(labels, return_inverse=True)
    if not len(crossings) and len(regions) <= 1:
        return None

    # The largest few faces of each region, then the cells of the cut faces: one winding
    # number evaluation for all of them.
    order = np.lexsort((-double_area[whole], labels))
    first = np.r_[0, np.flatnonzero(np.diff(labels[order])) + 1]
    rank = np.arange(len(order)) - np.repeat(first, np.diff(np.r_[first, len(order)]))
    sampled = order[(rank < REGION_SAMPLES) & (double_area[whole[order]] > 0)]
    sample_faces = whole[sampled]
    sample_centre = tri[sample_faces].mean(axis=1)
    sample_step = 1e-4 * np.sqrt(double_area[sample_faces])
    cells, cell_face, cell_step = _cells(tri, unit, crossings, np.flatnonzero(cut), scale)
    cell_centre = np.array([c.mean(axis=0) for c in cells]).reshape(-1, 3)
    centres = np.concatenate([sample_centre, cell_centre])
    normal = unit[np.concatenate([sample_faces, cell_face])]
    step = np.maximum(np.concatenate([sample_step, cell_step]), 1e-10 * scale)[:, None]
    w = winding(np.concatenate([centres + step * normal, centres - step * normal]))
    front, back = w[: len(centres)], w[len(centres):]
    boundary = (back > 0.5) & (front <= 0.5)

    votes = np.zeros(len(regions))
    counts = np.zeros(len(regions))
    np.add.at(votes, labels[sampled], boundary[: len(sampled)])
    np.add.at(counts, labels[sampled], 1.0)
    region_kept = (counts == 0) | (votes > counts / 2)  # zero-area regions are kept as they are
    kept_whole = whole[region_kept[labels]]
    kept_cells = np.flatnonzero(boundary[len(sampled):])
    if not len(crossings) and len(kept_whole) == len(whole):
        return None
    if not len(kept_whole) and not len(kept_cells):
        return None
    new_vertices = [vertices]
    new_faces = [faces[kept_whole]]
    source = [kept_whole]
    base = len(vertices)
    for c in kept_cells:
        polygon = cells[c]
        k = len(polygon)
        fan = base + np.stack([np.zeros(k - 2, np.int64), np.arange(1, k - 1), np.arange(2, k)], axis=1)
        new_vertices.append(polygon)
        new_faces.append(fan)
        source.append(np.full(k - 2, cell_face[c]))
        base += k
    dropped = len(whole) - len(kept_whole) + int(cut.sum()) - len(np.unique(cell_face[kept_cells]))
    return UnionSurface(np.concatenate(new_vertices), np.concatenate(new_faces).astype(np.int64),
                        np.concatenate(source).astype(np.int64), len(crossings), int(cut.sum()), dropped)


def _cells(tri, unit, crossings: SelfIntersections, cut_faces: np.ndarray, scale: float):
    """The convex cells of each face of ``cut_faces``: its triangle cut by the lines of its
    intersection segments (a coplanar partner: by that partner's edge lines). Returns the cells
    (list of (k, 3) float64 polygons, wound as their face), each one's face (c,) int64 and the
    step (c,) float64 off its plane at which its sides are tested: a tenth of its inradius times
    the sine of the flattest angle at which another face crosses its face (so the step stays on
    the cell's side of every crossing sheet)."""
    tol = RELATIVE_TOLERANCE * max(scale, 1e-300)
    pairs, segments, coplanar = crossings.pairs, crossings.segments, crossings.coplanar
    owner = np.concatenate([pairs[:, 0], pairs[:, 1]])
    other = np.concatenate([pairs[:, 1], pairs[:, 0]])
    segs = np.concatenate([segments, segments])
    flat = np.concatenate([coplanar, coplanar])
    order = np.argsort(owner, kind="stable")
    owner, other, segs, flat = owner[order], other[order], segs[order], flat[order]
    starts = np.searchsorted(owner, cut_faces)
    ends = np.searchsorted(owner, cut_faces, side="right")
    cells, cell_face, cell_step = [], [], []
    for f, s, e in zip(cut_faces, starts, ends):
        corners = tri[f]
        origin = corners[0]
        x_axis = corners[1] - origin
        x_axis /= np.linalg.norm(x_axis)
        y_axis = np.cross(unit[f], x_axis)
        frame = np.stack([x_axis, y_axis], axis=1)  # (3, 2): plane coordinates are (p - origin) @ frame
        lines = []
        sines = [1.0]
        for g, seg, is_flat in zip(other[s:e], segs[s:e], flat[s:e]):
            if is_flat:
                ends2 = [(tri[g][k], tri[g][(k + 1) % 3]) for k in range(3)]
            else:
                ends2 = [(seg[0], seg[1])]
                sines.append(float(np.linalg.norm(np.cross(unit[f], unit[g]))))
            for p, q in ends2:
                p2, q2 = (p - origin) @ frame, (q - origin) @ frame
                along = q2 - p2
                length = float(np.hypot(*along))
                if length <= tol:
                    continue
                normal = np.array([-along[1], along[0]]) / length
                if normal[0] < 0 or (normal[0] == 0 and normal[1] < 0):
                    normal = -normal
                offset = float(normal @ p2)
                if not any(abs(offset - c) <= tol and np.abs(normal - n).max() <= 1e-9 for n, c in lines):
                    lines.append((normal, offset))
        polygons = [(corners - origin) @ frame]
        for normal, offset in lines:
            polygons = [piece for poly in polygons for piece in _split(poly, normal, offset, tol)]
        sine = min(sines)
        for poly in polygons:
            edge = np.roll(poly, -1, axis=0) - poly
            area = 0.5 * float(np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1]))
            perimeter = float(np.hypot(edge[:, 0], edge[:, 1]).sum())
            if area <= tol * perimeter:
                continue  # a sliver along a cut: nothing a distance query would miss
            cells.append(origin + poly[:, :1] * x_axis + poly[:, 1:] * y_axis)
            cell_face.append(f)
            cell_step.append(0.1 * (2.0 * area / perimeter) * sine)
    return cells, np.asarray(cell_face, dtype=np.int64), np.asarray(cell_step, dtype=np.float64)


def _split(poly: np.ndarray, normal: np.ndarray, offset: float, tol: float) -> list[np.ndarray]:
    """A convex polygon (k, 2) (counter-clockwise) cut by the line ``normal . x = offset``: its
    pieces on either side (one when the line misses it), each counter-clockwise."""
    side = poly @ normal - offset
    side = np.where(np.abs(side) <= tol, 0.0, side)
    if (side >= 0).all() or (side <= 0).all():
        return [poly]
    below, above = [], []
    k = len(poly)
    for i in range(k):
        p, sp = poly[i], side[i]
        q, sq = poly[(i + 1) % k], side[(i + 1) % k]
        if sp <= 0:
            below.append(p)
        if sp >= 0:
            above.append(p)
        if sp * sq < 0:
            x = p + (q - p) * (sp / (sp - sq))
            below.append(x)
            above.append(x)
    return [np.asarray(piece) for piece in (below, above) if len(piece) >= 3]
