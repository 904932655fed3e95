"""The exact patches (:mod:`collider_server.engine.kinds.patches`): the posed faces near a row's
rest closest point answer it as the exact kind does, on the Khronos RiggedFigure (metres, collider
frame) and on the shipped walker's trained network."""

from pathlib import Path

import numpy as np
import pytest

from collider_contract.skeleton import SkeletonPose
from collider_server.engine.kinds import patches
from collider_server.engine.meshes import ExactSDF, Mesh, barycentric
from collider_server.engine.skinning import pose_at, random_poses, skin_velocities, skin_vertices
from collider_server.making.sampling import surface_band_points

WALKER = Path(__file__).parents[3] / "models" / "walker-neural.safetensors"
REACH, CELL = 0.008, 0.016


@pytest.fixture(scope="module")
def posed(figure):
    """The figure off its clip with its motion: ``(skin, cells, surface, exact SDF, points,
    their rest correspondents, the exact distances, closest points and faces)``; the points lie in the
    +-2 mm band, their rest correspondents are their exact closest points' barycentric images on
    the rest mesh."""
    _, skin, _, _, _ = figure
    transforms = random_poses(skin, 1, 41, perturbed_share=1.0).transforms[0]
    _, velocities = pose_at(skin, "animation 0", 0.4)
    vertices = skin_vertices(skin, transforms)
    surface = patches.posed_surface(vertices, skin.faces, velocities=skin_velocities(skin, transforms, velocities))
    exact = ExactSDF(Mesh(vertices, skin.faces, "posed"))
    points = surface_band_points(exact.mesh, 3000, 2e-3, 7)
    distance, closest, face = exact.query(points)
    corners = np.asarray(skin.faces)[face]
    rest = np.einsum("mj,mjc->mc", barycentric(closest, vertices[corners]), skin.vertices[corners])
    cells = patches.patch_cells(skin.vertices, skin.faces, REACH, CELL)
    return skin, cells, surface, exact, points, rest, distance, (closest, face)


def test_a_cell_lists_every_face_within_reach_of_its_points(figure, monkeypatch):
    """Any point within the surface margin of the rest surface finds, in its cell, every face
    within the reach of it (by brute force over all faces); the numba build gives the numpy
    build's cells, and so does numpy in pieces of 97 faces or grouping by a sort."""
    _, skin, rest_sdf, _, _ = figure
    cells = patches.patch_cells(skin.vertices, skin.faces, REACH, CELL)
    plain = patches.patch_cells(skin.vertices, skin.faces, REACH, CELL, fused=False)
    monkeypatch.setattr(patches, "BUILD_FACES", 97)
    monkeypatch.setattr(patches, "DENSE_CELLS", 0)
    for a, b, c in zip(cells, plain, patches.patch_cells(skin.vertices, skin.faces, REACH, CELL, fused=False)):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
    rng = np.random.default_rng(3)
    on = surface_band_points(rest_sdf.mesh, 400, 1e-9, 11)
    points = on + rng.normal(size=on.shape) * (0.5 * patches.SURFACE_MARGIN * CELL / 3)
    slot = patches.cells_of(points, cells)
    assert (slot >= 0).mean() > 0.99
    tri = np.asarray(skin.vertices)[np.asarray(skin.faces)]
    for p, s in zip(points[slot >= 0], slot[slot >= 0]):
        near = np.linalg.norm(patches.closest_on_triangles(np.tile(p, (len(tri), 1)), tri[:, 0], tri[:, 1],
                                                           tri[:, 2])[0] - p, axis=1) <= REACH
        listed = cells.faces[cells.start[s]:cells.start[s + 1]]
        assert set(np.flatnonzero(near)) <= set(listed)


def test_rows_at_their_exact_rest_points_get_the_exact_kind_s_answers(posed):
    """A row whose network puts it at its exact closest point's rest image gets the exact SDF's
    distance, normal and closest point's velocity (a posed face's barycentric blend), where the
    figure's surface is the mesh itself (no self-overlap near the point)."""
    skin, cells, surface, exact, points, rest, distance, (closest, face) = posed
    n = len(points)
    gradient = np.tile([0.0, 0.0, 1.0], (n, 1))  # any direction: the network's distance is 0 here
    d, normal, velocity, answered = patches.answer_on_patches(points, np.arange(n), rest, np.zeros(n), gradient,
                                                              0.01, cells, surface, skin.faces)
    assert (answered >= 0).all()
    same = np.abs(d - distance) < 1e-12
    assert same.mean() > 0.99
    np.testing.assert_allclose(normal[same], exact.gradient(points, distance, closest, face)[same], atol=1e-9)
    corners = np.asarray(skin.faces)[face]
    expected_velocity = np.einsum("mj,mjc->mc", barycentric(closest, surface.vertices[corners]),
                                  surface.velocities[corners])
    np.testing.assert_allclose(velocity[same], expected_velocity[same], atol=1e-9)


def test_the_kernel_answers_as_the_numpy_rule(posed):
    """The numba pass and the numpy rule give the same distances, normals, velocities and faces,
    rows answered and rows left to the network alike (closest points spread by 3 mm, network
    distances off by up to 12 mm: some beyond the reach, some beyond the band)."""
    skin, cells, surface, _, points, rest, distance, _ = posed
    rng = np.random.default_rng(5)
    n = len(points)
    network = distance + rng.uniform(-0.012, 0.012, n)
    gradient = rng.normal(size=(n, 3))
    spread = rest + rng.normal(size=(n, 3)) * 0.003 + network[:, None] * gradient / np.linalg.norm(
        gradient, axis=1, keepdims=True)
    point = rng.permutation(n)  # the rows in another order than the points
    rows = (points, point, spread[point], network[point], gradient[point], 0.01, cells, surface, skin.faces)
    fused = patches.answer_on_patches(*rows)
    plain = patches.answer_on_patches(*rows, fused=False)
    answered = fused[3] >= 0
    assert 0.2 < answered.mean() < 0.95
    np.testing.assert_array_equal(fused[3], plain[3])
    for a, b in zip(fused[:3], plain[:3]):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(fused[0][~answered], network[point][~answered])


def test_a_patch_farther_than_the_network_s_distance_and_the_reach_is_not_the_row_s(posed):
    """A network that puts a point's closest point on another part of the body (the rest image of
    a point at least 10 cm away) keeps its own answer: the faces there lie farther than it says
    plus the reach. Its own closest point answers; and a patch nearer than the network says (the
    network 2 cm off) answers too: the face is a real piece of the surface that near."""
    skin, cells, surface, _, points, rest, distance, _ = posed
    n = len(points)
    gradient = np.tile([0.0, 0.0, 1.0], (n, 1))
    far = np.array([np.flatnonzero(np.linalg.norm(points - p, axis=1) > 0.1)[0] for p in points])
    for where, network, answered in ((rest[far], distance, False), (rest, distance, True), (rest, distance + 0.02, True)):
        d, _, _, face = patches.answer_on_patches(points, np.arange(n), where + network[:, None] * gradient, network,
                                                  gradient, 0.05, cells, surface, skin.faces)
        share = (face >= 0).mean()
        assert share > 0.99 if answered else share < 0.01, share
        np.testing.assert_array_equal(d[face < 0], network[face < 0])


def test_rows_beyond_the_band_keep_the_network_s_answer(posed):
    skin, cells, surface, _, points, rest, _, _ = posed
    n = len(points)
    network = np.full(n, 0.011)
    d, _, _, face = patches.answer_on_patches(points, np.arange(n), rest, network, np.tile([0.0, 0.0, 1.0], (n, 1)),
                                              0.01, cells, surface, skin.faces)
    assert (face < 0).all() and (d == network).all()


def test_cells_need_a_positive_reach_and_size(figure):
    _, skin, _, _, _ = figure
    with pytest.raises(ValueError, match="reach and cell must be > 0"):
        patches.patch_cells(skin.vertices, skin.faces, 0.0, CELL)


@pytest.mark.skipif(not WALKER.exists(), reason="the shipped walker model is not in this checkout")
@pytest.mark.parametrize("near_points", [None, 0], ids=["through the network", "by the pose's cells"])
def test_the_shipped_walker_answers_near_its_skin_as_the_exact_kind(near_points):
    """The shipped walker's network at a pose off its clips, 3,000 points in the +-1 mm band of the
    exact union: nearly every point gets the exact kind's distance (to 1e-9 m), normal and
    velocity, through the network and its exact patches (a query this small) or by the pose's
    cells (a query of NEAR_POINTS or more; here every query), the points they leave through the
    network; the network alone misses by about 0.1 mm on average."""
    from collider_server.engine.modelfile import load_collider
    from collider_server.making.skinned import skinned_collider

    collider = load_collider(WALKER)
    collider.near_points = near_points
    skin = collider.skin
    exact = skinned_collider(skin, "walker", loop=True)
    transforms = random_poses(skin, 1, 909, perturbed_share=1.0).transforms[0]
    _, velocities = pose_at(skin, skin.clips[0].name, 0.3)
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 3000, 1e-3, 17)
    fields = ("distance", "normal", "velocity")
    pose = {"joint_transforms": transforms, "joint_velocities": velocities}
    truth = exact.query(points, fields, **pose)
    answer = collider.query(points, fields, **pose)
    assert np.isfinite(answer.distance).all() and np.isfinite(answer.normal).all()
    same = np.abs(answer.distance - truth.distance) < 1e-9
    assert same.mean() > 0.99
    np.testing.assert_allclose(answer.normal[same], truth.normal[same], atol=1e-6)
    np.testing.assert_allclose(answer.velocity[same], truth.velocity[same], atol=1e-6)
    assert (np.sign(answer.distance) != np.sign(truth.distance)).mean() < 0.002
    alone = collider.evaluate_at(points, False, None, SkeletonPose(joint_transforms=transforms))[0]
    collider.patches = None
    network = collider.evaluate_at(points, False, None, SkeletonPose(joint_transforms=transforms))[0]
    assert np.abs(alone - truth.distance).mean() < 0.2 * np.abs(network - truth.distance).mean()


def test_faces_of_no_area_answer_without_error():
    """A sliver (three corners on a line) and a face collapsed to a point beside a sound face (their
    points all fall in a corner's or an edge's region): both rules answer, the same, and the sound
    face's distance where it is the nearest."""
    vertices = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0],  # a sound face
                         [0.0, 0.0, 0.001], [0.005, 0.0, 0.001], [0.01, 0.0, 0.001],  # a sliver
                         [0.002, 0.002, 0.0]])
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 6, 6]])
    cells = patches.patch_cells(vertices, faces, 0.01, 0.01)
    surface = patches.posed_surface(vertices, faces)
    rng = np.random.default_rng(2)
    points = rng.uniform([-0.002, -0.002, -0.003], [0.012, 0.012, 0.003], (500, 3))
    rows = (points, np.arange(500), points * [1, 1, 0], points[:, 2].copy(), np.tile([0.0, 0.0, 1.0], (500, 1)),
            0.01, cells, surface, faces)
    fused, plain = patches.answer_on_patches(*rows), patches.answer_on_patches(*rows, fused=False)
    assert np.isfinite(fused[0]).all() and (fused[3] >= 0).mean() > 0.9
    np.testing.assert_array_equal(fused[3], plain[3])
    np.testing.assert_allclose(fused[0], plain[0], atol=1e-15)
    below = (points[:, 0] > 0) & (points[:, 1] > 0) & (points[:, 0] + points[:, 1] < 0.0095) & (points[:, 2] < 0)
    np.testing.assert_allclose(fused[0][below], points[below, 2], atol=1e-12)


BAND = 0.004


@pytest.fixture(scope="module")
def near(posed):
    """The posed figure's :class:`~patches.NearCells` (band 4 mm, cells 16 mm) with the faces its
    exact SDF keeps whole."""
    from collider_server.engine.union import faces_kept_whole

    skin, _, surface, exact, _, _, _, _ = posed
    kept = faces_kept_whole(surface.vertices, exact.mesh.faces, exact.winding_number, exact.edges)
    return patches.near_cells(surface, skin.faces, BAND, CELL, kept)


def test_a_pose_s_cell_lists_every_face_within_the_band_of_its_points(posed, near):
    """Any point within the band of the posed surface lies in a listed cell, which lists every face
    within the band of it (brute force); the numba build equals the numpy one (every cell that
    lists a face kept)."""
    skin, _, surface, exact, _, _, _, _ = posed
    cells = near.cells
    for a, b in zip(cells, patches.patch_cells(surface.vertices, skin.faces, BAND, CELL, margin=None, fused=False)):
        np.testing.assert_array_equal(a, b)
    points = surface_band_points(exact.mesh, 300, BAND, 13)
    slot = patches.cells_of(points, cells)
    assert (slot >= 0).all()
    tri = surface.vertices[np.asarray(skin.faces)]
    for p, s in zip(points, slot):
        within = np.linalg.norm(patches.closest_on_triangles(np.tile(p, (len(tri), 1)), tri[:, 0], tri[:, 1],
                                                             tri[:, 2])[0] - p, axis=1) <= BAND
        assert set(np.flatnonzero(within)) <= set(cells.faces[cells.start[s]:cells.start[s + 1]])


def test_points_near_the_posed_skin_get_the_exact_kind_s_answers(posed, near):
    """Points within the band in clean cells get the exact SDF's distance, normal and closest
    point's velocity (1e-12 m): every one of the +-2 mm band's here (the pose crosses nothing near
    them); the numpy rule answers the same."""
    skin, _, surface, exact, points, _, distance, (closest, face) = posed
    d, normal, velocity, answered = patches.answer_near_skin(points, near, surface, skin.faces)
    assert near.clean.mean() > 0.9 and (answered >= 0).mean() > 0.99
    on = answered >= 0
    np.testing.assert_allclose(d[on], distance[on], rtol=0, atol=1e-12)
    np.testing.assert_allclose(normal[on], exact.gradient(points, distance, closest, face)[on], atol=1e-9)
    corners = np.asarray(skin.faces)[face]
    expected = np.einsum("mj,mjc->mc", barycentric(closest, surface.vertices[corners]), surface.velocities[corners])
    np.testing.assert_allclose(velocity[on], expected[on], atol=1e-9)
    plain = patches.answer_near_skin(points, near, surface, skin.faces, fused=False)
    np.testing.assert_array_equal(plain[3], answered)
    for a, b in zip((d, normal, velocity), plain[:3]):
        np.testing.assert_allclose(a[on], b[on], rtol=0, atol=1e-12)


def test_points_beyond_the_band_or_by_a_face_not_kept_whole_are_left(posed):
    """A point farther than the band from the skin is not answered, nor one whose cell lists a face
    the exact kind does not keep whole (crossing another, or buried): the network answers them."""
    skin, _, surface, _, points, _, distance, (_, face) = posed
    narrow = patches.near_cells(surface, skin.faces, 0.001, CELL)
    answered = patches.answer_near_skin(points, narrow, surface, skin.faces)[3] >= 0
    np.testing.assert_array_equal(answered, np.abs(distance) <= 0.001)
    kept = np.ones(len(skin.faces), bool)
    kept[face[:50]] = False
    for fused in (True, False):
        answered = patches.answer_near_skin(points, patches.near_cells(surface, skin.faces, BAND, CELL, kept), surface,
                                            skin.faces, fused=fused)[3] >= 0
        assert not answered[:50].any() and answered.mean() > 0.5


@pytest.mark.skipif(not WALKER.exists(), reason="the shipped walker model is not in this checkout")
def test_where_the_walker_passes_through_itself_the_clean_cells_answer_as_the_union():
    """At poses off the clips where the walker's skin crosses itself, the points its pose's clean
    cells answer get the exact kind's answer (its union's boundary, 1e-9 m), in the +-3 mm band;
    with every face taken as kept (the self-overlap ignored) hundreds would not."""
    from collider_server.engine.modelfile import load_collider
    from collider_server.making.skinned import skinned_collider

    collider = load_collider(WALKER)
    skin = collider.skin
    exact = skinned_collider(skin, "walker", loop=True)
    crossing = wrong = 0
    for transforms in random_poses(skin, 8, 11, perturbed_share=0.5).transforms:
        pose = SkeletonPose(joint_transforms=transforms)
        near = collider.near_cells(None, pose)
        if near.clean.all():
            continue
        crossing += 1
        surface = collider.pose(None, pose).surface
        points = surface_band_points(Mesh(surface.vertices, skin.faces, "posed"), 20000, 3e-3, 5)
        truth = exact.query(points, ("distance",), joint_transforms=transforms).distance
        d, _, _, face = patches.answer_near_skin(points, near, surface, skin.faces)
        on = face >= 0
        assert 0.8 < on.mean() < 1.0
        np.testing.assert_allclose(d[on], truth[on], rtol=0, atol=1e-9)
        everything = patches.near_cells(surface, skin.faces, near.cells.reach, near.cells.cell)
        wrong += (np.abs(patches.answer_near_skin(points, everything, surface, skin.faces)[0] - truth) > 1e-4).sum()
    assert crossing >= 2 and wrong > 100


@pytest.mark.skipif(not WALKER.exists(), reason="the shipped walker model is not in this checkout")
def test_a_collide_only_query_answers_distance_and_normal_in_one_pass():
    """With its patches the articulated collider answers a collide-only query's distance and normal
    in one pass (``gradient_in_one_pass``), so that a large query's distances and the normals of its
    few colliding points come from one path (not the pose's cells' distance and the network's
    normal); the network alone keeps the distance pass, then the normals of the colliding points."""
    from collider_server.engine.modelfile import load_collider

    collider = load_collider(WALKER)
    calls = []
    evaluate_at = collider.evaluate_at

    def recording(local, want_gradient, time, skeleton=None):
        calls.append(bool(want_gradient))
        return evaluate_at(local, want_gradient, time, skeleton)

    collider.evaluate_at = recording
    transforms = random_poses(collider.skin, 1, 77, perturbed_share=0.0).transforms[0]
    points = surface_band_points(Mesh(skin_vertices(collider.skin, transforms), collider.skin.faces, "posed"), 2000,
                                 5e-3, 19)
    for patches_on, expected in ((True, [True]), (False, [False, True])):
        if not patches_on:
            collider.patches = None
        calls.clear()
        answer = collider.query(points, ("distance", "normal"), only_colliding=True, joint_transforms=transforms)
        assert calls == expected and 0 < (answer.distance < 1e-3).sum() < len(points)


@pytest.mark.skipif(not WALKER.exists(), reason="the shipped walker model is not in this checkout")
def test_only_a_query_of_near_points_or_more_uses_the_pose_s_cells():
    """A query smaller than ``near_points`` goes through the network without building the pose's
    cells (a cloth's query cannot repay them); one of ``near_points`` or more asks for them in every
    chunk; ``near_points = None`` never. The kinds' own ``near_points`` are at most half a chunk,
    so that every chunk of such a query (chunks alike in size) is as large: one path per query."""
    from collider_server.engine.kinds.animated_neural import AnimatedNeuralCollider
    from collider_server.engine.modelfile import load_collider

    collider = load_collider(WALKER)
    assert collider.near_points == patches.NEAR_POINTS == 65_536
    for chunk in (collider.chunk_points, AnimatedNeuralCollider.chunk_points, 400):
        least = patches.near_points(chunk)
        assert least <= patches.NEAR_POINTS and 2 * least <= chunk
        for n in (least, chunk - 1, chunk + 1, 2 * chunk + 3, 7 * chunk - 1):
            pieces = -(-n // chunk)
            assert min(n * (k + 1) // pieces - n * k // pieces for k in range(pieces)) >= least
    asked = []
    near_cells = collider.near_cells

    def recording(time, skeleton):
        asked.append(time)
        return near_cells(time, skeleton)

    collider.near_cells = recording
    points = surface_band_points(Mesh(collider.skin.vertices, collider.skin.faces, "rest"), 1000, 5e-3, 3)
    collider.chunk_points = 400  # 1,000 points: three chunks of 333 or 334
    for n, least, expected in ((1000, 1001, 0), (1000, 200, 3), (1000, None, 0), (150, 200, 0), (150, 150, 1)):
        collider.near_points = least
        asked.clear()
        answer = collider.query(points[:n], ("distance", "normal"), time=0.25)
        assert len(asked) == expected and np.isfinite(answer.distance).all(), (n, least)


@pytest.mark.skipif(not WALKER.exists(), reason="the shipped walker model is not in this checkout")
def test_a_large_query_is_answered_near_the_skin_by_the_pose_s_cells_without_the_network():
    """The pose's cells need no network near the skin: with the walker's network scrambled, a query
    of ``near_points`` or more points at a clip time still gets the exact kind's distances in the
    band (its skin crosses nothing there); a smaller one, through the scrambled network, does not."""
    import torch

    from collider_server.engine.modelfile import load_collider
    from collider_server.making.skinned import skinned_collider

    collider = load_collider(WALKER)
    with torch.no_grad():
        collider.network.grid.table.copy_(torch.randn_like(collider.network.grid.table))
    skin = collider.skin
    transforms, _ = pose_at(skin, skin.clips[0].name, 0.37)
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 2000, 1e-3, 23)
    truth = skinned_collider(skin, "walker", loop=True).query(points, ("distance",), joint_transforms=transforms)
    collider.near_points = 2000
    answer = collider.query(points, ("distance",), joint_transforms=transforms).distance
    np.testing.assert_allclose(answer, truth.distance, atol=1e-9)
    collider.near_points = 2001
    answer = collider.query(points, ("distance",), joint_transforms=transforms).distance
    assert np.abs(answer - truth.distance).mean() > 1e-4


def test_by_a_hole_s_rim_the_pose_s_cells_leave_the_points_to_the_network(posed):
    """A face taken out of the posed figure leaves a hole whose rim's faces meet one face at an
    edge: there the exact kind's sign (the winding number's) is not the pseudo-normal's, so every
    cell listing a rim face is unclean (its points go to the network); the closed figure's cells
    are nearly all clean."""
    from collider_server.engine.meshes import edge_index

    skin, _, surface, _, _, _, _, (_, face) = posed
    faces = np.asarray(skin.faces, np.int64)
    near = patches.pose_cells(surface, faces, edge_index(faces), BAND, CELL)
    assert near.clean.mean() > 0.9
    holed = np.delete(faces, face[0], axis=0)
    rim = np.flatnonzero([len(set(f) & set(faces[face[0]])) == 2 for f in holed])
    assert len(rim) == 3
    near = patches.pose_cells(patches.posed_surface(surface.vertices, holed), holed, edge_index(holed), BAND, CELL)
    cells = near.cells
    listing = np.array([np.isin(rim, cells.faces[cells.start[c]:cells.start[c + 1]]).any()
                        for c in range(len(cells.keys))])
    assert listing.sum() > 0 and not near.clean[listing].any() and near.clean[~listing].mean() > 0.9
