"""The query interface shared by every kind: field selection, eps, empty input, chunking, point
dtypes, input validation, numerically hard points, the out-of-domain rule and devices.
Units: metres; the sphere has radius 0.1 m and is centred at the origin of its frame."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from collider_contract import FIELDS, QueryError
from collider_contract.pose import MAX_COORDINATE_M
from collider_contract.queries import MAX_POINTS as MAX_POINTS_PER_CALL
from collider_server.engine.collider import Collider, ColliderInfo

KINDS = ["neural", "voxel", "mesh", "kdtree"]
ALL_FIELDS = list(FIELDS)


@pytest.fixture
def fresh_collider(analytic_shape, tiny_neural_collider):
    """A new (unshared, so mutable) small sphere collider of ``kind`` on ``device``."""
    from collider_server.making.bake import bake_collider

    def make(kind: str, device: str = "cpu") -> Collider:
        mesh = analytic_shape("sphere").mesh
        if kind == "neural":
            box = bake_collider(mesh, "kdtree", "box", show_progress=False)
            return tiny_neural_collider(box.domain_min, box.domain_max, device=device)
        return bake_collider(mesh, kind, f"sphere-{kind}", resolution=16, device=device,
                             show_progress=False)

    return make


def mixed_points(n=400, seed=0) -> np.ndarray:
    """Points near the 0.1 m sphere, deep inside, and far outside any domain: (n, 3) float64."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = np.concatenate([rng.uniform(0.0, 0.2, n - n // 4), rng.uniform(0.2, 50.0, n // 4)])
    return directions * radii[:, None]


def assert_results_equal(a, b):
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.mark.parametrize("kind", KINDS)
def test_only_the_fields_asked_for_are_returned(shape_collider, kind):
    collider = shape_collider("sphere", kind)
    points = mixed_points(50)
    everything = collider.query(points, ALL_FIELDS)
    for size in range(1, len(FIELDS) + 1):
        for subset in itertools.combinations(FIELDS, size):
            result = collider.query(points, list(reversed(subset)))
            assert list(result.fields()) == list(subset)
            for name in FIELDS:
                value = getattr(result, name)
                if name in subset:
                    np.testing.assert_array_equal(value, getattr(everything, name), err_msg=name)
                else:
                    assert value is None, name
    # A single field may be given as a string.
    assert list(collider.query(points, "collides").fields()) == ["collides"]


@pytest.mark.parametrize("kind", KINDS)
def test_distance_and_collides_do_no_gradient_work(fresh_collider, kind):
    collider = fresh_collider(kind)
    calls = []
    evaluate = collider.evaluate

    def recording_evaluate(local, want_gradient):
        calls.append(want_gradient)
        distance, gradient = evaluate(local, want_gradient)
        assert (gradient is None) == (not want_gradient)
        return distance, gradient

    collider.evaluate = recording_evaluate
    points = mixed_points(64)
    collider.query(points, ["distance", "collides"])
    assert calls and not any(calls)
    calls.clear()
    collider.query(points, ["collides"])
    assert calls and not any(calls)
    for fields in (["normal"], ["contact"], ["distance", "contact"]):
        calls.clear()
        collider.query(points, fields)
        assert calls and all(calls), fields


@pytest.mark.parametrize("kind", KINDS)
def test_eps_is_per_call(shape_collider, kind):
    collider = shape_collider("sphere", kind)
    points = mixed_points(200, seed=1)
    results = {eps: collider.query(points, ALL_FIELDS, eps=eps) for eps in (0.0, 1e-3, 5e-3)}
    base = results[0.0]
    for eps, result in results.items():
        np.testing.assert_array_equal(result.distance, base.distance)
        np.testing.assert_array_equal(result.collides, base.distance < eps)
        # The returned distance and normal are float32: the contact (float64) matches them to
        # float32 rounding of the push |eps - d|.
        push = (eps - base.distance.astype(np.float64))[:, None]
        error = np.abs(result.contact - (points + push * base.normal))
        rounding = 2e-7 * (np.abs(push) + np.abs(base.distance)[:, None]) + 1e-12
        assert (error <= rounding).all()
    # Between 1 mm and 5 mm from the surface: collides with the larger eps only.
    between = (base.distance > 1e-3) & (base.distance < 5e-3)
    assert between.any()
    assert not results[1e-3].collides[between].any() and results[5e-3].collides[between].all()


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("empty", [np.zeros((0, 3)), np.zeros((0, 3), np.float32), [], np.zeros(0)])
def test_empty_input_gives_empty_fields(shape_collider, kind, empty):
    result = shape_collider("sphere", kind).query(empty, ALL_FIELDS)
    assert result.distance.shape == (0,) and result.distance.dtype == np.float32
    assert result.normal.shape == (0, 3) and result.normal.dtype == np.float32
    assert result.contact.shape == (0, 3)
    assert result.collides.shape == (0,) and result.collides.dtype == bool


@pytest.mark.parametrize("kind", KINDS)
def test_tiny_chunks_give_identical_results(fresh_collider, kind):
    collider = fresh_collider(kind)
    points = mixed_points(301, seed=2)
    whole = collider.query(points, ALL_FIELDS)
    collider.chunk_points = 7  # an instance attribute: this collider only
    chunked = collider.query(points, ALL_FIELDS)
    if kind == "neural":
        # A float32 matrix product's blocking depends on the batch size: the last bit of a
        # distance may change with the chunk size (it does not change between repeated calls).
        np.testing.assert_allclose(chunked.distance, whole.distance, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(chunked.normal, whole.normal, rtol=0, atol=1e-5)
        np.testing.assert_allclose(chunked.contact, whole.contact, rtol=0, atol=1e-6)
        return
    for name in ("distance", "normal", "collides"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name), err_msg=name)
    # torch's vectorised and scalar tail loops may round the last bit of the float64 normal
    # differently (the float32 normal is identical): contacts agree to 1e-15 m.
    np.testing.assert_allclose(chunked.contact, whole.contact, rtol=0, atol=1e-15)


@pytest.mark.parametrize("only_colliding", [False, True])
def test_no_evaluate_call_takes_more_than_chunk_points(fresh_collider, only_colliding):
    """The chunking bounds the memory of a call: every point's distance is evaluated once, in
    pieces of at most ``chunk_points`` (the collide-only gradient pass too), alike in size (none
    left small: a kind may answer a large call by another path than a small one)."""
    collider = fresh_collider("voxel")
    collider.chunk_points = 7  # an instance attribute: this collider only
    calls = []
    evaluate = collider.evaluate

    def recording(local, want_gradient):
        calls.append((len(local), bool(want_gradient)))
        return evaluate(local, want_gradient)

    collider.evaluate = recording
    points = mixed_points(30, seed=5)  # inside and far outside the domain box
    collider.query(points, ALL_FIELDS, eps=0.05, only_colliding=only_colliding)
    if only_colliding:
        assert [n for n, gradient in calls if not gradient] == [6, 6, 6, 6, 6]
        assert 0 < max(n for n, gradient in calls if gradient) <= 7
    else:
        assert calls == [(6, True)] * 5


def test_query_local_gives_no_normal_unless_asked(shape_collider):
    collider = shape_collider("sphere", "voxel")
    local = mixed_points(20, seed=6)
    distance, normal, velocity = collider.query_local(local, False)
    assert normal is None and distance.shape == (20,) and distance.dtype == np.float64
    with_normal = collider.query_local(local, True)
    np.testing.assert_array_equal(with_normal[0], distance)
    assert with_normal[1].shape == (20, 3) and with_normal[1].dtype == np.float64
    assert velocity is None and with_normal[2] is None  # a static collider's surface is still


def test_repr_names_the_kind_the_model_and_the_device(shape_collider):
    assert repr(shape_collider("sphere", "voxel")) == "<VoxelCollider 'sphere-voxel' on cpu>"


@pytest.mark.parametrize("kind", KINDS)
def test_float32_float64_and_list_points(shape_collider, kind):
    collider = shape_collider("sphere", kind)
    points32 = mixed_points(100, seed=3).astype(np.float32)
    points64 = points32.astype(np.float64)
    r32 = collider.query(points32, ALL_FIELDS)
    r64 = collider.query(points64, ALL_FIELDS)
    rlist = collider.query(points64.tolist(), ALL_FIELDS)
    assert r32.contact.dtype == np.float32 and r64.contact.dtype == np.float64
    assert rlist.contact.dtype == np.float64
    for name in ("distance", "normal", "collides"):
        np.testing.assert_array_equal(getattr(r32, name), getattr(r64, name), err_msg=name)
        np.testing.assert_array_equal(getattr(rlist, name), getattr(r64, name), err_msg=name)
    np.testing.assert_array_equal(r32.contact, r64.contact.astype(np.float32))
    # Integer coordinates are numbers too.
    ints = collider.query([[0, 0, 1], [2, 0, 0]], "distance").distance
    np.testing.assert_array_equal(ints, collider.query([[0.0, 0, 1], [2, 0, 0]], "distance").distance)


@pytest.mark.parametrize(
    "points, message",
    [
        (np.array([[0.0, 0.0, np.nan]]), r"NaN or Inf \(first at row 0"),
        (np.array([[0.0, 0.0, 0.0], [np.inf, 0.0, 0.0]]), r"NaN or Inf \(first at row 1"),
        (np.zeros((4, 2)), r"shape \(n, 3\), got \[4, 2\]"),
        (np.zeros(3), r"shape \(n, 3\), got \[3\]"),
        (np.zeros((2, 3, 3)), r"shape \(n, 3\), got \[2, 3, 3\]"),
        (np.array([["a", "b", "c"]]), "points must be float32, float64 or integers, got "),
        (np.array([[1 + 2j, 0, 0]]), "points must be float32, float64 or integers, got "),
        (np.array([[True, False, True]]), "points must be float32, float64 or integers, got "),
    ],
)
def test_bad_points_are_rejected_with_a_clear_message(shape_collider, points, message):
    with pytest.raises(ValueError, match=message):
        shape_collider("sphere", "mesh").query(points, "distance")


def test_too_many_points_are_rejected_before_any_work(shape_collider):
    # A broadcast view: MAX_POINTS_PER_CALL + 1 rows without the memory.
    points = np.broadcast_to(np.zeros(3), (MAX_POINTS_PER_CALL + 1, 3))
    with pytest.raises(ValueError, match=rf"too many points in one call: {MAX_POINTS_PER_CALL + 1} "
                                         rf"> {MAX_POINTS_PER_CALL}"):
        shape_collider("sphere", "voxel").query(points, "distance")


def test_ragged_point_lists_are_rejected_with_a_clear_message(shape_collider):
    with pytest.raises(ValueError, match=r"points must be an \(n, 3\) array"):
        shape_collider("sphere", "mesh").query([[0.0, 0.0, 0.0], [1.0, 2.0]], "distance")


@pytest.mark.parametrize(
    "fields, message",
    [
        (["distance", "speed"], r"unknown field\(s\) \['speed'\]; valid fields are"),
        ("normals", r"unknown field\(s\) \['normals'\]"),
        ([], "no fields asked for"),
    ],
)
def test_bad_fields_are_rejected(shape_collider, fields, message):
    with pytest.raises(ValueError, match=message):
        shape_collider("sphere", "voxel").query(np.zeros((1, 3)), fields)


@pytest.mark.parametrize("eps, message, code", [
    (float("nan"), "^eps must be a finite number, got nan$", "bad-eps"),
    (float("inf"), "^eps must be a finite number, got inf$", "bad-eps"),
    ("big", "^eps must be a finite number, got 'big'$", "bad-eps"),
    (True, "^eps must be a finite number, got True$", "bad-eps"),
    (MAX_COORDINATE_M + 1, r"^eps=1000001\.0 is outside \[0, 1e\+06\] \(world units\)$", "eps-out-of-range"),
    (-1e-3, r"^eps=-0\.001 is outside \[0, 1e\+06\] \(world units\)$", "eps-out-of-range"),
    (-MAX_COORDINATE_M * 1.5, r"^eps=-1500000\.0 is outside", "eps-out-of-range")])
def test_bad_eps_is_rejected(shape_collider, eps, message, code):
    """One eps policy (the contract's): a finite number of world units in [0, 1e6], the value
    refused named as given (not rounded), the service's 422 problem code."""
    with pytest.raises(QueryError, match=message) as refused:
        shape_collider("sphere", "voxel").query(np.zeros((1, 3)), "contact", eps=eps)
    assert refused.value.status == 422 and refused.value.code == code


def test_eps_up_to_the_coordinate_range_is_accepted(shape_collider):
    collider = shape_collider("sphere", "voxel")
    points = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.0]])  # 0.4 m outside, 0.1 m inside
    assert collider.query(points, "collides", eps=MAX_COORDINATE_M).collides.all()
    collides = collider.query(points, "collides", eps=0.0).collides
    assert collides.tolist() == [False, True]  # eps 0: only the point inside


def _pose(block=np.eye(3), translation=(0.0, 0.0, 0.0), bottom=(0.0, 0.0, 0.0, 1.0)):
    m = np.eye(4)
    m[:3, :3] = block
    m[:3, 3] = translation
    m[3] = bottom
    return m


@pytest.mark.parametrize(
    "pose, message",
    [
        (np.eye(3), r"4x4 matrix, got shape \(3, 3\)"),
        ([[1, 0], [0, 1]], r"4x4 matrix, got shape \(2, 2\)"),
        ("identity", "4x4 matrix"),
        (_pose(translation=(0, np.nan, 0)), "NaN or Inf"),
        (_pose(np.diag([1.0, 1.0, -1.0])), "reflection"),
        (_pose(np.diag([1.0, 2.0, 1.0])), "not rigid"),
        (_pose([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "not rigid"),
        (_pose(np.zeros((3, 3))), "scale 0"),
        (_pose(bottom=(0.0, 0.0, 1.0, 1.0)), r"bottom row must be \[0, 0, 0, 1\]"),
    ],
)
def test_bad_poses_are_rejected(shape_collider, pose, message):
    with pytest.raises(QueryError, match=message) as caught:
        shape_collider("sphere", "voxel").query(np.zeros((1, 3)), "distance", pose=pose)
    assert isinstance(caught.value, ValueError) and caught.value.code == "bad-pose"


@pytest.mark.parametrize("kind", KINDS)
def test_numerically_hard_points_stay_finite(shape_collider, analytic_shape, kind):
    """Points exactly on the surface (vertices), at the sphere's centre (zero gradient), on the
    box's edges and corners, duplicated, and 1e-12 m off the surface: finite fields, unit
    normals, identical answers for identical points."""
    sphere, box = analytic_shape("sphere"), analytic_shape("box")
    on_sphere = sphere.mesh.vertices[:50]
    corners = box.mesh.vertices  # the 8 corners
    edges = 0.5 * (corners[:, None] + corners[None, :]).reshape(-1, 3)  # edge/face midpoints too
    cases = {
        "sphere": np.concatenate([
            on_sphere, np.zeros((3, 3)), on_sphere * (1 + 1e-12), on_sphere * (1 - 1e-12),
            np.repeat(on_sphere[:2], 5, axis=0), [[1e-12, 0, 0], [0, 0, -1e-12]]]),
        "box": np.concatenate([corners, edges, corners * (1 + 1e-12), np.repeat(corners[:1], 4, axis=0)]),
    }
    for shape_name, points in cases.items():
        result = shape_collider(shape_name, kind).query(points, ALL_FIELDS)
        for name in ("distance", "normal", "contact"):
            assert np.isfinite(getattr(result, name)).all(), (shape_name, name)
        np.testing.assert_allclose(np.linalg.norm(result.normal, axis=1), 1.0, atol=1e-6)
        _, first = np.unique(points, axis=0, return_index=True)
        _, inverse = np.unique(points, axis=0, return_inverse=True)
        for name in ("distance", "normal", "contact"):
            values = getattr(result, name)
            np.testing.assert_array_equal(values, values[first][inverse.ravel()], err_msg=name)


@pytest.mark.parametrize("kind", ["voxel", "mesh"])
def test_surface_and_centre_values_are_right(shape_collider, analytic_shape, kind):
    sphere = analytic_shape("sphere")
    collider = shape_collider("sphere", kind)
    on_surface = collider.query(sphere.mesh.vertices[:200], ALL_FIELDS, eps=1e-3)
    tolerance = 1e-9 if kind == "mesh" else 1.5e-4
    assert np.abs(on_surface.distance).max() < tolerance
    assert on_surface.collides.all()
    radial = sphere.mesh.vertices[:200] / 0.1
    assert np.einsum("ij,ij->i", on_surface.normal, radial).min() > np.cos(np.radians(3))
    centre = collider.query(np.zeros((1, 3)), ["distance", "normal"])
    # The voxel kind rounds the SDF's cone at the centre over one cell (3.8 mm at 64^3).
    assert abs(centre.distance[0] + 0.1) < (1e-4 if kind == "mesh" else 4e-3)


@pytest.mark.parametrize("kind", ["voxel", "neural"])
def test_points_outside_the_domain_get_the_conservative_rule(shape_collider, kind):
    """Outside its domain box a grid or a network knows nothing: the answer is the value at the
    clamped point (cut at 0) plus the distance to the box, so it is never below the distance to
    the box, and the normal points away from it."""
    collider = shape_collider("sphere", kind)
    lo, hi = collider.domain_min, collider.domain_max
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(300, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    far = directions * rng.uniform(0.3, 1e4, 300)[:, None]
    far = far[(np.abs(far) > hi).any(axis=1)]
    result = collider.query(far, ["distance", "normal", "contact"])
    clamped = np.clip(far, lo, hi)
    box_distance = np.linalg.norm(far - clamped, axis=1)
    at_box = collider.query(clamped, "distance").distance.astype(np.float64)
    np.testing.assert_allclose(result.distance, box_distance + np.maximum(at_box, 0), rtol=1e-6,
                               atol=1e-6)
    assert np.isfinite(result.normal).all() and np.isfinite(result.contact).all()
    np.testing.assert_allclose(np.linalg.norm(result.normal, axis=1), 1.0, atol=1e-6)
    away = (far - clamped) / box_distance[:, None]
    assert np.einsum("ij,ij->i", result.normal, away).min() > 0.0
    # Beyond a few box sizes the direction away from the box dominates.
    very_far = box_distance > 10.0
    assert np.einsum("ij,ij->i", result.normal[very_far], away[very_far]).min() > 0.7
    assert (result.distance >= box_distance.astype(np.float32) - 1e-6).all()


def test_voxel_far_points_are_never_below_the_distance_to_the_box(shape_collider):
    collider = shape_collider("torus", "voxel")
    far = np.array([[1e3, 0, 0], [0, -1e5, 1e5], [7.0, 8.0, 9.0], [0.0, 0.0, 0.2]])
    box_distance = np.linalg.norm(far - np.clip(far, collider.domain_min, collider.domain_max), axis=1)
    distance = collider.query(far, "distance").distance
    assert (distance >= box_distance * (1 - 1e-6)).all()


def test_the_normal_is_continuous_across_the_domain_box(shape_collider):
    """Just outside the box the normal is the model's normal at the box (the clamped point's),
    as just inside: the rule joins the inside without a jump (where the model is positive on the
    box, as a baked voxel grid is)."""
    collider = shape_collider("sphere", "voxel")
    hi = collider.domain_max[0]
    rng = np.random.default_rng(8)
    on_face = np.column_stack([np.full(20, hi), rng.uniform(-0.05, 0.05, (20, 2))])
    step = np.array([1e-7, 0.0, 0.0])
    inside = collider.query(on_face - step, ["distance", "normal"])
    outside = collider.query(on_face + step, ["distance", "normal"])
    assert (inside.distance > 0.005).all()  # the face is off the sphere
    assert np.einsum("ij,ij->i", inside.normal, outside.normal).min() > 0.999


class ConstantCollider(Collider):
    """A model that gives one value everywhere in its box [-1, 1]^3 (metres) and a zero gradient
    (what a collapsed network answers): the base class alone decides every normal."""

    kind = "constant"

    def __init__(self, value: float):
        super().__init__(ColliderInfo("flat", "constant", [-1.0] * 3, [1.0] * 3))
        self.value = value

    def evaluate(self, local, want_gradient):
        gradient = np.zeros((len(local), 3)) if want_gradient else None
        return np.full(len(local), self.value), gradient

    def tensors(self):
        return {"value": np.array([self.value])}

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        return cls(float(tensors["value"][0]))


@pytest.mark.parametrize("value", [0.3, -1.5])
def test_a_zero_gradient_takes_the_documented_fallback_normals(value):
    """Inside the box: the direction from the box centre. Outside: the direction to ``p`` from
    ``c - f(c) n(c)``, ``c`` the clamped point and ``n(c)`` (no gradient there) the direction
    away from the box; the distance is ``|p - c| + max(f(c), 0)``. World = collider frame."""
    collider = ConstantCollider(value)
    inside = np.array([[0.5, 0.0, 0.0], [0.0, -0.3, 0.4]])
    outside = np.array([[1.2, 0.0, 0.0], [2.8, 0.0, 0.0], [1.2, 0.5, 3.0], [-3.0, -3.0, 0.0],
                        [0.0, 0.0, 9.0]])
    if value < 0:  # only points farther from the box than -f(c) (there the normal turns back)
        outside = outside[1:]
    result = collider.query(np.concatenate([inside, outside]), ["distance", "normal"])
    np.testing.assert_allclose(result.distance[:2], value)
    np.testing.assert_allclose(result.normal[:2], inside / np.linalg.norm(inside, axis=1)[:, None],
                               atol=1e-7)
    clamped = np.clip(outside, -1.0, 1.0)
    away = outside - clamped
    away_unit = away / np.linalg.norm(away, axis=1)[:, None]
    np.testing.assert_allclose(result.distance[2:], np.linalg.norm(away, axis=1) + max(value, 0.0),
                               rtol=1e-7)
    direction = outside - (clamped - value * away_unit)
    np.testing.assert_allclose(result.normal[2:],
                               direction / np.linalg.norm(direction, axis=1)[:, None], atol=1e-7)
    assert np.einsum("ij,ij->i", result.normal[2:], away_unit).min() > 0.999  # away from the box


def test_cpu_path_is_explicit(fresh_collider):
    for kind in ("voxel", "neural"):
        assert fresh_collider(kind, "cpu").device == "cpu"
    with pytest.raises(ValueError, match="unknown device"):
        fresh_collider("voxel", "tpu-9000")


def test_the_exact_kinds_run_on_the_cpu_whatever_device_is_asked(fresh_collider):
    """What the service and the SDK report (``device_of``) is where each kind runs."""
    from collider_server.engine.devices import DEVICE_KINDS, device_of

    assert set(DEVICE_KINDS) == {"voxel", "neural", "neural-skinned"}
    assert device_of("skinned", "cuda:1") == "cpu"
    for kind in ("mesh", "kdtree"):
        assert device_of(kind, "cuda:1") == "cpu" and fresh_collider(kind, "cpu").device == "cpu"
    assert device_of("neural", "cuda:1") == "cuda:1" and device_of("voxel", "cpu") == "cpu"


@pytest.mark.parametrize("kind", ["voxel", "neural"])
def test_devices_agree_with_the_cpu(fresh_collider, device, kind):
    points = mixed_points(500, seed=6)
    on_device = fresh_collider(kind, device)
    assert on_device.device.startswith(device)
    result = on_device.query(points, ALL_FIELDS)
    reference = fresh_collider(kind, "cpu").query(points, ALL_FIELDS)
    np.testing.assert_allclose(result.distance, reference.distance, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(result.normal, reference.normal, atol=1e-4)
    again = on_device.query(points, ALL_FIELDS)
    assert_results_equal(again, result)  # deterministic
