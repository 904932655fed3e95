"""The exact SDF of a mesh that passes through itself answers against the boundary of the region
whose winding number exceeds 1/2 (:mod:`collider_server.engine.union`), and the one
self-intersection finder it and the mesh check share (:mod:`collider_server.engine.intersections`).
Truth: the union of axis-aligned boxes computed from rectangles (independent of the mesh code),
libigl's own triangle-triangle test, and the winding number at contacts. Metres."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from collider_server.engine.intersections import self_intersections
from collider_server.engine.meshes import ExactSDF, Mesh

CUBE = ((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1))  # 0.2 m
BAR = ((0.02, -0.02, -0.03), (0.06, 0.02, 0.25))  # through the cube's top face, its end buried


def box_mesh(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.box(bounds=[lo, hi])
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def boxes_mesh(*boxes, name="boxes") -> Mesh:
    """Closed boxes (lo, hi) written as one mesh, wound outward."""
    vertices, faces = [], []
    for lo, hi in boxes:
        v, f = box_mesh(lo, hi)
        faces.append(f + sum(len(x) for x in vertices))
        vertices.append(v)
    return Mesh(np.concatenate(vertices), np.concatenate(faces), name)


def rectangle_distance(points, axis, level, lo2, hi2):
    """Distance (n,) from points to the closed rectangle at coordinate ``level`` on ``axis``,
    spanning ``lo2``..``hi2`` on the two other axes (in increasing axis order)."""
    other = [a for a in range(3) if a != axis]
    q = points[:, other]
    gap = np.maximum(np.maximum(lo2 - q, q - hi2), 0.0)
    return np.sqrt((gap ** 2).sum(axis=1) + (points[:, axis] - level) ** 2)


def union_of_boxes_sdf(points, boxes):
    """Signed distance to the boundary of the union of closed axis-aligned boxes: each box face
    cut by the other boxes' bounds into rectangles, a rectangle kept when the point a hair
    outside it (along the face's outward normal) lies in no box; the distance is to the nearest
    kept rectangle, negative inside a box."""
    boxes = [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in boxes]
    best = np.full(len(points), np.inf)
    for k, (lo, hi) in enumerate(boxes):
        for axis, side in itertools.product(range(3), (0, 1)):
            level = (lo, hi)[side][axis]
            normal = np.zeros(3)
            normal[axis] = 1.0 if side else -1.0
            other = [a for a in range(3) if a != axis]
            cuts = []
            for a in other:
                c = {lo[a], hi[a]}
                for j, (lo2, hi2) in enumerate(boxes):
                    if j != k:
                        c |= {x for x in (lo2[a], hi2[a]) if lo[a] < x < hi[a]}
                cuts.append(sorted(c))
            for (u0, u1), (v0, v1) in itertools.product(zip(cuts[0], cuts[0][1:]), zip(cuts[1], cuts[1][1:])):
                centre = np.zeros(3)
                centre[axis] = level
                centre[other[0]], centre[other[1]] = 0.5 * (u0 + u1), 0.5 * (v0 + v1)
                outside = centre + 1e-9 * normal
                if any(((outside >= lo2) & (outside <= hi2)).all() for j, (lo2, hi2) in enumerate(boxes) if j != k):
                    continue
                best = np.minimum(best, rectangle_distance(points, axis, level, np.array([u0, v0]),
                                                           np.array([u1, v1])))
    inside = np.zeros(len(points), dtype=bool)
    for lo, hi in boxes:
        inside |= ((points >= lo) & (points <= hi)).all(axis=1)
    return np.where(inside, -best, best)


def rotation(seed):
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=seed).as_matrix()


def test_the_issue_case_a_point_by_the_buried_end_of_a_bar_in_a_cube():
    """Issue 33's minimal case: a point 0.5 mm above the bar's end face, buried in the cube, is
    57.9 mm from the union's surface (the cube's side at x = 0.1); its contact lands outside."""
    from collider_server.engine.kinds.mesh import MeshCollider
    from collider_server.making.bake import bake_collider

    mesh = boxes_mesh(CUBE, BAR, name="two-boxes")
    point = np.array([[0.0421, 0.0, -0.0295]])
    sdf = ExactSDF(mesh)
    distance, closest, face = sdf.query(point)
    assert abs(distance[0] + 0.0579) < 1e-6
    np.testing.assert_allclose(closest[0], [0.1, 0.0, -0.0295], atol=1e-12)
    assert np.allclose(sdf._face_normals[face[0]], [1.0, 0.0, 0.0])  # a face of the cube's x = 0.1 side
    collider = bake_collider(mesh, "mesh", "two-boxes", show_progress=False)
    assert isinstance(collider, MeshCollider)
    eps = 0.001
    result = collider.query(point, ["distance", "normal", "contact"], eps=eps)
    assert abs(result.distance[0] + 0.0579) < 1e-6
    contact = result.contact[0]
    assert sdf.winding_number((contact + 1e-6 * result.normal[0])[None])[0] < 0.5
    assert sdf.winding_number(contact[None])[0] < 0.5 and abs(contact[0] - (0.1 + eps)) < 1e-9
    union = sdf.union
    assert union is not None and union.crossing_pairs == 8 and union.dropped_faces == 2  # the bar's end


@pytest.mark.parametrize("seed", [0, 1])
def test_random_points_against_the_union_of_boxes_computed_from_rectangles(seed):
    """Three boxes crossing (a cube, a bar through it, a slab through both), turned by a random
    rotation: distance and sign within 1e-9 m of the rectangles' union; the closest point lies on
    the union's boundary (its winding number 1/2 or ... off it along the normal, outside)."""
    boxes = [CUBE, BAR, ((-0.15, -0.05, -0.02), (0.03, 0.05, 0.04))]
    mesh = boxes_mesh(*boxes)
    turn = rotation(seed)
    rng = np.random.default_rng(seed)
    points = rng.uniform((-0.2, -0.2, -0.2), (0.2, 0.2, 0.32), (4000, 3))
    truth = union_of_boxes_sdf(points, boxes)
    sdf = ExactSDF(Mesh(mesh.vertices @ turn.T, mesh.faces, "turned"))
    distance, closest, face = sdf.query(points @ turn.T)
    np.testing.assert_allclose(distance, truth, atol=1e-9)
    normal = sdf.gradient(points @ turn.T, distance, closest, face)
    assert (sdf.winding_number(closest + 1e-7 * normal) < 0.5).all()
    # Each closest point lies in the mesh face it names.
    from collider_server.engine.meshes import barycentric

    weights = barycentric(closest, sdf.mesh.vertices[sdf.mesh.faces[face]])
    assert (weights > -1e-9).all()


def test_boxes_touching_face_to_face_lose_the_shared_wall():
    """A box against another's side (coplanar faces wound against each other, partly
    overlapping): the wall between them is inside the union; a flush box (coplanar faces wound
    alike) keeps both."""
    touching = [((0.0, 0.0, 0.0), (0.1, 0.1, 0.1)), ((0.1, 0.03, 0.02), (0.2, 0.07, 0.13))]
    flush = [((0.0, 0.0, 0.0), (0.1, 0.1, 0.1)), ((0.05, 0.03, 0.02), (0.1, 0.07, 0.13))]
    rng = np.random.default_rng(3)
    for boxes in (touching, flush):
        points = rng.uniform(-0.05, 0.25, (3000, 3))
        points[:500, 0] = rng.uniform(0.095, 0.105, 500)  # near the shared plane
        sdf = ExactSDF(boxes_mesh(*boxes))
        np.testing.assert_allclose(sdf.query(points)[0], union_of_boxes_sdf(points, boxes), atol=1e-9)
    assert self_intersections(*box_mesh(*touching[0])).pairs.shape == (0, 2)
    joined = boxes_mesh(*touching)
    found = self_intersections(joined.vertices, joined.faces)
    assert found.coplanar.any()


def test_a_box_buried_in_another_is_left_out_and_a_cavity_kept():
    """No face crosses: a box inside another, wound alike, is buried (winding 2 inside it); wound
    the other way it is a cavity (winding 0) and stays a surface."""
    outer, inner = ((-0.1,) * 3, (0.1,) * 3), ((-0.02,) * 3, (0.02,) * 3)
    point = np.array([[0.0, 0.0, 0.015]])
    buried = ExactSDF(boxes_mesh(outer, inner))
    assert abs(buried.query(point)[0][0] + 0.085) < 1e-12
    assert buried.union.crossing_pairs == 0 and buried.union.dropped_faces == 12
    v, f = box_mesh(*inner)
    o, g = box_mesh(*outer)
    cavity = ExactSDF(Mesh(np.concatenate([o, v]), np.concatenate([g, f[:, ::-1] + 8]), "cavity"))
    assert cavity.union is None and abs(cavity.query(point)[0][0] - 0.005) < 1e-12


def test_a_mesh_that_crosses_nothing_is_its_own_surface(load_shared_mesh):
    box = boxes_mesh(CUBE)
    sdf = ExactSDF(box)
    assert sdf.union is None
    spot = load_shared_mesh("spot.obj")
    assert len(self_intersections(spot.vertices, spot.faces)) == 0
    assert ExactSDF(spot).union is None


def test_the_finder_agrees_with_libigls_triangle_test():
    """Random triangles, every pair (no candidate search): the pairs that cross and their
    segments equal libigl's tri_tri_intersection_test_3d, pair by pair."""
    import igl

    rng = np.random.default_rng(7)
    centres = rng.uniform(0.0, 1.0, (60, 1, 3))
    tri = centres + rng.normal(0.0, 0.15, (60, 3, 3))
    vertices = tri.reshape(-1, 3)
    faces = np.arange(len(vertices)).reshape(-1, 3)
    found = self_intersections(vertices, faces)
    mine = {tuple(p): s for p, s in zip(found.pairs.tolist(), found.segments)}
    hits = 0
    for i, j in itertools.combinations(range(len(tri)), 2):
        a, b = tri[i], tri[j]
        hit, coplanar, source, target = igl.tri_tri_intersection_test_3d(a[:1], a[1:2], a[2:], b[:1], b[1:2], b[2:])
        assert not coplanar
        length = float(np.linalg.norm(target - source)) if hit else 0.0
        if length < 1e-9:
            assert (i, j) not in mine
            continue
        hits += 1
        segment = mine[(i, j)]
        ends = {tuple(np.round(x, 9)) for x in segment}
        assert ends == {tuple(np.round(x, 9)) for x in (source[0], target[0])}
    assert hits == len(mine) >= 20


def test_faces_sharing_an_edge_or_a_corner_cross_only_beyond_it():
    """A fan of faces around a corner touches, never crosses; two faces sharing only a corner
    cross when one folds through the other; vertices split along a seam count as shared."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0.2, 0.2, -0.5], [0.3, 0.1, 0.5]], float)
    touching = np.array([[0, 1, 2], [0, 2, 3]])
    assert len(self_intersections(v, touching)) == 0
    folded = np.array([[0, 1, 2], [0, 4, 5]])  # shares corner 0 and passes through face 0
    found = self_intersections(v, folded)
    assert len(found) == 1 and np.allclose(found.segments[0][np.argmin(np.abs(found.segments[0]).sum(1))], 0)
    split = np.concatenate([v, v[[0, 2]]])  # corners 0 and 2 again, as a texture seam writes them
    assert len(self_intersections(split, np.array([[0, 1, 2], [6, 7, 3]]))) == 0


def self_overlapping_spot(load_shared_mesh):
    """Two copies of spot written as one mesh, the second moved by a quarter of its size: their
    surfaces cross along a closed curve (a skin folding into itself, in miniature)."""
    spot = load_shared_mesh("spot.obj")
    shift = 0.25 * np.ptp(spot.vertices, axis=0).max() * np.array([1.0, 0.2, 0.1])
    return Mesh(np.concatenate([spot.vertices, spot.vertices + shift]),
                np.concatenate([spot.faces, spot.faces + len(spot.vertices)]), "two-spots")


def test_band_points_where_spot_overlaps_itself_get_contacts_outside(load_shared_mesh):
    """The +-1 mm band around every face of two crossing spots (units taken as metres): the points
    with winding number near 2 (in both) are inside, and their contacts (eps 1 mm) land outside
    the body, but where a straight step past the surface must re-enter it: the closest point is
    on the crease where the copies cross at a fold narrower than 90 degrees (their outward normals
    more than 90 degrees apart), or the other copy lies within eps of it. The nearest triangle's
    answer (what the exact SDF gave before) puts nearly all of them inside."""
    import igl

    from collider_server.making.mesh_check import check_mesh
    from collider_server.making.sampling import surface_points

    mesh = self_overlapping_spot(load_shared_mesh)
    found = self_intersections(mesh.vertices, mesh.faces)
    assert len(found) > 100
    assert check_mesh(mesh).intersecting_pairs == len(found)
    sdf = ExactSDF(mesh)
    surface, normals = surface_points(mesh, 20_000, seed=5)
    offsets = np.random.default_rng(5).uniform(-0.001, 0.001, len(surface))
    points = surface + offsets[:, None] * normals
    deep = points[sdf.winding_number(points) > 1.5]
    assert len(deep) > 1000
    eps = 0.001
    distance, closest, face = sdf.query(deep)
    normal = sdf.gradient(deep, distance, closest, face)
    assert (distance < 0).all()
    inside = sdf.winding_number(deep + (eps - distance)[:, None] * normal) >= 0.5
    assert inside.mean() < 0.05
    half = len(mesh.faces) // 2
    copies = [mesh.faces[:half], mesh.faces[half:]]
    gaps, nearest = zip(*(igl.point_mesh_squared_distance(closest[inside], mesh.vertices, f)[:2] for f in copies))
    gaps = np.sqrt(np.stack(gaps))
    on_crease = (gaps < 1e-9).all(axis=0)
    fold = (sdf._face_normals[nearest[0]] * sdf._face_normals[nearest[1] + half]).sum(axis=1)
    assert ((on_crease & (fold < 0)) | (gaps.min(axis=0) < 1e-9) & (gaps.max(axis=0) < eps)).all()
    nearest_triangle = igl.point_mesh_squared_distance(deep, mesh.vertices, mesh.faces)[2]
    step = nearest_triangle - deep
    old = nearest_triangle + eps * step / np.linalg.norm(step, axis=1, keepdims=True)
    assert (sdf.winding_number(old) >= 0.5).mean() > 0.9


def test_the_animated_exact_kind_answers_against_the_union_in_every_frame_with_right_velocities():
    """A bar sliding down through a still cube (0.1 m/s, two frames 1 s apart): at a time
    between the frames, distances equal the rectangles' union at that time, and the velocity of
    a point by the bar's side, a face cut by the cube's top, is the bar's (face indices refer to
    the mesh, not to the union's triangles), by the cube's side none."""
    from collider_contract.animation import Timeline
    from collider_server.engine.animated_meshes import AnimatedMesh
    from collider_server.making.bake import bake_animated_collider

    rest = boxes_mesh(CUBE, BAR)
    frames = np.stack([rest.vertices, rest.vertices])
    frames[1, 8:, 2] -= 0.1
    collider = bake_animated_collider(AnimatedMesh(frames, rest.faces, Timeline(2, 1.0, loop=False)), "mesh",
                                      "sliding-bar", show_progress=False)
    t = 0.25
    bar = (np.array(BAR[0]) - [0, 0, 0.025], np.array(BAR[1]) - [0, 0, 0.025])
    rng = np.random.default_rng(11)
    points = rng.uniform((-0.2, -0.2, -0.2), (0.2, 0.2, 0.32), (2000, 3))
    got = collider.query(points, ["distance"], time=t).distance
    np.testing.assert_allclose(got, union_of_boxes_sdf(points, [CUBE, bar]), atol=1e-9)
    probes = np.array([[0.061, 0.0, 0.05],   # by the bar's side, under the cube's top: inside
                       [0.065, 0.0, 0.15],   # by the bar's side above the cube
                       [0.11, 0.0, 0.0]])    # by the cube's side
    result = collider.query(probes, ["distance", "velocity"], time=t)
    np.testing.assert_allclose(result.distance, [-0.039, 0.005, 0.01], atol=1e-9)
    np.testing.assert_allclose(result.velocity, [[0, 0, 0], [0, 0, -0.1], [0, 0, 0]], atol=1e-12)


def test_a_bake_of_the_two_boxes_reads_the_union_distance_in_the_overlap(tmp_path, capsys):
    """``collider bake`` of the two boxes written as one OBJ, to a 32^3 voxel grid: deep in the
    overlap the grid holds the union's distance (-60 mm to the cube's side), not the nearest
    triangle's (-20 mm to the bar's side); the bake's mesh check says so in words."""
    import trimesh

    from collider_cli.main import main
    from collider_server.engine.modelfile import load_collider

    mesh = boxes_mesh(CUBE, BAR)
    path = tmp_path / "two-boxes.obj"
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(path)
    code = main(["bake", str(path), "--kind", "voxel", "--resolution", "32", "--name", "two-boxes",
                 "--models", str(tmp_path), "--quiet"])
    out = capsys.readouterr().out
    assert code == 0
    assert "8 pairs of faces that cross each other" in out and "contact refer to the boundary of the union" in out
    collider = load_collider(tmp_path / "two-boxes.safetensors")
    distance = collider.query(np.array([[0.04, 0.0, 0.0]]), ["distance"]).distance[0]
    assert abs(distance + 0.06) < 1e-3


def test_the_kdtree_kind_answers_from_the_unions_vertices_not_the_buried_ones():
    """The approximate kind too answers against the union: the bar's buried end corners are not
    among its vertices, so the issue's point is answered by a corner of the union's boundary."""
    from collider_server.making.bake import bake_collider

    mesh = boxes_mesh(CUBE, BAR, name="two-boxes")
    collider = bake_collider(mesh, "kdtree", "two-boxes", show_progress=False)
    vertices = collider.tensors()["vertices"]
    buried = ((vertices > np.array(CUBE[0]) + 1e-9) & (vertices < np.array(CUBE[1]) - 1e-9)).all(axis=1)
    assert not buried.any()
    # the bar's corners where it leaves the cube's top face are vertices of the union
    assert any(np.allclose(v, [0.02, -0.02, 0.1]) for v in vertices)
    point = np.array([[0.0421, 0.0, -0.0295]])
    distance = collider.query(point, ["distance"]).distance[0]
    assert distance < -0.05  # a buried corner would answer about -0.0005


def test_the_numba_finder_gives_the_numpy_references_pairs_and_segments(load_shared_mesh):
    """The fast path (numba broad phase and pre-filter, :mod:`.intersection_kernels`) against the
    numpy reference: the same box pairs, and the same crossing pairs, segments and coplanar flags,
    bit for bit, on meshes that cross (two boxes, two spots, random triangles, coplanar
    overlapping boxes, faces sharing a corner, folded or in one plane) and ones that do not (spot, a posed skinned arm)."""
    from collider_server.engine import intersection_kernels, intersections
    from collider_server.engine.skinning import pose_at, skin_vertices
    from collider_server.making.skinned import skinned_arm

    if intersection_kernels.numba is None:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(3)
    random = rng.uniform(0.0, 1.0, (80, 1, 3)) + rng.normal(0.0, 0.15, (80, 3, 3))
    arm = skinned_arm()
    spot = load_shared_mesh("spot.obj")
    folded = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, -0.5], [0.3, 0.1, 0.5]], float)
    fan = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [-0.2, 1, 0], [-1, 0.1, 0]], float)
    meshes = [Mesh(folded, np.array([[0, 1, 2], [0, 3, 4]])), Mesh(fan, np.array([[0, 1, 2], [0, 3, 4], [0, 4, 5]])),
              boxes_mesh(CUBE, BAR), boxes_mesh(((0, 0, 0), (1, 1, 1)), ((0.5, 0, 0), (1.5, 1, 1))),
              self_overlapping_spot(load_shared_mesh), Mesh(random.reshape(-1, 3), np.arange(240).reshape(-1, 3)),
              spot, Mesh(skin_vertices(arm, pose_at(arm, "wave", 0.7, "loop")[0]), arm.faces)]
    crossing = 0
    for mesh in meshes:
        tri = mesh.vertices[mesh.faces]
        reference = intersections.overlapping_boxes(tri.min(axis=1), tri.max(axis=1))
        reference = reference[np.lexsort((reference[:, 1], reference[:, 0]))]
        assert np.array_equal(intersection_kernels.box_pairs(tri.min(axis=1), tri.max(axis=1)), reference)
        slow = self_intersections(mesh.vertices, mesh.faces, fast=False)
        fast = self_intersections(mesh.vertices, mesh.faces)
        assert np.array_equal(fast.pairs, slow.pairs)
        assert np.array_equal(fast.segments, slow.segments)
        assert np.array_equal(fast.coplanar, slow.coplanar)
        crossing += len(slow) > 0
    assert crossing == 6


def test_the_faces_kept_whole_are_those_neither_crossing_nor_buried():
    """The cube and the bar through its top (their end buried), and a box buried in another: the
    faces kept whole are exactly those that cross no other face and do not lie inside the other
    box (judged by the boxes themselves); a mesh that crosses nothing keeps every face."""
    from collider_server.engine.union import faces_kept_whole

    for boxes in ((CUBE, BAR), (((-0.1,) * 3, (0.1,) * 3), ((-0.02,) * 3, (0.02,) * 3))):
        mesh = boxes_mesh(*boxes)
        sdf = ExactSDF(mesh)
        kept = faces_kept_whole(mesh.vertices, mesh.faces, sdf.winding_number, sdf.edges)
        crossing = np.zeros(len(mesh.faces), bool)
        crossing[self_intersections(mesh.vertices, mesh.faces).pairs.reshape(-1)] = True
        corners = mesh.vertices[mesh.faces]  # (f, 3, 3); each box's 12 faces in turn
        box = np.repeat(np.arange(len(boxes)), 12)
        inside_other = np.array([any(((corners[f] >= lo).all(1) & (corners[f] <= hi).all(1)).all()
                                     for j, (lo, hi) in enumerate(boxes) if j != box[f])
                                 for f in range(len(mesh.faces))])
        np.testing.assert_array_equal(kept, ~crossing & ~inside_other)
        assert 0 < kept.sum() < len(kept)
    box = boxes_mesh(CUBE)
    sdf = ExactSDF(box)
    assert faces_kept_whole(box.vertices, box.faces, sdf.winding_number, sdf.edges).all()
