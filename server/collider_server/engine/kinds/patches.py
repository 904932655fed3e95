"""Exact patches: a mesh's posed triangles near a point of its rest pose, and the exact distance,
normal and closest point to them: the answer near the surface of the articulated network (kind
``neural-skinned``: the skin at a pose) and of a deformed network that keeps its frames (the
frames at a time); units and frames: the collider's.

The articulated network carries a posed point x to a rest point y of each candidate part and
answers ``f(y)`` there; its error is the rest field's plus the map's (the walker, 1.73 m: 0.08-0.11
mm mean in the +-1 mm band). Near the skin it also says *where* x's closest point lies:
``c = y - f(y) grad f / |grad f|``, a point of the rest surface. The rest mesh's triangles within
``reach`` of c, posed as the exact kind poses them (the flat triangles between the skinned
vertices), hold x's closest posed point wherever the network's c lies within ``reach`` of that
point's rest position. Their distance is then the exact kind's distance to the skin, their normal
the direction from the closest point (the pseudo-normal of its face, edge or vertex on the surface;
the sign is the pseudo-normal's, Baerentzen and Aanaes 2005), and the closest point's velocity
the blend of its face's vertex velocities. Elsewhere the patch is a real piece of the posed skin:
its distance is never less than the distance to the whole skin.

:func:`patch_cells` lists, once per model, each cell of a sparse grid near the rest surface with
the faces a rest point in it may need (every face within ``reach`` of any point of the cell);
:func:`posed_surface` prepares a pose (vertices, pseudo-normals, vertex velocities);
:func:`answer_on_patches` answers the network's rows, in one numba pass (a numpy reference beside
it, tested equal).

A large query (:func:`near_points` or more points) needs no network to find the faces: the pose's
cells (:func:`pose_cells`, the same build over the posed mesh) list every face within the band of
each of their points, and where none of them crosses another or lies buried (the exact kind's own
rule, :func:`~collider_server.engine.union.faces_kept_whole`) a point within the band is answered
by its nearest listed face (:func:`answer_near_skin`), the exact kind's answer; the other points
go through the network (:func:`answer_near_first`). Building them costs a pose 30-45 ms (the
walker's), which a small query cannot repay.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..meshes import edge_index, pseudo_normals

#: A network's exact patches, in its finest cells (the walker's: 8.1 mm): rows the network answers
#: within ``PATCH_BAND`` of the surface are answered by the posed faces within ``PATCH_REACH`` of
#: their rest closest point, listed in cells of ``PATCH_CELL``.
PATCH_BAND = 2.0
PATCH_REACH = 1.0
PATCH_CELL = 2.0
#: The side of a pose's cells (:func:`near_cells`), in the same finest cells: each lists the faces
#: within ``PATCH_BAND`` of its points (the walker's: 16 mm cells, 18 faces a cell).
NEAR_CELL = 2.0
#: A query of at least this many points is answered near the skin by its pose's cells
#: (:func:`answer_near_skin`, :func:`near_points`); a smaller one cannot repay building them
#: (:func:`pose_cells`), at about 1 us saved a point.
NEAR_POINTS = 65_536
#: A cell is kept where the rest surface passes within this fraction of a cell of it: the
#: network's closest points lie on the rest surface to its error (a tenth of a millimetre), far
#: inside this margin.
SURFACE_MARGIN = 0.25
#: Faces per piece of :func:`patch_cells`' numpy build (its cell pairs in bounded memory).
BUILD_FACES = 4096
#: Grids of at most this many cells are grouped by a counting sort over all of them (16 bytes a
#: cell while it runs); larger ones by a sort of the listed pairs.
DENSE_CELLS = 1 << 25


class PatchCells(NamedTuple):
    """The faces each cell near the rest surface lists (:func:`patch_cells`): the grid's
    ``origin`` (3,) and ``cell`` side (collider units), ``dims`` (3,) int64 cells per axis,
    ``keys`` (k,) int64 the listed cells' linear indices (sorted), ``start`` (k + 1,) int64 where
    each cell's faces begin in ``faces`` (m,) int32, and ``reach``: every face within it of any
    point of a cell is listed there."""

    origin: np.ndarray
    cell: float
    dims: np.ndarray
    keys: np.ndarray
    start: np.ndarray
    faces: np.ndarray
    reach: float


class PosedSurface(NamedTuple):
    """The skin at one pose (:func:`posed_surface`), collider frame: ``vertices`` (V, 3), unit
    ``face_normals`` (F, 3), ``edge_normals`` (F, 3, 3) (per face, the edge opposite each corner),
    ``vertex_normals`` (V, 3), ``velocities`` (V, 3) m/s or None (a still pose), and ``spheres``
    (F, 4): each face's centroid and the radius about it that holds the face (a cheap bound that
    lets the nearest face's search skip the faces farther than the nearest so far)."""

    vertices: np.ndarray
    face_normals: np.ndarray
    edge_normals: np.ndarray
    vertex_normals: np.ndarray
    velocities: np.ndarray | None
    spheres: np.ndarray


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """The closest points on triangles ``(a, b, c)`` to points ``p``, all (m, 3) (Ericson,
    Real-Time Collision Detection 5.1.5). Returns ``(closest (m, 3), barycentric (m, 3),
    feature (m,) int64)``: 0 the face's inside, 1-3 the corner a, b or c, 4-6 the edge opposite
    corner c, a or b (ab, bc, ca)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp, cp = p - b, p - c
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    m = len(p)
    bary = np.zeros((m, 3))
    feature = np.full(m, -1, np.int64)

    def put(mask, weights, code):
        mask = mask & (feature < 0)
        bary[mask] = weights[mask]
        feature[mask] = code

    one, zero = np.ones(m), np.zeros(m)
    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), np.stack([one, zero, zero], 1), 1)
        put((d3 >= 0) & (d4 <= d3), np.stack([zero, one, zero], 1), 2)
        put((d6 >= 0) & (d5 <= d6), np.stack([zero, zero, one], 1), 3)
        v = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - v, v, zero], 1), 4)
        w = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - w, zero, w], 1), 6)
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), np.stack([zero, 1 - w, w], 1), 5)
        # A face of no area has every point in a corner's or an edge's region; should rounding
        # leave one to the inside, its first corner, not a division by zero.
        put(va + vb + vc == 0, np.stack([one, zero, zero], 1), 1)
        denominator = 1.0 / (va + vb + vc)
        v, w = vb * denominator, vc * denominator
        put(np.ones(m, bool), np.stack([1 - v - w, v, w], 1), 0)
    closest = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return closest, bary, feature


def patch_cells(vertices: np.ndarray, faces: np.ndarray, reach: float, cell: float,
                margin: float | None = SURFACE_MARGIN, fused: bool = True) -> PatchCells:
    """:class:`PatchCells` of the mesh ``vertices`` (V, 3) and ``faces`` (F, 3): cells of side
    ``cell``, each listing the faces within ``reach`` of any of its points (collider units); kept
    where the surface passes within ``margin`` cells of the cell (:data:`SURFACE_MARGIN`: a rest
    mesh's cells, which the network's closest points fall in), or every cell that lists a face
    (``margin`` None: a posed mesh's cells, which any point within ``reach`` of the surface falls
    in). A face's box grown by ``reach`` names its cells; a cell lists the face where it lies
    within ``reach`` plus half the cell's diagonal of the cell's centre (so that no face within
    ``reach`` of a point of the cell is missed), nearest that centre first. In numba
    (:func:`_cell_kernel` counts each face's cells, then lists them; :func:`_grouped` sorts them
    by cell: the walker's rest cells in 16 ms, 0.23 s in numpy) when numba is there and ``fused``,
    else numpy in pieces of :data:`BUILD_FACES` faces (the same cells)."""
    if not (reach > 0 and cell > 0):
        raise ValueError(f"reach and cell must be > 0, got {reach} and {cell}")
    vertices = np.ascontiguousarray(vertices, np.float64)
    faces = np.ascontiguousarray(faces, np.int64)
    origin = vertices.min(0) - reach - cell
    dims = np.floor((vertices.max(0) + reach + cell - origin) / cell).astype(np.int64) + 1
    half_diagonal = 0.5 * np.sqrt(3.0) * cell
    size = int(dims.prod())
    if fused and _cell_kernel is not None:
        counts = np.zeros(len(faces), np.int64)
        none = np.zeros(0, np.int64)
        _cell_kernel(vertices, faces, origin, cell, dims, reach, half_diagonal, counts, none, none, none.astype(
            np.float64), counts)  # the count of each face's cells, then the cells themselves
        total = int(counts.sum())
        key, face, gap = np.empty(total, np.int64), np.empty(total, np.int64), np.empty(total)
        _cell_kernel(vertices, faces, origin, cell, dims, reach, half_diagonal, np.cumsum(counts) - counts, key, face,
                     gap, counts)
    else:
        key, face, gap = _cell_pairs_numpy(vertices, faces, origin, cell, dims, reach, half_diagonal)
    if not len(key):  # no faces (or none of finite size): no cells
        return PatchCells(origin, float(cell), dims, np.zeros(0, np.int64), np.zeros(1, np.int64),
                          np.zeros(0, np.int32), float(reach))
    if fused and _cell_kernel is not None and size <= DENSE_CELLS:
        key, face, gap = _grouped(key, face, gap, size)  # a counting sort by cell (the same order)
    else:
        order = np.lexsort((face, gap, key))  # within a cell, the faces nearest its centre first
        key, face, gap = key[order], face[order], gap[order]
    first = np.r_[True, key[1:] != key[:-1]]
    if margin is not None:
        cell_start = np.flatnonzero(first)
        near = gap[cell_start] <= half_diagonal + margin * cell  # (sorted: a cell's nearest face first)
        keep = np.repeat(near, np.diff(np.r_[cell_start, len(key)]))
        key, face = key[keep], face[keep]
        first = np.r_[True, key[1:] != key[:-1]]
    start = np.r_[np.flatnonzero(first), len(key)].astype(np.int64)
    return PatchCells(origin, float(cell), dims, key[first].astype(np.int64), start, face.astype(np.int32),
                      float(reach))


def _cell_pairs_numpy(vertices, faces, origin, cell, dims, reach, half_diagonal):
    """:func:`patch_cells`' (cell key, face, gap to the cell's centre) pairs in numpy."""
    pieces = []
    for first_face in range(0, len(faces), BUILD_FACES):  # a dense mesh's pairs in bounded memory
        tri = vertices[faces[first_face:first_face + BUILD_FACES]]
        lo = np.floor((tri.min(1) - reach - origin) / cell).astype(np.int64)
        span = np.floor((tri.max(1) + reach - origin) / cell).astype(np.int64) - lo + 1
        count = span.prod(1)
        face = np.repeat(np.arange(len(tri)), count)
        local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        s = span[face]
        ijk = lo[face] + np.stack([local // (s[:, 1] * s[:, 2]), (local // s[:, 2]) % s[:, 1], local % s[:, 2]], 1)
        centre = origin + (ijk + 0.5) * cell
        t = tri[face]
        gap = np.linalg.norm(centre - closest_on_triangles(centre, t[:, 0], t[:, 1], t[:, 2])[0], axis=1)
        listed = gap <= reach + half_diagonal
        key = (ijk[listed, 0] * dims[1] + ijk[listed, 1]) * dims[2] + ijk[listed, 2]
        pieces.append((key, face[listed] + first_face, gap[listed]))
    return tuple(np.concatenate([piece[k] for piece in pieces]) for k in range(3))


def posed_surface(vertices: np.ndarray, faces: np.ndarray, edges: np.ndarray | None = None,
                  velocities: np.ndarray | None = None) -> PosedSurface:
    """:class:`PosedSurface` of the posed ``vertices`` (V, 3) (``faces`` (F, 3); ``edges`` their
    :func:`~collider_server.engine.meshes.edge_index`, computed when not given) and their
    ``velocities`` (V, 3) or None."""
    vertices = np.ascontiguousarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    normals = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    lengths = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.where(lengths > 0, lengths, 1.0)
    edge, vertex = pseudo_normals(vertices, faces, normals, edge_index(faces) if edges is None else edges)
    tri = vertices[faces]
    centre = tri.mean(1)
    radius = np.sqrt(((tri - centre[:, None]) ** 2).sum(2).max(1))
    return PosedSurface(vertices, np.ascontiguousarray(normals), np.ascontiguousarray(edge),
                        np.ascontiguousarray(vertex), None if velocities is None else
                        np.ascontiguousarray(velocities, np.float64),
                        np.ascontiguousarray(np.column_stack([centre, radius])))


def cells_of(points: np.ndarray, cells: PatchCells) -> np.ndarray:
    """(m,) int64: each point's listed cell (an index into ``cells.keys``), -1 where none."""
    if not len(cells.keys):
        return np.full(len(points), -1, np.int64)
    ijk = np.floor((points - cells.origin) / cells.cell).astype(np.int64)
    inside = ((ijk >= 0) & (ijk < cells.dims)).all(1)
    key = (ijk[:, 0] * cells.dims[1] + ijk[:, 1]) * cells.dims[2] + ijk[:, 2]
    slot = np.minimum(np.searchsorted(cells.keys, key), len(cells.keys) - 1)
    return np.where(inside & (cells.keys[slot] == key), slot, -1)


def _nearest_numpy(points, closest, cells, surface, faces, tiny):
    """The numpy rule of the kernel's search: for each of ``points`` (m, 3) the nearest posed face
    among its rest ``closest`` point's cell's, ``(signed distance, normal, face, barycentric)``
    (NaN, 0, -1, 0 where the point lies in no listed cell)."""
    m = len(points)
    distance, normal = np.full(m, np.nan), np.zeros((m, 3))
    face, bary = np.full(m, -1, np.int64), np.zeros((m, 3))
    slot = cells_of(closest, cells)
    rows = np.flatnonzero(slot >= 0)
    if not len(rows):
        return distance, normal, face, bary
    count = cells.start[slot[rows] + 1] - cells.start[slot[rows]]
    row = np.repeat(rows, count)
    entry = np.repeat(cells.start[slot[rows]], count) + np.arange(count.sum()) - np.repeat(np.cumsum(count) - count,
                                                                                          count)
    f = cells.faces[entry].astype(np.int64)
    tri = surface.vertices[faces[f]]
    q, b, feature = closest_on_triangles(points[row], tri[:, 0], tri[:, 1], tri[:, 2])
    d2 = ((points[row] - q) ** 2).sum(1)
    order = np.lexsort((entry, d2, row))  # the first nearest in list order, as the kernel keeps
    best = order[np.r_[True, row[order][1:] != row[order][:-1]]]
    r, f, feature, b = row[best], f[best], feature[best], b[best]
    pseudo = surface.face_normals[f].copy()
    for k in range(3):
        at = feature == 1 + k
        pseudo[at] = surface.vertex_normals[faces[f[at], k]]
    for code, k in ((4, 2), (5, 0), (6, 1)):
        at = feature == code
        pseudo[at] = surface.edge_normals[f[at], k]
    offset = points[r] - q[best]
    length = np.sqrt(d2[best])
    sign = np.where((offset * pseudo).sum(1) < 0, -1.0, 1.0)
    distance[r] = sign * length
    direction = offset / np.where(length > tiny, length, 1.0)[:, None] * sign[:, None]
    normal[r] = np.where((length > tiny)[:, None], direction, pseudo)
    face[r], bary[r] = f, b
    return distance, normal, face, bary


def answer_on_patches(points: np.ndarray, point: np.ndarray, rest: np.ndarray, distance: np.ndarray,
                      gradient: np.ndarray, band: float, cells: PatchCells, surface: PosedSurface,
                      faces: np.ndarray, fused: bool = True):
    """The network's rows answered on their patches: row r of posed point ``points[point[r]]``
    ((n, 3); ``point`` (m,) int64) carried to ``rest[r]`` (m, 3), where the network answers
    ``distance[r]`` (m,) and the rest-frame ``gradient[r]`` (m, 3). A row within ``band`` of the
    skin (|distance| <= band) takes its rest closest point ``rest - distance * gradient /
    |gradient|`` and the nearest posed face among that point's cell's (:func:`patch_cells`) and
    is answered there unless that face lies farther than the network's distance plus the cells'
    reach (then the patch is not the row's: a closest point put on another limb; a face nearer
    than the network says is a real piece of the surface that near, and answers). Returns
    ``(distance (m,), normal (m, 3), velocity (m, 3) or None, face (m,) int64)``, collider frame
    and units: the signed distance to that face (the network's where the row is not answered),
    the unit direction from its closest point (its pseudo-normal on the surface, within 1e-9 of
    the mesh's size), the closest point's velocity (the blend of its face's vertex velocities, the
    exact kind's rule; None for a still ``surface``), and the face (-1: not answered; the normal
    and velocity are then zero). One numba pass (:func:`_answer_kernel`) when numba is there and
    ``fused``, else numpy (the same answers)."""
    points = np.ascontiguousarray(points, np.float64)
    point = np.ascontiguousarray(point, np.int64)
    rest = np.ascontiguousarray(rest, np.float64)
    gradient = np.ascontiguousarray(gradient, np.float64)
    faces = np.ascontiguousarray(faces, np.int64)
    tiny = 1e-9 * max(float(np.ptp(surface.vertices, axis=0).max()), 1e-30)
    m = len(point)
    out = np.array(distance, np.float64)
    normal, face = np.zeros((m, 3)), np.full(m, -1, np.int64)
    moving = surface.velocities is not None
    velocity = np.zeros((m if moving else 0, 3))
    if fused and _answer_kernel is not None:
        _answer_kernel(points, point, rest, out, gradient, float(band), cells.origin, cells.cell, cells.dims,
                       cells.keys, cells.start, cells.faces, cells.reach, surface.vertices, faces, surface.spheres,
                       surface.face_normals, surface.edge_normals, surface.vertex_normals,
                       surface.velocities if moving else np.zeros((0, 3)), tiny, normal, velocity, face)
        return out, normal, velocity if moving else None, face
    rows = np.flatnonzero(np.abs(out) <= band)
    length = np.linalg.norm(gradient[rows], axis=1)
    closest = rest[rows] - (out[rows] / np.where(length > 0, length, 1.0))[:, None] * gradient[rows]
    d, n, f, b = _nearest_numpy(points[point[rows]], closest, cells, surface, faces, tiny)
    take = (f >= 0) & (np.abs(d) <= np.abs(out[rows]) + cells.reach)
    rows, d, n, f, b = rows[take], d[take], n[take], f[take], b[take]
    out[rows], normal[rows], face[rows] = d, n, f
    if moving:
        velocity[rows] = np.einsum("mj,mjc->mc", b, surface.velocities[faces[f]])
    return out, normal, velocity if moving else None, face


class NearCells(NamedTuple):
    """A posed skin's cells (:func:`near_cells`): ``cells``, the :class:`PatchCells` of the posed
    mesh (each lists every face within ``cells.reach``, the band, of any of its points), and
    ``clean`` (k,) bool, the cells whose every listed face lies wholly on the surface the exact
    kind measures to (:func:`~collider_server.engine.union.faces_kept_whole`: no face there
    crosses another or lies buried in the body)."""

    cells: PatchCells
    clean: np.ndarray


def near_cells(surface: PosedSurface, faces: np.ndarray, band: float, cell: float,
               kept_whole: np.ndarray | None = None) -> NearCells:
    """:class:`NearCells` of a posed ``surface`` (``faces`` (F, 3)): cells of side ``cell`` listing
    the faces within ``band`` of any of their points; ``kept_whole`` (F,) bool the faces wholly on
    the exact kind's surface (None: every face). Collider units."""
    cells = patch_cells(surface.vertices, faces, band, cell, margin=None)
    if kept_whole is None or not len(cells.faces):
        return NearCells(cells, np.ones(len(cells.keys), bool))
    return NearCells(cells, np.logical_and.reduceat(kept_whole[cells.faces], cells.start[:-1]))


def pose_cells(surface: PosedSurface, faces: np.ndarray, edges: np.ndarray, band: float, cell: float) -> NearCells:
    """:func:`near_cells` of a posed ``surface`` (``faces`` (F, 3), ``edges`` their
    :func:`~collider_server.engine.meshes.edge_index`), clean where the exact kind's own rule keeps
    every listed face whole (:func:`~collider_server.engine.union.faces_kept_whole` by the posed
    mesh's winding number: a skin may pass through itself) and each of them meets two faces at
    every edge (at a hole's rim the exact kind's sign, the winding number's, is not the
    pseudo-normal's). The walker's 7,920 faces: 30-45 ms, most of it the self-intersection test and
    the cells."""
    from ..meshes import ExactSDF, Mesh
    from ..union import faces_kept_whole

    exact = ExactSDF(Mesh(surface.vertices, faces, "posed"), edges)
    kept = faces_kept_whole(surface.vertices, exact.mesh.faces, exact.winding_number, edges)
    closed = (np.bincount(edges.ravel())[edges] == 2).all(axis=1) if len(edges) else np.zeros(0, bool)
    return near_cells(surface, faces, band, cell, kept & closed)


def near_points(chunk_points: int) -> int:
    """The fewest points of a query a kind answering in chunks of ``chunk_points`` answers by the
    pose's cells: :data:`NEAR_POINTS`, or half a chunk where that is less. A collider sees a query
    a chunk at a time, and a query's chunks are cut alike in size (``Collider.query_local``), so a
    query of this many points or more has every chunk as large: the whole query takes one path."""
    return min(NEAR_POINTS, chunk_points // 2)


def answer_near_first(points: np.ndarray, near: NearCells, surface: PosedSurface, faces: np.ndarray,
                      want_gradient: bool, through_network):
    """A large query's answers (:func:`near_points` or more ``points`` (n, 3)): those the pose's
    cells answer (:func:`answer_near_skin`), the others by ``through_network(points (m, 3),
    want_gradient) -> (distance, gradient or None, velocity or None)``. Returns the collider's
    ``(distance (n,), normal (n, 3) or None, velocity (n, 3) or None)`` (a normal where
    ``want_gradient``, a velocity where also the surface moves), collider frame and units."""
    distance, normal, velocity, face = answer_near_skin(points, near, surface, faces)
    left = np.flatnonzero(face < 0)  # in no clean cell, or beyond the band
    if len(left):
        d, g, v = through_network(points[left], want_gradient)
        distance[left] = d
        if want_gradient:
            normal[left] = g
        if velocity is not None and v is not None:
            velocity[left] = v
    if not want_gradient:
        return distance, None, None
    return distance, normal, velocity


def answer_near_skin(points: np.ndarray, near: NearCells, surface: PosedSurface, faces: np.ndarray,
                     fused: bool = True):
    """Points ``points`` (n, 3) answered by the posed skin itself where they lie in a clean cell of
    ``near`` and within its band of the skin: the nearest face of the cell's (every face that near
    is listed there, so it is the skin's nearest), whose distance signed by its pseudo-normal, unit
    direction and closest point's velocity are the exact kind's answer (no face there crosses
    another or lies buried, so the surface about the closest point is the body's boundary).
    Returns ``(distance (n,), normal (n, 3), velocity (n, 3) or None, face (n,) int64)``, collider
    frame and units, as :func:`answer_on_patches`' (face -1: not answered; distance NaN, normal and
    velocity zero there). One numba pass (:func:`_near_kernel`) when numba is there and ``fused``,
    else numpy (the same answers)."""
    points = np.ascontiguousarray(points, np.float64)
    faces = np.ascontiguousarray(faces, np.int64)
    cells = near.cells
    tiny = 1e-9 * max(float(np.ptp(surface.vertices, axis=0).max()), 1e-30)
    n = len(points)
    moving = surface.velocities is not None
    velocity = np.zeros((n if moving else 0, 3))
    if fused and _near_kernel is not None:
        distance, normal, face = np.full(n, np.nan), np.zeros((n, 3)), np.full(n, -1, np.int64)
        _near_kernel(points, cells.reach, cells.origin, cells.cell, cells.dims, cells.keys, cells.start, cells.faces,
                     near.clean, surface.vertices, faces, surface.spheres, surface.face_normals, surface.edge_normals,
                     surface.vertex_normals, surface.velocities if moving else np.zeros((0, 3)), tiny, distance,
                     normal, velocity, face)
        return distance, normal, velocity if moving else None, face
    distance, normal, face, bary = _nearest_numpy(points, points, cells, surface, faces, tiny)
    slot = cells_of(points, cells)
    clean = near.clean[np.maximum(slot, 0)] if len(near.clean) else np.zeros(n, bool)
    left = (face < 0) | ~(np.abs(distance) <= cells.reach) | ~clean
    distance[left], normal[left], face[left] = np.nan, 0.0, -1
    if moving:
        answered = ~left
        velocity[answered] = np.einsum("mj,mjc->mc", bary[answered], surface.velocities[faces[face[answered]]])
    return distance, normal, velocity if moving else None, face


try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; numpy answers without it
    _answer_kernel = _near_kernel = _cell_kernel = _grouped = None
else:
    @numba.njit(cache=True, nogil=True, inline="always")
    def _closest_one(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):  # pragma: no cover
        """:func:`closest_on_triangles` of one point: ``(u, v, w, feature)``."""
        abx, aby, abz = bx - ax, by - ay, bz - az
        acx, acy, acz = cx - ax, cy - ay, cz - az
        d1 = abx * (px - ax) + aby * (py - ay) + abz * (pz - az)
        d2 = acx * (px - ax) + acy * (py - ay) + acz * (pz - az)
        if d1 <= 0.0 and d2 <= 0.0:
            return 1.0, 0.0, 0.0, 1
        d3 = abx * (px - bx) + aby * (py - by) + abz * (pz - bz)
        d4 = acx * (px - bx) + acy * (py - by) + acz * (pz - bz)
        if d3 >= 0.0 and d4 <= d3:
            return 0.0, 1.0, 0.0, 2
        d5 = abx * (px - cx) + aby * (py - cy) + abz * (pz - cz)
        d6 = acx * (px - cx) + acy * (py - cy) + acz * (pz - cz)
        if d6 >= 0.0 and d5 <= d6:
            return 0.0, 0.0, 1.0, 3
        vc = d1 * d4 - d3 * d2
        if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v = d1 / (d1 - d3)
            return 1.0 - v, v, 0.0, 4
        vb = d5 * d2 - d1 * d6
        if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            w = d2 / (d2 - d6)
            return 1.0 - w, 0.0, w, 6
        va = d3 * d6 - d5 * d4
        if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            return 0.0, 1.0 - w, w, 5
        if va + vb + vc == 0.0:  # no area, left by rounding: its first corner (as closest_on_triangles)
            return 1.0, 0.0, 0.0, 1
        denominator = 1.0 / (va + vb + vc)
        v, w = vb * denominator, vc * denominator
        return 1.0 - v - w, v, w, 0

    @numba.njit(cache=True, nogil=True, inline="always")
    def _nearest_listed(px, py, pz, first, last, cell_faces, spheres, vertices, faces, limit):  # pragma: no cover
        """The nearest of the listed faces ``cell_faces[first:last]`` to a point within ``limit``
        (inf: any): ``(squared distance, face (-1: none), feature, u, v, w, closest x, y, z)``,
        the first nearest in list order; a face whose bounding sphere lies farther than the nearest
        so far is skipped."""
        best, best_face, best_feature = limit * limit, -1, -1
        best_length = limit
        bu = bv = bw = qx = qy = qz = 0.0
        for e in range(first, last):
            f = cell_faces[e]
            reach_f = spheres[f, 3] + best_length
            if (px - spheres[f, 0]) ** 2 + (py - spheres[f, 1]) ** 2 + (pz - spheres[f, 2]) ** 2 > reach_f * reach_f:
                continue  # the face's every point is farther than the nearest so far
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
            bx, by, bz = vertices[b, 0], vertices[b, 1], vertices[b, 2]
            cx, cy, cz = vertices[c, 0], vertices[c, 1], vertices[c, 2]
            u, v, w, feature = _closest_one(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
            x = u * ax + v * bx + w * cx
            y = u * ay + v * by + w * cy
            z = u * az + v * bz + w * cz
            d2 = (px - x) ** 2 + (py - y) ** 2 + (pz - z) ** 2
            if d2 < best or (best_face < 0 and d2 <= best):
                best, best_face, best_feature = d2, f, feature
                bu, bv, bw, qx, qy, qz = u, v, w, x, y, z
                best_length = np.sqrt(d2)
        return best, best_face, best_feature, bu, bv, bw, qx, qy, qz

    @numba.njit(cache=True, nogil=True, inline="always")
    def _put_answer(r, px, py, pz, best, f, feature, u, v, w, qx, qy, qz, faces, face_normals, edge_normals,
                    vertex_normals, velocities, tiny, distance, normal, velocity, face):  # pragma: no cover
        """Row ``r``'s answer on face ``f`` (its closest point ``q`` at squared distance ``best``,
        on ``feature`` with barycentric ``u, v, w``): the distance signed by the pseudo-normal of
        the face, edge or vertex ``q`` lies on, the unit direction from ``q`` (that pseudo-normal on
        the surface), and ``q``'s velocity."""
        if feature == 0:
            nx, ny, nz = face_normals[f, 0], face_normals[f, 1], face_normals[f, 2]
        elif feature <= 3:
            corner = faces[f, feature - 1]
            nx, ny, nz = vertex_normals[corner, 0], vertex_normals[corner, 1], vertex_normals[corner, 2]
        else:
            opposite = (2, 0, 1)[feature - 4]
            nx, ny, nz = edge_normals[f, opposite, 0], edge_normals[f, opposite, 1], edge_normals[f, opposite, 2]
        ox, oy, oz = px - qx, py - qy, pz - qz
        length = np.sqrt(best)
        sign = -1.0 if ox * nx + oy * ny + oz * nz < 0.0 else 1.0
        distance[r] = sign * length
        if length > tiny:
            normal[r, 0], normal[r, 1], normal[r, 2] = sign * ox / length, sign * oy / length, sign * oz / length
        else:
            normal[r, 0], normal[r, 1], normal[r, 2] = nx, ny, nz
        face[r] = f
        if len(velocities):
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            for axis in range(3):
                velocity[r, axis] = u * velocities[a, axis] + v * velocities[b, axis] + w * velocities[c, axis]

    @numba.njit(cache=True, nogil=True, inline="always")
    def _cell_at(x, y, z, origin, cell, dims, keys):  # pragma: no cover
        """The listed cell (an index into ``keys``) holding a point, -1 where none."""
        i = int(np.floor((x - origin[0]) / cell))
        j = int(np.floor((y - origin[1]) / cell))
        k = int(np.floor((z - origin[2]) / cell))
        if i < 0 or j < 0 or k < 0 or i >= dims[0] or j >= dims[1] or k >= dims[2]:
            return -1
        key = (i * dims[1] + j) * dims[2] + k
        s = np.searchsorted(keys, key)
        if s >= len(keys) or keys[s] != key:
            return -1
        return s

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _answer_kernel(points, point, rest, distance, gradient, band, origin, cell, dims, keys, start, cell_faces,
                       reach, vertices, faces, spheres, face_normals, edge_normals, vertex_normals, velocities,
                       tiny, normal, velocity, face):  # pragma: no cover
        """:func:`answer_on_patches` in one pass over the rows (numba, parallel)."""
        for r in numba.prange(len(point)):
            d = distance[r]
            if not abs(d) <= band:
                continue
            gx, gy, gz = gradient[r, 0], gradient[r, 1], gradient[r, 2]
            g = np.sqrt(gx * gx + gy * gy + gz * gz)
            scale = d / g if g > 0.0 else 0.0
            s = _cell_at(rest[r, 0] - scale * gx, rest[r, 1] - scale * gy, rest[r, 2] - scale * gz, origin, cell, dims,
                         keys)
            if s < 0:
                continue
            p = point[r]
            px, py, pz = points[p, 0], points[p, 1], points[p, 2]
            best, f, feature, u, v, w, qx, qy, qz = _nearest_listed(px, py, pz, start[s], start[s + 1], cell_faces,
                                                                    spheres, vertices, faces, np.inf)
            if f < 0 or np.sqrt(best) > abs(d) + reach:
                continue  # no face, or the patch is not the row's
            _put_answer(r, px, py, pz, best, f, feature, u, v, w, qx, qy, qz, faces, face_normals, edge_normals,
                        vertex_normals, velocities, tiny, distance, normal, velocity, face)

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _near_kernel(points, band, origin, cell, dims, keys, start, cell_faces, clean, vertices, faces, spheres,
                     face_normals, edge_normals, vertex_normals, velocities, tiny, distance, normal, velocity,
                     face):  # pragma: no cover
        """:func:`answer_near_skin` in one pass over the points (numba, parallel)."""
        for p in numba.prange(len(points)):
            px, py, pz = points[p, 0], points[p, 1], points[p, 2]
            s = _cell_at(px, py, pz, origin, cell, dims, keys)
            if s < 0 or not clean[s]:
                continue
            best, f, feature, u, v, w, qx, qy, qz = _nearest_listed(px, py, pz, start[s], start[s + 1], cell_faces,
                                                                    spheres, vertices, faces, band * (1.0 + 1e-9))
            if f >= 0 and np.sqrt(best) <= band:  # (the numpy rule's test: the same number)
                _put_answer(p, px, py, pz, best, f, feature, u, v, w, qx, qy, qz, faces, face_normals, edge_normals,
                            vertex_normals, velocities, tiny, distance, normal, velocity, face)

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _cell_kernel(vertices, faces, origin, cell, dims, reach, half_diagonal, offsets, key, face, gap,
                     counts):  # pragma: no cover
        """:func:`patch_cells`' pairs: per face the cells its box grown by ``reach`` names whose
        centre lies within ``reach`` plus ``half_diagonal`` of it, counted into ``counts`` (and
        written from ``offsets`` into ``key``, ``face``, ``gap`` when they have room)."""
        limit = reach + half_diagonal
        loose = limit * (1.0 + 1e-9)  # the cheap tests only skip what is surely beyond the limit
        for f in numba.prange(len(faces)):
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
            bx, by, bz = vertices[b, 0], vertices[b, 1], vertices[b, 2]
            cx, cy, cz = vertices[c, 0], vertices[c, 1], vertices[c, 2]
            nx = (by - ay) * (cz - az) - (bz - az) * (cy - ay)
            ny = (bz - az) * (cx - ax) - (bx - ax) * (cz - az)
            nz = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            length = np.sqrt(nx * nx + ny * ny + nz * nz)
            mx, my, mz = (ax + bx + cx) / 3.0, (ay + by + cy) / 3.0, (az + bz + cz) / 3.0
            radius = np.sqrt(max((ax - mx) ** 2 + (ay - my) ** 2 + (az - mz) ** 2,
                                 (bx - mx) ** 2 + (by - my) ** 2 + (bz - mz) ** 2,
                                 (cx - mx) ** 2 + (cy - my) ** 2 + (cz - mz) ** 2))
            i0 = int(np.floor((min(ax, bx, cx) - reach - origin[0]) / cell))
            i1 = int(np.floor((max(ax, bx, cx) + reach - origin[0]) / cell))
            j0 = int(np.floor((min(ay, by, cy) - reach - origin[1]) / cell))
            j1 = int(np.floor((max(ay, by, cy) + reach - origin[1]) / cell))
            k0 = int(np.floor((min(az, bz, cz) - reach - origin[2]) / cell))
            k1 = int(np.floor((max(az, bz, cz) + reach - origin[2]) / cell))
            n = 0
            for i in range(i0, i1 + 1):
                x = origin[0] + (i + 0.5) * cell
                for j in range(j0, j1 + 1):
                    y = origin[1] + (j + 0.5) * cell
                    for k in range(k0, k1 + 1):
                        z = origin[2] + (k + 0.5) * cell
                        if length > 0.0 and abs((x - ax) * nx + (y - ay) * ny + (z - az) * nz) > loose * length:
                            continue  # farther than the limit from the face's plane
                        if np.sqrt((x - mx) ** 2 + (y - my) ** 2 + (z - mz) ** 2) - radius > loose:
                            continue  # and from its bounding sphere
                        u, v, w, _ = _closest_one(x, y, z, ax, ay, az, bx, by, bz, cx, cy, cz)
                        qx, qy, qz = u * ax + v * bx + w * cx, u * ay + v * by + w * cy, u * az + v * bz + w * cz
                        d = np.sqrt((x - qx) ** 2 + (y - qy) ** 2 + (z - qz) ** 2)  # (numpy's arithmetic)
                        if d <= limit:
                            if len(key):
                                key[offsets[f] + n] = (i * dims[1] + j) * dims[2] + k
                                face[offsets[f] + n] = f
                                gap[offsets[f] + n] = d
                            n += 1
            counts[f] = n

    @numba.njit(cache=True, nogil=True)
    def _grouped(key, face, gap, size):  # pragma: no cover
        """The pairs ``(key, face, gap)`` ordered by key, then gap, then face (as ``np.lexsort``):
        a counting sort over ``size`` cells, then each cell's few faces by insertion."""
        start = np.zeros(size + 1, np.int64)
        for e in range(len(key)):
            start[key[e] + 1] += 1
        for c in range(size):
            start[c + 1] += start[c]
        at = start[:-1].copy()
        out_key, out_face, out_gap = np.empty_like(key), np.empty_like(face), np.empty_like(gap)
        for e in range(len(key)):
            slot = at[key[e]]
            out_key[slot], out_face[slot], out_gap[slot] = key[e], face[e], gap[e]
            at[key[e]] = slot + 1
        for c in range(size):
            for e in range(start[c] + 1, start[c + 1]):
                g, f = out_gap[e], out_face[e]
                m = e - 1
                while m >= start[c] and (out_gap[m] > g or (out_gap[m] == g and out_face[m] > f)):
                    out_gap[m + 1], out_face[m + 1] = out_gap[m], out_face[m]
                    m -= 1
                out_gap[m + 1], out_face[m + 1] = g, f
        return out_key, out_face, out_gap
