"""Hard cases of the engine: each test states a guarantee and proves it on every collider kind
where it applies (neural, voxel, mesh, kdtree). Units: metres. Points, normals and contacts are in
the world frame; ``local`` arrays are in the collider frame.

The neural kind runs on a small random (untrained, seeded) network, and the guarantees that hold
for any network (finite answers, fallbacks, invariances) also on whatever ``models/bunny`` is.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from collider_contract import MAX_COORDINATE_M, QueryError, default_eps
from collider_contract.pose import PoseError, as_pose
from collider_server.engine.collider import Collider

REPO_ROOT = Path(__file__).resolve().parents[2]

KINDS = ["neural", "grid", "voxel", "mesh", "kdtree"]  # grid: the neural default preset
ALL = ["distance", "normal", "contact", "collides"]


def rotation(axis, angle) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def pose_matrix(rot=np.eye(3), translation=(0, 0, 0), scale=1.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = scale * rot
    m[:3, 3] = translation
    return m


def assert_sane(result, n: int) -> None:
    """Every field present is finite, and every normal is a unit vector (never zero)."""
    for name, values in result.fields().items():
        assert len(values) == n, name
        if values.dtype != np.bool_:
            assert np.isfinite(values).all(), f"{name} holds {values[~np.isfinite(values)][:3]}"
    if result.normal is not None and n:
        np.testing.assert_allclose(np.linalg.norm(result.normal, axis=1), 1.0, atol=1e-5)


def blas_blocked(collider: Collider) -> bool:
    """A neural MLP preset (paper, fast): its matrix products are blocked by BLAS according to
    the batch's shape. The grid preset's CPU kernel computes each point alone."""
    architecture = collider.info.settings.get("architecture", {})
    return collider.info.kind == "neural" and architecture.get("encoding") != "grid"


def assert_batch_invariant(collider: Collider, a, b, rows=slice(None)) -> None:
    """``a`` equals ``b[rows]`` field by field: bit for bit, except for the neural MLP presets,
    whose float32 answer for a point may differ in the last bits with its neighbours (a limit,
    documented in the README)."""
    for name in ("distance", "normal", "contact", "collides"):
        x, y = getattr(a, name), getattr(b, name)[rows]
        if not blas_blocked(collider) or x.dtype == np.bool_:
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-6, err_msg=name)


@pytest.fixture(params=KINDS)
def sphere_collider(request, shape_collider):
    """The procedural 0.1 m sphere as each kind (neural, grid: small random networks)."""
    return shape_collider("sphere", request.param)


@pytest.fixture(scope="module")
def shipped_bunny():
    """``models/bunny`` as it is in the repository (any kind, any preset); skips when absent."""
    from collider_server.engine.repository import ModelRepository

    path = REPO_ROOT / "models" / "bunny.safetensors"
    if not path.is_file():
        pytest.skip("models/bunny.safetensors is absent")
    return ModelRepository(REPO_ROOT / "models").load("bunny", "cpu")


def box_distance(collider: Collider, local: np.ndarray) -> np.ndarray:
    """Euclidean distance from collider-frame points to the collider's domain box."""
    return np.linalg.norm(local - np.clip(local, collider.domain_min, collider.domain_max), axis=1)


# -- 1, 2. medial axis, centre points, dead zones ------------------------------------------------


def test_centre_and_medial_points_get_finite_unit_normals(sphere_collider):
    # The sphere's centre (every direction is closest) and points on the medial axis of a box
    # drawn around it: the gradient vanishes or is ambiguous there.
    t = np.linspace(-0.05, 0.05, 11)
    medial = np.concatenate([np.zeros((1, 3)), np.stack([t, t, 0 * t], 1), np.stack([t, -t, t], 1)])
    a = sphere_collider.query(medial, ALL)
    assert_sane(a, len(medial))
    # The choice is deterministic: the same points give bit-identical answers, alone or in a batch.
    b = sphere_collider.query(np.concatenate([medial, np.random.default_rng(0).normal(size=(50, 3))]), ALL)
    assert_batch_invariant(sphere_collider, a, b, slice(0, len(medial)))


def zero_gradient_network(make, lo, hi) -> Collider:
    """A neural collider whose output layer is all zeros: f = 0 everywhere, gradient exactly 0
    (the extreme dead zone of a ReLU network)."""
    import torch

    collider = make(lo, hi, seed=3)
    last = collider.network.body[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
    return collider


def test_vanishing_gradient_falls_back_to_the_direction_from_the_domain_centre_then_plus_z(
        tiny_neural_collider):
    lo, hi = np.array([-0.1, -0.2, -0.1]), np.array([0.1, 0.0, 0.3])
    collider = zero_gradient_network(tiny_neural_collider, lo, hi)
    centre = 0.5 * (lo + hi)
    local = np.array([centre, centre + [0.05, 0, 0], centre + [0, -0.01, 0.02], [0.0, -0.1, 0.0]])
    result = collider.query(local, ["distance", "normal", "contact"], eps=1e-3)
    assert_sane(result, len(local))
    np.testing.assert_array_equal(result.normal[0], [0, 0, 1])  # at the centre itself: +z
    away = local[1:] - centre
    np.testing.assert_allclose(result.normal[1:], away / np.linalg.norm(away, axis=1, keepdims=True),
                               atol=1e-6)
    # contact = p + (eps - 0) n: moved eps along the fallback normal.
    np.testing.assert_allclose(result.contact, local + 1e-3 * result.normal, atol=1e-9)


# -- 3. far points and the coordinate range ------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_far_points_are_conservative_growing_and_point_away(sphere_collider, dtype):
    size = float((sphere_collider.domain_max - sphere_collider.domain_min).max())
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(20, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    factors = np.array([10.0, 1e3, 1e5, MAX_COORDINATE_M / size / 1.01])
    for direction in directions:
        points = (direction[None, :] * (factors * size)[:, None]).astype(dtype)
        result = sphere_collider.query(points, ALL)
        assert_sane(result, len(points))
        local = points.astype(np.float64)
        # Never closer than the domain box (a model knows nothing beyond it), and growing.
        assert (result.distance >= box_distance(sphere_collider, local) * (1 - 1e-6) - 1e-6).all()
        assert (np.diff(result.distance) > 0).all()
        # The normal points away from the object (towards the query point).
        assert (result.normal @ direction > 0.99).all()
        assert not result.collides.any()


def test_the_coordinate_range_is_enforced_with_a_clear_error(sphere_collider):
    ok = np.array([[MAX_COORDINATE_M, -MAX_COORDINATE_M, 0.0]])
    assert_sane(sphere_collider.query(ok, ALL), 1)
    for bad_value in (MAX_COORDINATE_M * 1.000001, 1e39, 1e300, -1e300):
        points = np.zeros((5, 3))
        points[3, 1] = bad_value
        with pytest.raises(ValueError, match=r"coordinate range .*row 3"):
            sphere_collider.query(points, ALL)
    for translation in (1e300, 2 * MAX_COORDINATE_M):
        with pytest.raises(QueryError, match="translation .*coordinate range") as refused:
            sphere_collider.query(np.zeros((1, 3)), ALL, pose=pose_matrix(translation=(0, translation, 0)))
        assert refused.value.code == "bad-pose"
    with pytest.raises(PoseError, match="scale"):
        as_pose(pose_matrix(scale=1e300))
    with pytest.raises(ValueError, match="eps"):
        sphere_collider.query(np.zeros((1, 3)), ALL, eps=1e300)


def test_the_largest_pose_translation_still_gives_finite_answers(sphere_collider):
    t = np.array([MAX_COORDINATE_M, -MAX_COORDINATE_M, MAX_COORDINATE_M]) * (1 - 1e-6)
    points = t + np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3], [-MAX_COORDINATE_M, MAX_COORDINATE_M, -1.0]])
    result = sphere_collider.query(points, ALL, pose=pose_matrix(translation=t))
    assert_sane(result, 3)


# -- 7. NaN, Inf, denormals, -0.0 ----------------------------------------------------------------


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_input_is_refused_naming_the_row(sphere_collider, bad):
    points = np.full((4, 3), 0.05)
    points[2, 0] = bad
    with pytest.raises(ValueError, match="row 2"):
        sphere_collider.query(points, ALL)
    pose = np.eye(4)
    pose[1, 3] = bad
    with pytest.raises(QueryError, match="row 1, column 3") as refused:
        sphere_collider.query(points[:1], ALL, pose=pose)
    assert refused.value.code == "bad-pose"


def test_denormals_and_negative_zero_do_not_contaminate_a_batch(sphere_collider):
    rng = np.random.default_rng(2)
    base = rng.uniform(-0.15, 0.15, size=(64, 3))
    odd = np.array([[-0.0, -0.0, -0.0], [5e-324, -5e-324, 1e-310], [0.1, -0.0, 2.2e-308]])
    alone = sphere_collider.query(base, ALL)
    mixed = sphere_collider.query(np.concatenate([odd, base]), ALL)
    assert_sane(mixed, len(odd) + len(base))
    assert_batch_invariant(sphere_collider, alone, mixed, slice(len(odd), None))
    # -0.0 and denormals answer as the exact zero does.
    zero = sphere_collider.query(np.zeros((1, 3)), ALL)
    np.testing.assert_allclose(mixed.distance[:2], zero.distance[0], atol=1e-6)


# -- 8, 9. far-away colliders, rotated and scaled poses -----------------------------------------


def test_a_collider_1e4_m_away_answers_as_the_untranslated_one(sphere_collider):
    rng = np.random.default_rng(3)
    local = rng.uniform(-0.15, 0.15, size=(300, 3))
    rot = rotation([1, -2, 0.5], 1.3)
    near = pose_matrix(rot)
    far = pose_matrix(rot, [1.0e4, -2.5e4, 0.7e4])
    world_near = local @ rot.T
    world_far = world_near + far[:3, 3]  # float64 points
    a = sphere_collider.query(world_near, ALL, pose=near)
    b = sphere_collider.query(world_far, ALL, pose=far)
    # float64 carries 1e4 m to ~2e-12 m; the engine sees the same local points up to that.
    np.testing.assert_allclose(b.distance, a.distance, atol=2e-6)
    np.testing.assert_allclose(b.normal, a.normal, atol=2e-4)
    np.testing.assert_allclose(b.contact - far[:3, 3], a.contact, atol=1e-8)
    np.testing.assert_array_equal(a.collides[np.abs(a.distance - 1e-3) > 1e-5],
                                  b.collides[np.abs(a.distance - 1e-3) > 1e-5])


@pytest.mark.parametrize("scale", [0.5, 3.0])
def test_rotated_scaled_pose_scales_distance_and_the_default_eps(sphere_collider, scale):
    rng = np.random.default_rng(4)
    local = rng.uniform(-0.15, 0.15, size=(400, 3))
    rot = rotation([0.3, 1, -1], 0.8)
    pose = pose_matrix(rot, [0.2, -0.1, 0.4], scale)
    world = (scale * local) @ rot.T + pose[:3, 3]
    plain = sphere_collider.query(local, ALL)
    posed = sphere_collider.query(world, ALL, pose=pose)
    np.testing.assert_allclose(posed.distance, scale * plain.distance, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(posed.normal, plain.normal @ rot.T, atol=1e-5)
    # The default eps is 1 mm in collider units times the pose's scale, in collides and contact.
    eps = 1e-3 * scale
    assert default_eps(sphere_collider.info.meters_per_unit, as_pose(pose)) == pytest.approx(eps)
    np.testing.assert_array_equal(posed.collides, posed.distance.astype(np.float64) < eps)
    expected = world + (eps - scale * plain.distance.astype(np.float64))[:, None] * posed.normal
    np.testing.assert_allclose(posed.contact, expected, atol=1e-6)


# -- 10. batch invariance ------------------------------------------------------------------------


@pytest.mark.parametrize("n", [0, 1, 7])
def test_small_batches_answer_as_the_same_rows_of_a_big_one(sphere_collider, n):
    rng = np.random.default_rng(5)
    points = rng.uniform(-0.2, 0.2, size=(1000, 3))
    big = sphere_collider.query(points, ALL)
    small = sphere_collider.query(points[:n], ALL)
    assert_sane(small, n)
    assert_batch_invariant(sphere_collider, small, big, slice(0, n))


def test_shuffled_and_chunked_batches_answer_the_same(sphere_collider, monkeypatch):
    rng = np.random.default_rng(6)
    points = rng.uniform(-0.2, 0.2, size=(100_000, 3))
    whole = sphere_collider.query(points, ALL)
    order = rng.permutation(len(points))
    shuffled = sphere_collider.query(points[order], ALL)
    # Chunking, as a 1e7-point call does, with chunks of 4,099 points (a prime: ragged last chunk).
    monkeypatch.setattr(type(sphere_collider), "chunk_points", 4099)
    chunked = sphere_collider.query(points, ALL)
    assert_batch_invariant(sphere_collider, shuffled, whole, order)
    assert_batch_invariant(sphere_collider, chunked, whole)


@pytest.mark.slow
def test_ten_million_points_in_one_call_are_chunked_and_match(shape_collider):
    collider = shape_collider("sphere", "voxel")
    rng = np.random.default_rng(7)
    points = rng.uniform(-0.2, 0.2, size=(10_000_000, 3)).astype(np.float32)
    result = collider.query(points, ["distance", "collides"])
    assert result.distance.shape == (10_000_000,) and np.isfinite(result.distance).all()
    rows = rng.integers(0, len(points), 2000)
    np.testing.assert_array_equal(collider.query(points[rows], ["distance"]).distance,
                                  result.distance[rows])


def test_cpu_and_cuda_agree(shape_collider, device):
    if device == "cpu":
        pytest.skip("compares cuda against cpu")
    from collider_server.engine.modelfile import load_collider, save_collider  # noqa: F401

    cpu = shape_collider("sphere", "voxel")
    gpu = type(cpu).from_tensors(cpu.info, cpu.tensors(), device="cuda")
    points = np.random.default_rng(8).uniform(-0.2, 0.2, size=(10_000, 3))
    a, b = cpu.query(points, ALL), gpu.query(points, ALL)
    np.testing.assert_allclose(a.distance, b.distance, atol=1e-6)
    np.testing.assert_allclose(a.normal, b.normal, atol=1e-4)


# -- 13. projection idempotence ------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["mesh", "voxel"])
def test_projection_is_idempotent(shape_collider, kind):
    # A point moved to its contact is at eps; projecting the contact again moves it < 1e-6 m for
    # the exact mesh. The voxel kind's contact is one Newton step on a trilinear interpolant, off
    # by its interpolation error: a second projection moves it < 2 % of a cell (measured 1.2 %).
    # Not for kdtree (a nearest-vertex estimate) or a random network (not a distance).
    if True:
        collider = shape_collider("sphere", kind)
        rng = np.random.default_rng(9)
        d = rng.normal(size=(2000, 3))
        points = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.09, 0.1, (2000, 1))
        first = collider.query(points, ALL, eps=1e-3)
        assert first.collides.all()
        second = collider.query(first.contact, ALL, eps=1e-3)
        moved = np.linalg.norm(second.contact - first.contact, axis=1)
        cell = float(np.max(getattr(collider, "_spacing", 0.0)))
        bound = 1e-6 if kind == "mesh" else 0.02 * cell
        assert moved.max() < bound, (kind, moved.max())
        np.testing.assert_allclose(second.distance, 1e-3, atol=bound)


# -- 4. exactly on the surface: vertices, edges, sharp creases -----------------------------------


def test_points_exactly_on_vertices_edges_and_creases_of_fandisk(load_shared_mesh):
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.bake import bake_collider

    mesh = load_shared_mesh("fandisk.obj")
    collider = bake_collider(mesh, "mesh", "fandisk", show_progress=False)
    exact = ExactSDF(mesh)
    tri = mesh.vertices[mesh.faces]
    edges = 0.5 * (tri[:, 0] + tri[:, 1])
    points = np.concatenate([mesh.vertices, edges, tri.mean(axis=1)])
    eps = 1e-3 * float(np.ptp(mesh.vertices, axis=0).max())
    result = collider.query(points, ALL, eps=eps)
    assert_sane(result, len(points))
    assert np.abs(result.distance).max() < 1e-9 * max(1.0, float(np.abs(mesh.vertices).max()))
    assert result.collides.all()
    # Every contact leaves the surface to the outside, at least most of eps away (at a crease
    # the chosen face normal is one of the faces meeting there: still outside the solid).
    d_contact = exact.signed_distance(result.contact.astype(np.float64))
    assert (d_contact > 0.5 * eps).all(), (d_contact.min() / eps, np.argmin(d_contact))
    assert (d_contact <= eps * (1 + 1e-9)).all()


# -- 11. degenerate meshes ------------------------------------------------------------------------


def degenerate_box():
    """A unit-ish box (0.2 m) with zero-area faces, duplicated faces, unreferenced vertices and
    every triangle wound inward; returns (Mesh, the clean box's analytic SDF)."""
    import trimesh

    from collider_server.engine.meshes import Mesh

    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide().subdivide().subdivide()
    v = np.asarray(box.vertices, np.float64)
    f = np.asarray(box.faces, np.int64)[:, ::-1]  # inward winding
    n = len(v)
    v = np.concatenate([v, [[5.0, 5.0, 5.0], [-3.0, 0.0, 0.0]],  # unreferenced, far away
                        v[:1]])  # a duplicate vertex
    f = np.concatenate([f, f[:3],  # duplicate faces
                        [[0, 0, 1], [1, 2, 1], [n + 2, 0, 0]]])  # zero-area faces
    return Mesh(v, f, "degenerate-box"), (lambda p: np.linalg.norm(np.maximum(np.abs(p) - 0.1, 0), axis=1)
                                         + np.minimum((np.abs(p) - 0.1).max(axis=1), 0))


@pytest.mark.parametrize("kind", ["voxel", "mesh", "kdtree"])
def test_degenerate_meshes_give_a_correct_collider(kind, tmp_path):
    import trimesh

    from collider_server.making.bake import bake_collider
    from collider_server.making.mesh_files import load_mesh

    mesh, sdf = degenerate_box()
    path = tmp_path / "degenerate.obj"
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(path)
    loaded = load_mesh(path)
    collider = bake_collider(loaded, kind, "degenerate", resolution=32, show_progress=False)
    rng = np.random.default_rng(10)
    points = rng.uniform(-0.15, 0.15, size=(3000, 3))
    result = collider.query(points, ALL)
    assert_sane(result, len(points))
    truth = sdf(points)
    clear = np.abs(truth) > 0.02
    # Inside stays inside despite the inward winding and the junk faces.
    assert np.array_equal(result.distance[clear] < 0, truth[clear] < 0)
    if kind != "kdtree":  # exact and voxel kinds are distances; kdtree is a vertex estimate
        tolerance = 1e-9 if kind == "mesh" else 0.01
        np.testing.assert_allclose(result.distance, truth, atol=tolerance)


# -- 12. eikonal sanity of the shipped neural models ----------------------------------------------


@pytest.mark.xfail(strict=False, reason=(
    "a limit found (README, hard cases): the shipped grid networks are not eikonal enough; "
    "measured |grad f| in [0.9, 1.1] for 90.0 % (bunny) and 77.8 % (dragon) of their +-1 mm band"))
@pytest.mark.parametrize("name", ["bunny", "dragon"])
def test_shipped_neural_models_are_distance_functions_in_the_band(name):
    from collider_server.engine.meshes import ExactSDF  # noqa: F401
    from collider_server.engine.repository import ModelRepository

    if not (REPO_ROOT / "models" / f"{name}.safetensors").is_file():
        pytest.skip(f"models/{name}.safetensors is absent")
    collider = ModelRepository(REPO_ROOT / "models").load(name, "cpu")
    if collider.info.kind != "neural":
        pytest.skip(f"models/{name} is a {collider.info.kind} collider")
    # Points in the +-1 mm band of the model's own zero set: sample the box, keep |f| < 1 mm.
    rng = np.random.default_rng(11)
    box = rng.uniform(collider.domain_min, collider.domain_max, size=(60_000, 3))
    d, _ = collider.evaluate(box, False)
    band = box[np.abs(d) < 1e-3]
    assert len(band) > 200
    _, gradient = collider.evaluate(band, True)
    norm = np.linalg.norm(gradient, axis=1)
    inside = np.mean((norm >= 0.9) & (norm <= 1.1))
    assert inside >= 0.99, f"|grad f| in [0.9, 1.1] for only {100 * inside:.2f} % of the band"


def test_shipped_bunny_gives_sane_answers_on_the_hard_points(shipped_bunny):
    size = float((shipped_bunny.domain_max - shipped_bunny.domain_min).max())
    centre = 0.5 * (shipped_bunny.domain_min + shipped_bunny.domain_max)
    rng = np.random.default_rng(12)
    far = centre + rng.normal(size=(10, 3)) * size * 1e4
    points = np.concatenate([centre[None], far, rng.uniform(shipped_bunny.domain_min,
                                                            shipped_bunny.domain_max, (500, 3))])
    result = shipped_bunny.query(points, ALL)
    assert_sane(result, len(points))
    assert (result.distance[1:11] >= box_distance(shipped_bunny, far) - 1e-6).all()
    chunks = [shipped_bunny.query(points[i:i + 7], ALL) for i in range(0, len(points), 7)]
    for name in ALL:
        joined = np.concatenate([getattr(c, name) for c in chunks])
        if blas_blocked(shipped_bunny):
            np.testing.assert_allclose(joined, getattr(result, name), rtol=1e-6, atol=1e-7)
        else:  # the grid preset: bit-identical in chunks of 7
            np.testing.assert_array_equal(joined, getattr(result, name), err_msg=name)


# -- 5. open meshes: inside / outside agrees with the winding number away from the holes ---------

OPEN_MESHES = ["stanford-bunny.obj", "teapot.obj", "spot.obj", "suzanne.obj"]


@pytest.mark.slow  # bakes four meshes and sums the exact winding number (~1 min)
@pytest.mark.parametrize("name", OPEN_MESHES)
def test_open_meshes_sign_agrees_with_the_exact_winding_number(name, load_shared_mesh):
    import igl

    from collider_server.making.bake import bake_collider

    mesh = load_shared_mesh(name)
    size = float(np.ptp(mesh.vertices, axis=0).max())
    rng = np.random.default_rng(13)
    lo, hi = mesh.bounds
    points = rng.uniform(lo - 0.05 * size, hi + 0.05 * size, size=(1500, 3))
    # The exact generalised winding number (a sum over every triangle: slow, obviously right).
    winding = igl.winding_number(np.ascontiguousarray(mesh.vertices, np.float64),
                                 np.ascontiguousarray(mesh.faces, np.int64), points)
    for kind in ("mesh", "voxel"):
        collider = bake_collider(mesh, kind, name, resolution=64, show_progress=False)
        distance = collider.query(points, ["distance"]).distance
        # Away from the holes (w near 0 or 1) and from the surface (one voxel cell and more).
        clear = ((winding < 0.1) | (winding > 0.9)) & (np.abs(distance) > 2 * size / 64)
        agree = np.mean((distance[clear] < 0) == (winding[clear] > 0.5))
        assert clear.sum() > 500 and agree == 1.0, (kind, agree, clear.sum())


# -- 6. features thinner than 2 eps: the contact is never on the far side ---------------------------


def thin_spots(mesh, exact, max_thickness: float, count: int, seed: int):
    """Surface points (face centroids) whose solid, measured along the inward normal, is thinner
    than ``max_thickness``: (points (m, 3), outward normals (m, 3), thickness (m,))."""
    tri = mesh.vertices[mesh.faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(normal, axis=1)
    keep = area > 0
    centre, normal = tri[keep].mean(axis=1), normal[keep] / area[keep, None]
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(centre), min(4000, len(centre)), replace=False)
    centre, normal = centre[pick], normal[pick]
    steps = np.linspace(0.02, 1.0, 50) * max_thickness
    inside = np.stack([exact.signed_distance(centre - t * normal) < 0 for t in steps], axis=1)
    # Thin: inside just below the surface, outside again before max_thickness.
    thin = inside[:, 0] & ~inside.all(axis=1)
    exit_step = np.argmax(~inside & np.cumsum(inside, axis=1).astype(bool), axis=1)
    thickness = steps[exit_step]
    order = np.flatnonzero(thin)[:count]
    return centre[order], normal[order], thickness[order]


VOXEL_TOO_COARSE = pytest.mark.xfail(strict=True, reason=(
    "a limit found: the teapot's spout and handle (0.02-0.09 units thick) are thinner than a "
    "64^3 voxel cell (0.12): the grid blurs them and some contacts land past the far face"))


@pytest.mark.slow  # bakes the bunny and the teapot (~1-2 min)
@pytest.mark.parametrize("name, thin_m, kind", [
    ("stanford-bunny.obj", 0.006, "mesh"), ("stanford-bunny.obj", 0.006, "voxel"),
    ("teapot.obj", 0.1, "mesh"), pytest.param("teapot.obj", 0.1, "voxel", marks=VOXEL_TOO_COARSE)])
def test_thin_features_never_get_their_contact_on_the_far_side(name, thin_m, kind, load_shared_mesh):
    """Points just inside a feature thinner than 2 eps (bunny ears, teapot spout and handle) are
    pushed out, never on through the far face. Measured: every contact short of the far face;
    99 % (bunny) and 97-99 % (teapot) back out through the near face itself; the others leave
    sideways at creases, or (teapot, eps larger than the gap between its parts) land in another
    part: a limit of any eps wider than the features and gaps it is used near."""
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.bake import bake_collider

    mesh = load_shared_mesh(name)
    exact = ExactSDF(mesh)
    spots, normals, thickness = thin_spots(mesh, exact, thin_m, 200, seed=14)
    assert len(spots) > 50, f"too few features of {name} thinner than {thin_m} m"
    eps = thin_m  # every feature found is thinner than 2 eps
    entered = spots - 0.25 * thickness[:, None] * normals  # just through the near face
    collider = bake_collider(mesh, kind, name, resolution=64, show_progress=False)
    result = collider.query(entered, ["distance", "contact", "collides"], eps=eps)
    assert result.collides.all()
    along = np.einsum("ij,ij->i", result.contact - entered, normals)
    assert (along > -0.75 * thickness).all()  # never past the far face
    assert np.mean(along > 0) >= 0.95, np.mean(along > 0)  # nearly all out through the near face
