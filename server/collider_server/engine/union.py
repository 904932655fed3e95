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

from .intersections import RELATIVE_TOLERANCE, SelfIntersections, diagonal, face_boxes, self_intersections

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
    whole : the first ``whole`` triangles are the mesh's faces kept whole (``source`` names them)
    """

    vertices: np.ndarray
    faces: np.ndarray
    source: np.ndarray
    crossing_pairs: int
    cut_faces: int
    dropped_faces: int
    whole: int


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
    scale = diagonal(*face_boxes(tri))
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
    corners, sizes, cell_face, cell_step = _cells(tri, unit, crossings, np.flatnonzero(cut), scale)
    first_corner = np.cumsum(sizes) - sizes
    cell_centre = (np.add.reduceat(corners, first_corner, axis=0) / sizes[:, None] if len(sizes)
                   else np.zeros((0, 3)))
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
    # Fans over the kept cells' corners, appended after the mesh's vertices.
    fans = sizes[kept_cells] - 2
    start = len(vertices) + np.repeat(first_corner[kept_cells], fans)
    corner = 1 + np.arange(fans.sum()) - np.repeat(np.cumsum(fans) - fans, fans)
    triangles = np.stack([start, start + corner, start + corner + 1], axis=1)
    dropped = len(whole) - len(kept_whole) + int(cut.sum()) - len(np.unique(cell_face[kept_cells]))
    return UnionSurface(np.concatenate([vertices, corners]), np.concatenate([faces[kept_whole], triangles]),
                        np.concatenate([kept_whole, np.repeat(cell_face[kept_cells], fans)]), len(crossings),
                        int(cut.sum()), dropped, len(kept_whole))


def faces_kept_whole(vertices: np.ndarray, faces: np.ndarray, winding, edges: np.ndarray) -> np.ndarray:
    """(f,) bool: the faces that lie wholly on the surface the exact SDF measures to (the
    boundary of ``{winding > 1/2}``, :func:`union_surface`): every face where that is the mesh
    itself, else the faces it keeps whole (not those that cross another, nor those buried)."""
    union = union_surface(vertices, faces, winding, edges)
    if union is None:
        return np.ones(len(faces), bool)
    kept = np.zeros(len(faces), bool)
    kept[union.source[:union.whole]] = True
    return kept


def _cells(tri, unit, crossings: SelfIntersections, cut_faces: np.ndarray, scale: float):
    """The convex cells of each face of ``cut_faces``: its triangle cut by the lines of its
    intersection segments (a coplanar partner: by that partner's edge lines). Returns the cells'
    corners (n, 3) float64, cell after cell, each cell's corner count (c,) int64 (a convex
    polygon wound as its face), its face (c,) int64 and the step (c,) float64 off its plane at
    which its sides are tested: a tenth of its inradius times the sine of the flattest angle at which another face crosses its face (so the step stays on
    the cell's side of every crossing sheet)."""
    tol = RELATIVE_TOLERANCE * max(scale, 1e-300)
    pairs, segments, coplanar = crossings.pairs, crossings.segments, crossings.coplanar
    owner = np.concatenate([pairs[:, 0], pairs[:, 1]])
    other = np.concatenate([pairs[:, 1], pairs[:, 0]])
    segs = np.concatenate([segments, segments])
    flat = np.concatenate([coplanar, coplanar])
    # Each face's flattest crossing (coplanar partners do not count: the step leaves both alike).
    sine = np.ones(len(tri))
    crossing = ~flat
    np.minimum.at(sine, owner[crossing], np.linalg.norm(np.cross(unit[owner[crossing]], unit[other[crossing]]), axis=1))
    # Every cut line as (face, p, q): a segment, or a coplanar partner's three edges.
    line_face = np.concatenate([owner[crossing]] + [owner[flat]] * 3)
    p = np.concatenate([segs[crossing, 0]] + [tri[other[flat], k] for k in range(3)])
    q = np.concatenate([segs[crossing, 1]] + [tri[other[flat], (k + 1) % 3] for k in range(3)])
    # Plane coordinates of each face: origin its first corner, x along its first edge.
    origin = tri[:, 0]
    x_axis = tri[:, 1] - tri[:, 0]
    x_axis /= np.maximum(np.linalg.norm(x_axis, axis=1, keepdims=True), 1e-300)
    y_axis = np.cross(unit, x_axis)

    def plane(points, faces):
        offset = points - origin[faces]
        return np.stack([(offset * x_axis[faces]).sum(1), (offset * y_axis[faces]).sum(1)], axis=1)

    p2, q2 = plane(p, line_face), plane(q, line_face)
    along = q2 - p2
    length = np.hypot(along[:, 0], along[:, 1])
    ok = length > tol
    normal = np.stack([-along[:, 1], along[:, 0]], axis=1) / np.where(ok, length, 1.0)[:, None]
    normal *= np.where((normal[:, 0] < 0) | ((normal[:, 0] == 0) & (normal[:, 1] < 0)), -1.0, 1.0)[:, None]
    offset = (normal * p2).sum(1)
    order = np.flatnonzero(ok)[np.argsort(line_face[ok], kind="stable")]
    line_face, normal, offset = line_face[order], normal[order].tolist(), offset[order].tolist()
    starts = np.searchsorted(line_face, cut_faces)
    ends = np.searchsorted(line_face, cut_faces, side="right")
    corners2 = [plane(tri[:, k][cut_faces], cut_faces) for k in range(3)]
    cells, cell_face, cell_step = [], [], []
    for i, (f, s, e) in enumerate(zip(cut_faces.tolist(), starts.tolist(), ends.tolist())):
        lines: list[tuple[float, float, float]] = []
        for (nx, ny), c in zip(normal[s:e], offset[s:e]):
            if not any(abs(c - c2) <= tol and abs(nx - mx) <= 1e-9 and abs(ny - my) <= 1e-9
                       for mx, my, c2 in lines):
                lines.append((nx, ny, c))
        polygons = [[tuple(corners2[k][i]) for k in range(3)]]
        for nx, ny, c in lines:
            polygons = [piece for poly in polygons for piece in _split(poly, nx, ny, c, tol)]
        for poly in polygons:
            area, perimeter = _area_perimeter(poly)
            if area <= tol * perimeter:
                continue  # a sliver along a cut: nothing a distance query would miss
            cells.append(poly)
            cell_face.append(f)
            cell_step.append(0.1 * (2.0 * area / perimeter) * sine[f])
    cell_face = np.asarray(cell_face, dtype=np.int64)
    sizes = np.array([len(c) for c in cells], dtype=np.int64)
    flat2 = np.array([xy for c in cells for xy in c], dtype=np.float64).reshape(-1, 2)
    face = np.repeat(cell_face, sizes)
    points = origin[face] + flat2[:, :1] * x_axis[face] + flat2[:, 1:] * y_axis[face]
    return points.reshape(-1, 3), sizes, cell_face, np.asarray(cell_step, dtype=np.float64)


def _area_perimeter(poly: list[tuple[float, float]]) -> tuple[float, float]:
    """Area and perimeter of a counter-clockwise polygon (plane coordinates)."""
    area = perimeter = 0.0
    for (x0, y0), (x1, y1) in zip(poly, poly[1:] + poly[:1]):
        area += x0 * y1 - x1 * y0
        perimeter += ((x1 - x0) ** 2 + (y1 - y0) ** 2) ** 0.5
    return 0.5 * area, perimeter


def _split(poly: list[tuple[float, float]], nx: float, ny: float, offset: float,
           tol: float) -> list[list[tuple[float, float]]]:
    """A convex polygon (counter-clockwise, plane coordinates) cut by the line ``(nx, ny) . x =
    offset``: its pieces on either side (one when the line misses it), each counter-clockwise."""
    side = [nx * x + ny * y - offset for x, y in poly]
    side = [0.0 if abs(d) <= tol else d for d in side]
    if all(d >= 0 for d in side) or all(d <= 0 for d in side):
        return [poly]
    below, above = [], []
    k = len(poly)
    for i in range(k):
        (px, py), sp = poly[i], side[i]
        (qx, qy), sq = poly[(i + 1) % k], side[(i + 1) % k]
        if sp <= 0:
            below.append((px, py))
        if sp >= 0:
            above.append((px, py))
        if sp * sq < 0:
            u = sp / (sp - sq)
            x = (px + (qx - px) * u, py + (qy - py) * u)
            below.append(x)
            above.append(x)
    return [piece for piece in (below, above) if len(piece) >= 3]
