"""Collide-only queries (``only_colliding=True``): ``normal`` and ``contact`` only for points with
``distance < eps``, the others get ``normal`` [0, 0, 0] and ``contact`` = the point; the gradient
is evaluated for the colliding points only (the exact mesh kinds evaluate it with the distance,
in one pass: ``gradient_in_one_pass``). Units: metres; the sphere has radius 0.1 m."""

from __future__ import annotations

import numpy as np
import pytest

from collider_contract import FIELDS, ModelQuery, Placed, SceneQuery, finish, finish_scene
from collider_contract.pose import as_pose
from collider_server.engine.collider import Collider

from .test_collider import KINDS, fresh_collider, mixed_points  # noqa: F401  (fixture)


@pytest.fixture
def collider_of(fresh_collider):
    """``fresh_collider`` plus "neural-grid": an untrained grid network (analytic gradient path)
    over the sphere's domain, its table drawn large so the encoding matters."""

    def make(kind: str) -> Collider:
        if kind != "neural-grid":
            return fresh_collider(kind)
        import torch

        from collider_server.engine.collider import ColliderInfo
        from collider_server.engine.kinds.neural import GridArchitecture, NeuralCollider, build_network

        box = fresh_collider("kdtree")
        arch = GridArchitecture(levels=4, features=2, base_resolution=4, max_resolution=40,
                                table_log2=10, hidden_layers=2, hidden_width=16)
        lo, hi = box.domain_min, box.domain_max
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            network = build_network(arch, 0.5 * (lo + hi), 0.5 * float((hi - lo).max()))
            with torch.no_grad():
                network.table.normal_(0.0, 0.5)
        info = ColliderInfo("grid", "neural", lo.tolist(), hi.tolist(),
                            settings={"architecture": dict(arch.__dict__)})
        return NeuralCollider(info, network, "cpu")

    return make


SCALED_POSE = np.array([[0, -2.0, 0, 0.3], [2.0, 0, 0, -0.1], [0, 0, 2.0, 0.05], [0, 0, 0, 1]])


def near_surface(n=600, seed=1, radius=0.1, band=0.01):
    """Points within ``band`` of the sphere's surface, both sides (metres, collider frame)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * (radius + rng.uniform(-band, band, n))[:, None]


def record_gradient_points(collider: Collider) -> list:
    """Wrap the collider's own ``evaluate`` to record how many points each gradient call took."""
    sizes = []
    evaluate = collider.evaluate

    def recording(local, want_gradient):
        if want_gradient:
            sizes.append(len(local))
        return evaluate(local, want_gradient)

    collider.evaluate = recording
    return sizes


@pytest.mark.parametrize("kind", KINDS + ["neural-grid"])
@pytest.mark.parametrize("pose", [None, SCALED_POSE], ids=["identity", "scaled-pose"])
def test_colliding_points_get_the_full_answer_the_others_the_documented_one(collider_of, kind, pose):
    collider = collider_of(kind)
    local = np.concatenate([near_surface(), mixed_points(200)])
    scale = 1.0 if pose is None else 2.0
    points = local * scale if pose is None else local @ SCALED_POSE[:3, :3].T + SCALED_POSE[:3, 3]
    eps = 0.002 * scale
    full = collider.query(points, FIELDS, pose=pose, eps=eps)
    sizes = record_gradient_points(collider)
    only = collider.query(points, FIELDS, pose=pose, eps=eps, only_colliding=True)
    hit = full.collides
    assert 0 < hit.sum() < len(points)  # (the tiny neural collider is untrained: any share)
    np.testing.assert_array_equal(only.distance, full.distance)
    np.testing.assert_array_equal(only.collides, hit)
    np.testing.assert_allclose(only.normal[hit], full.normal[hit], atol=2e-5)
    np.testing.assert_allclose(only.contact[hit], full.contact[hit], atol=2e-6 * scale)
    assert not only.normal[~hit].any()
    np.testing.assert_array_equal(only.contact[~hit], points[~hit])
    if collider.gradient_in_one_pass:  # the exact mesh: distance and gradient in one pass
        assert sizes == [len(points)]
    else:  # the gradient pass saw (about) the colliding points only, not all of them
        assert hit.sum() <= sum(sizes) <= hit.sum() + 2


@pytest.mark.parametrize("kind", ["voxel", "neural"])
def test_points_exactly_at_eps_follow_collides(fresh_collider, kind):
    """The gradient threshold must not miss a point that ``distance < eps`` calls colliding."""
    collider = fresh_collider(kind)
    points = near_surface(2000, band=0.004)
    distance = collider.query(points, "distance").distance.astype(np.float64)
    for eps in np.sort(distance[distance >= 0])[::47]:  # eps equal to (float32) distances
        result = collider.query(points, FIELDS, eps=float(eps), only_colliding=True)
        assert np.allclose(np.linalg.norm(result.normal[result.collides], axis=1), 1.0, atol=1e-5)
        assert not result.normal[~result.collides].any()


@pytest.mark.parametrize("kind", ["voxel", "mesh"])
def test_collides_is_strict_and_the_gradient_pass_is_exact_to_a_relative_1e9(fresh_collider, kind):
    """Against the exact float64 world distance ``d`` of a point (identity pose, metres):
    ``eps = d`` does not collide, the next float64 above does and gets its unit normal, and
    ``eps`` 0.1 nm below ``d`` (more than a relative 1e-9 of it) costs no gradient."""
    collider = fresh_collider(kind)
    points = near_surface(40, seed=3, band=0.03)
    distance, _, _ = collider.query_local(points.astype(np.float64), False)
    chosen = np.flatnonzero((distance > 0.002) & (distance < 0.05))[:4]
    assert len(chosen) == 4
    sizes = record_gradient_points(collider)
    for i in chosen:
        d = float(distance[i])
        at = collider.query(points, FIELDS, eps=d, only_colliding=True)
        assert not at.collides[i] and not at.normal[i].any()
        above = collider.query(points, FIELDS, eps=float(np.nextafter(d, np.inf)),
                               only_colliding=True)
        assert above.collides[i]
        assert np.linalg.norm(above.normal[i]) == pytest.approx(1.0, abs=1e-6)
        sizes.clear()
        below = collider.query(points, FIELDS, eps=d - 1e-10, only_colliding=True)
        assert not below.collides[i] and not below.normal[i].any()
        if not collider.gradient_in_one_pass:
            assert sum(sizes) == below.collides.sum()  # the colliding points, not point i


@pytest.mark.parametrize("kind", ["voxel", "neural"])
def test_without_gradient_fields_the_mode_changes_nothing(fresh_collider, kind):
    collider = fresh_collider(kind)
    sizes = record_gradient_points(collider)
    points = near_surface()
    a = collider.query(points, ["distance", "collides"], only_colliding=True)
    b = collider.query(points, ["distance", "collides"])
    np.testing.assert_array_equal(a.distance, b.distance)
    np.testing.assert_array_equal(a.collides, b.collides)
    assert sizes == []


def test_query_local_takes_a_threshold_per_point(fresh_collider):
    """What a batch joining requests of different eps (and modes) passes: +inf = every point,
    -inf = none."""
    collider = fresh_collider("voxel")
    local = near_surface(300)
    distance, normal, _ = collider.query_local(local, True)
    below = np.full(300, -np.inf)
    below[:100] = np.inf
    below[100:200] = 0.001
    d2, n2, _ = collider.query_local(local, True, below)
    np.testing.assert_array_equal(d2, distance)
    np.testing.assert_array_equal(n2[:100], normal[:100])
    middle = np.arange(100, 200)[distance[100:200] < 0.001]
    np.testing.assert_array_equal(n2[middle], normal[middle])
    assert not np.delete(n2, np.concatenate([np.arange(100), middle]), axis=0).any()
    # Strictly below: a threshold equal to each point's own distance gives no normal at all.
    _, n3, _ = collider.query_local(local, True, distance)
    assert not n3.any()


def test_assembly_answers_free_points_whatever_normal_it_is_given(fresh_collider):
    """``finish`` and ``finish_scene`` with ``only_colliding``: a point with
    ``distance >= eps`` gets normal [0, 0, 0] and contact = the point even when the normal handed
    in is a full one (a point a hair above eps gets one from the gradient pass); a colliding point
    gets the full answer. Scene: the sphere at the origin and the same sphere 1 km away along x
    (nearest to none of these points), eps 2 mm and 3 mm, metres."""
    collider = fresh_collider("voxel")
    points = np.concatenate([near_surface(200, seed=5), mixed_points(50, seed=5)])
    poses = [as_pose(None), as_pose(np.array([[1.0, 0, 0, 1e3], [0, 1, 0, 0], [0, 0, 1, 0],
                                               [0, 0, 0, 1]]))]
    eps = [2e-3, 3e-3]
    answers = [collider.query_local(pose.to_local(points), True) for pose in poses]  # all normals
    full = finish(ModelQuery(points, FIELDS, poses[0], eps[0]), eps[0], *answers[0])
    hit = full.collides
    assert 0 < hit.sum() < len(points)
    single = finish(ModelQuery(points, FIELDS, poses[0], eps[0], True), eps[0], *answers[0])
    scene = finish_scene(SceneQuery(points, (Placed("a", poses[0]), Placed("b", poses[1])), FIELDS, None,
                                    True), eps, answers)
    assert not scene.collider.any()
    for only in (single, scene):
        np.testing.assert_array_equal(only.collides, hit)
        np.testing.assert_array_equal(only.distance, full.distance)
        np.testing.assert_array_equal(only.normal[hit], full.normal[hit])
        np.testing.assert_array_equal(only.contact[hit], full.contact[hit])
        assert not only.normal[~hit].any()
        np.testing.assert_array_equal(only.contact[~hit], points[~hit])
