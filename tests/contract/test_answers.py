"""How a query is answered: the eps policy, prepare / evaluate / finish, collide-only mode, the
velocity field, the time an animated collider needs, the scene rule and the finiteness guard, each
checked against closed forms in the world frame (an analytic sphere, possibly moving, or a
half-space as the collider's ``evaluate``; metres, seconds)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from collider_contract import (
    DEFAULT_EPS_METERS,
    IDENTITY,
    Evaluation,
    ModelQuery,
    QueryError,
    QueryResult,
    SceneCollider,
    SceneQuery,
    SkeletonPose,
    answer_model_query,
    answer_scene_query,
    as_pose,
    check_finite,
    default_eps,
    finish,
    finish_scene,
    nearest_collider,
    prepare,
    require_time,
    resolve_eps,
)
from collider_contract.answers import gradient_threshold

ALL_FIELDS = ("distance", "normal", "contact", "collides", "velocity")


#: +90 degrees about z, exactly
QUARTER_TURN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def rotation_z(degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def pose_matrix(rotation=np.eye(3), translation=(0.0, 0.0, 0.0), scale=1.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = scale * np.asarray(rotation)
    m[:3, 3] = translation
    return m


class Sphere:
    """A sphere of ``radius`` (collider units) about the collider frame's origin, as an
    ``Evaluate``: its exact SDF and unit normal, the normal only below ``gradient_below``; when
    ``growth`` (collider units/s) its radius grows at that rate, so that its surface moves along
    the normal at ``growth`` (the velocity it gives, collider frame). Records every call's
    arguments."""

    def __init__(self, radius: float, growth: float | None = None):
        self.radius = radius
        self.growth = growth
        self.calls = []

    def __call__(self, local, want_gradient, gradient_below, time):
        self.calls.append((np.array(local), want_gradient, gradient_below, time))
        r = np.linalg.norm(local, axis=1)
        distance = r - self.radius
        if not want_gradient:
            return distance, None, None
        normal = local / r[:, None]
        if gradient_below is not None:
            normal = np.where((distance < gradient_below)[:, None], normal, 0.0)
        return distance, normal, None if self.growth is None else self.growth * normal


class HalfSpace:
    """The half-space z < 0 of the collider frame: distance = z, normal +z (everywhere, whatever
    ``gradient_below``: ``finish`` must zero the free points' normals itself)."""

    def __init__(self, honour_threshold: bool = True):
        self.honour_threshold = honour_threshold
        self.calls = []

    def __call__(self, local, want_gradient, gradient_below, time):
        self.calls.append((np.array(local), want_gradient, gradient_below, time))
        distance = local[:, 2].copy()
        if not want_gradient:
            return distance, None, None
        normal = np.tile([0.0, 0.0, 1.0], (len(local), 1))
        if gradient_below is not None and self.honour_threshold:
            normal[distance >= gradient_below] = 0.0
        return distance, normal, None


def sphere_in_world(points, radius, rotation=np.eye(3), translation=(0.0, 0.0, 0.0), scale=1.0,
                    eps=1e-3, spin=(0.0, 0.0, 0.0), drift=(0.0, 0.0, 0.0), scale_rate=0.0, growth=0.0):
    """The closed-form answer of a sphere posed in the world: centre ``translation``, radius
    ``scale * radius`` (the rotation does not move a sphere centred at the origin). Its frame
    turns at ``spin`` (rad/s, world), moves at ``drift`` (world units/s) and scales at
    ``scale_rate`` (1/s); its radius grows at ``growth`` (collider units/s): a contact ``c`` moves
    at ``spin x (c - t) + drift + scale_rate / scale (c - t) + growth * scale * normal``."""
    offset = np.asarray(points, dtype=np.float64) - translation
    r = np.linalg.norm(offset, axis=1)
    unit = offset / r[:, None]
    distance = r - scale * radius
    contact = np.asarray(translation) + (scale * radius + eps) * unit
    arm = contact - translation
    velocity = (np.cross(spin, arm) + np.asarray(drift) + scale_rate / scale * arm
                + growth * scale * unit)
    return {"distance": distance, "normal": unit, "contact": contact, "collides": distance < eps,
            "velocity": velocity}


def skew(w) -> np.ndarray:
    """The matrix of ``w x``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def pose_rate(rotation, scale, spin=(0.0, 0.0, 0.0), drift=(0.0, 0.0, 0.0), scale_rate=0.0):
    """d/dt of the pose ``[s R, t]`` turning at ``spin``, moving at ``drift``, scaling at
    ``scale_rate``: ``[s W R + s' R, v; 0 0 0 0]``."""
    rate = np.zeros((4, 4))
    rate[:3, :3] = scale * skew(spin) @ rotation + scale_rate * np.asarray(rotation)
    rate[:3, 3] = drift
    return rate


def local_of(points, rotation, translation, scale):
    """World -> collider frame by the closed form R^T (p - t) / s."""
    return (np.asarray(points, np.float64) - translation) @ np.asarray(rotation) / scale


# -- the eps policy ----------------------------------------------------------------------------

def test_the_default_eps_is_one_millimetre_in_collider_units_times_the_scale():
    assert DEFAULT_EPS_METERS == 1e-3
    assert default_eps(1.0, IDENTITY) == 1e-3
    assert default_eps(0.01, IDENTITY) == pytest.approx(0.1, rel=1e-15)      # centimetres
    assert default_eps(1000.0, IDENTITY) == pytest.approx(1e-6, rel=1e-15)   # kilometres
    twice = as_pose(pose_matrix(rotation_z(30), (5.0, 0.0, 0.0), 2.0))
    assert default_eps(0.01, twice) == pytest.approx(0.2, rel=1e-15)
    assert default_eps(1.0, as_pose(pose_matrix(scale=0.5))) == pytest.approx(5e-4, rel=1e-15)


def test_a_given_eps_is_kept_as_it_is_whatever_the_units_and_scale():
    twice = as_pose(pose_matrix(scale=2.0))
    assert resolve_eps(None, 0.01, twice) == pytest.approx(0.2, rel=1e-15)
    assert resolve_eps(0.0, 0.01, twice) == 0.0
    assert resolve_eps(0.25, 0.01, twice) == 0.25
    assert resolve_eps(1e6, 1.0, IDENTITY) == 1e6


@pytest.mark.parametrize("eps, scale, expected", [
    (0.9, 3.0, 0.3 * (1 + 1e-9)), (2.0, 0.5, 4.0 * (1 + 1e-9)), (1e-3, 1.0, 1e-3 * (1 + 1e-9)),
    (0.0, 1.0, 1e-39), (0.0, 4.0, 1e-39)])
def test_the_gradient_threshold_is_eps_over_the_scale_raised_by_a_relative_1e9(eps, scale, expected):
    assert gradient_threshold(eps, as_pose(pose_matrix(scale=scale))) == pytest.approx(expected, rel=1e-15)


# -- prepare / evaluate / finish ---------------------------------------------------------------

@pytest.mark.parametrize("fields, only_colliding, want, below", [
    (["distance"], False, False, None), (["distance", "collides"], True, False, None),
    (["normal"], False, True, None), (["contact", "collides"], True, True, 0.1 * (1 + 1e-9))])
def test_prepare_says_what_the_collider_must_compute(fields, only_colliding, want, below):
    rotation, translation = rotation_z(90), (1.0, 2.0, 3.0)
    points = np.array([[1.0, 2.0, 3.5], [1.0, 4.0, 3.0], [0.0, 2.0, 5.0]], np.float32)
    query = ModelQuery.build(points, fields, pose_matrix(rotation, translation, 2.0), eps=0.2,
                             only_colliding=only_colliding)
    evaluation = prepare(query, 0.01)
    assert isinstance(evaluation, Evaluation)
    assert evaluation.local.dtype == np.float64
    np.testing.assert_allclose(evaluation.local, [[0.0, 0.0, 0.25], [1.0, 0.0, 0.0], [0.0, 0.5, 1.0]],
                               rtol=0, atol=1e-15)
    assert evaluation.want_gradient is want and evaluation.eps == 0.2
    assert evaluation.gradient_below == (None if below is None else pytest.approx(below, rel=1e-15))
    sphere = Sphere(1.0)
    distance, normal, velocity = evaluation.run(sphere)
    assert len(sphere.calls) == 1
    local, wanted, given_below, time = sphere.calls[0]
    assert local.tolist() == evaluation.local.tolist() and wanted is want and given_below == evaluation.gradient_below
    assert time is None and evaluation.time is None
    np.testing.assert_allclose(distance, [-0.75, 0.0, np.sqrt(1.25) - 1.0], rtol=0, atol=1e-15)
    assert (normal is None) is (not want) and velocity is None


def test_prepare_resolves_the_default_eps_in_world_units():
    query = ModelQuery.build(np.zeros((1, 3)), "collides", pose_matrix(scale=4.0))
    assert prepare(query, 0.01).eps == pytest.approx(0.4, rel=1e-15)  # 0.1 cm x 4
    assert prepare(ModelQuery.build(np.zeros((1, 3)), "collides"), 1.0).eps == 1e-3


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("rotation, translation, scale, meters_per_unit", [
    (np.eye(3), (0.0, 0.0, 0.0), 1.0, 1.0),
    (rotation_z(90), (10.0, -20.0, 5.0), 1.0, 1.0),
    (rotation_z(37), (0.5, 0.25, -1.0), 2.5, 0.01),
    (rotation_z(-120), (3e5, 0.0, 0.0), 0.2, 1000.0),
])
def test_a_model_query_is_answered_as_the_posed_sphere_in_the_world(dtype, rotation, translation,
                                                                       scale, meters_per_unit):
    radius = 0.5
    eps = 1e-3 / meters_per_unit * scale  # the default: 1 mm in collider units, times the scale
    rng = np.random.default_rng(6)
    directions = rng.normal(size=(40, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    # world points from 0.3 to 1.7 radii from the centre, and some within eps of the surface
    radii = np.concatenate([rng.uniform(0.3, 1.7, 30), 1.0 + rng.uniform(-1.0, 1.5, 10) * eps / (scale * radius)])
    points = (np.asarray(translation) + directions * (scale * radius * radii)[:, None]).astype(dtype)
    query = ModelQuery.build(points, ALL_FIELDS[::-1], pose_matrix(rotation, translation, scale))
    result = answer_model_query(query, meters_per_unit, Sphere(radius))
    expected = sphere_in_world(points, radius, rotation, translation, scale, eps)
    assert (result.distance.dtype, result.normal.dtype, result.contact.dtype, result.collides.dtype) == (
        np.float32, np.float32, dtype, np.bool_)
    assert result.distance.shape == (40,) and result.normal.shape == result.contact.shape == (40, 3)
    assert result.collider is None and result.model is None
    tolerance = 1e-6 * max(1.0, np.abs(translation).max()) if dtype == np.float64 else 0.05
    np.testing.assert_allclose(result.distance, expected["distance"], rtol=1e-6, atol=tolerance)
    np.testing.assert_allclose(result.normal, expected["normal"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.contact, expected["contact"], rtol=1e-7, atol=tolerance)
    assert result.collides.sum() > 0 and not result.collides.all()
    # a static collider under a still pose: its surface does not move
    assert result.velocity.dtype == np.float32 and result.velocity.tolist() == [[0.0, 0.0, 0.0]] * 40
    if dtype == np.float64:
        np.testing.assert_array_equal(result.collides, expected["collides"])


def test_the_contact_is_computed_in_float64_and_given_in_the_points_dtype():
    # a point 1e5 m out: float32 arithmetic would be off by centimetres
    points = np.array([[100000.5, 0.0, 0.0]], np.float32)
    result = answer_model_query(ModelQuery.build(points, "contact", eps=0.25), 1.0, Sphere(1.0))
    expected = np.float32(1.25)  # the offset surface of the sphere: radius + eps
    assert result.contact.dtype == np.float32 and result.contact.tolist() == [[expected, 0.0, 0.0]]


def test_only_the_fields_asked_for_are_given():
    points = np.array([[0.0, 0.0, 2.0]])
    for fields in (["distance"], ["normal"], ["contact"], ["collides"], ["distance", "contact"]):
        result = answer_model_query(ModelQuery.build(points, fields), 1.0, Sphere(1.0))
        assert sorted(result.fields()) == sorted(fields)
        for name in ALL_FIELDS:
            assert (getattr(result, name) is None) is (name not in fields)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("scale", [1.0, 3.0])
def test_collide_only_mode_answers_free_points_with_a_zero_normal_and_the_point_itself(dtype, scale):
    rotation, translation = rotation_z(90), np.array([1.0, -2.0, 0.5])
    eps = 0.05
    # world distances to the posed unit sphere (radius scale): inside, within eps, outside
    # (exactly at eps: test_a_point_exactly_at_eps_does_not_collide)
    world_d = np.array([-0.5, 0.0, 0.04, 0.0501, 0.06, 2.0])
    directions = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0], [0.6, 0.8, 0]])
    points = (translation + directions * (scale + world_d)[:, None]).astype(dtype)
    sphere = Sphere(1.0)
    query = ModelQuery.build(points, ALL_FIELDS, pose_matrix(rotation, translation, scale), eps, True)
    result = answer_model_query(query, 1.0, sphere)
    # the collider was asked for normals below eps / scale only (+ a relative 1e-9)
    assert sphere.calls[0][2] == pytest.approx(eps / scale * (1 + 1e-9), rel=1e-15)
    expected = sphere_in_world(points, 1.0, rotation, translation, scale, eps)
    colliding = expected["distance"] < eps
    assert colliding.tolist() == [True, True, True, False, False, False]
    assert result.collides.tolist() == colliding.tolist()
    np.testing.assert_allclose(result.distance, expected["distance"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.normal[colliding], expected["normal"][colliding], rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.contact[colliding], expected["contact"][colliding], rtol=0, atol=1e-6)
    assert result.normal[~colliding].tolist() == [[0.0, 0.0, 0.0]] * 3
    assert result.contact.dtype == dtype
    assert result.contact[~colliding].tobytes() == points[~colliding].tobytes()


def test_collide_only_mode_zeroes_the_normals_the_collider_gave_anyway():
    points = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.5], [7.0, 8.0, 9.0]])
    query = ModelQuery.build(points, ["normal", "contact"], eps=0.5, only_colliding=True)
    result = answer_model_query(query, 1.0, HalfSpace(honour_threshold=False))
    assert result.normal.tolist() == [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    assert result.contact.tolist() == [[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [7.0, 8.0, 9.0]]
    # without the mode every point gets its normal and its contact
    full = answer_model_query(ModelQuery.build(points, ["normal", "contact"], eps=0.5), 1.0,
                              HalfSpace(honour_threshold=False))
    assert full.normal.tolist() == [[0.0, 0.0, 1.0]] * 3
    assert full.contact.tolist() == [[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [7.0, 8.0, 0.5]]


def test_collide_only_mode_without_gradient_fields_changes_nothing():
    points = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 0.5]])
    sphere = Sphere(1.0)
    result = answer_model_query(ModelQuery.build(points, ["distance", "collides"], eps=0.1,
                                                 only_colliding=True), 1.0, sphere)
    assert sphere.calls[0][1:] == (False, None, None)
    assert result.distance.tolist() == [1.0, -0.5] and result.collides.tolist() == [False, True]


def test_a_point_exactly_at_eps_does_not_collide():
    points = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, np.nextafter(0.5, 0.0)]])
    result = answer_model_query(ModelQuery.build(points, ALL_FIELDS, eps=0.5, only_colliding=True),
                                1.0, HalfSpace())
    assert result.collides.tolist() == [False, True]
    assert result.normal.tolist() == [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    assert result.contact.tolist() == [[0.0, 0.0, 0.5], [0.0, 0.0, 0.5]]


def test_a_point_that_collides_only_after_scaling_gets_its_normal():
    # collider distance 0.3 = eps / scale exactly, yet 0.3 * 3 = 0.8999999999999999 < eps = 0.9:
    # the point collides, and the relative 1e-9 above eps / scale gets its normal computed.
    assert 0.9 / 3.0 == 0.3 and 0.3 * 3.0 < 0.9
    points = np.array([[0.0, 0.0, 0.9], [0.0, 0.0, 0.9 * (1 + 1e-8)]])
    half_space = HalfSpace()
    result = answer_model_query(ModelQuery.build(points, ALL_FIELDS, pose_matrix(scale=3.0), 0.9, True),
                                1.0, half_space)
    assert half_space.calls[0][0][:, 2].tolist()[0] == 0.3
    assert result.collides.tolist() == [True, False]
    assert result.normal.tolist() == [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]
    assert result.contact[0].tolist() == [0.0, 0.0, 0.9 + (0.9 - 0.3 * 3.0)]


def test_finish_scales_distances_and_rotates_normals_into_the_world():
    pose = pose_matrix(rotation_z(90), (1.0, 0.0, 0.0), 2.0)
    points = np.array([[1.0, 3.0, 0.0], [1.0, 0.0, 0.0]], np.float32)
    query = ModelQuery.build(points, ALL_FIELDS, pose)
    distance = np.array([0.5, -1.0])           # collider units
    normal = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # collider frame
    result = finish(query, 1.5, distance, normal)
    assert isinstance(result, QueryResult)
    assert result.distance.dtype == np.float32 and result.distance.tolist() == [1.0, -2.0]
    np.testing.assert_allclose(result.normal, [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], rtol=0, atol=1e-7)
    np.testing.assert_allclose(result.contact, [[1.0, 3.5, 0.0], [1.0, 0.0, 3.5]], rtol=0, atol=1e-6)
    assert result.collides.tolist() == [True, True]
    assert finish(query, 1.0, distance, normal).collides.tolist() == [False, True]  # 1.0 < 1.0: no
    only = finish(ModelQuery.build(points, ["distance", "collides"], pose), 1.5, distance, None)
    assert only.normal is None and only.contact is None and only.distance.tolist() == [1.0, -2.0]


# -- the finiteness guard ----------------------------------------------------------------------

@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # inf x 0
def test_an_answer_that_is_not_finite_is_refused_naming_the_first_bad_row():
    class Overflowing(Sphere):
        def __call__(self, local, want_gradient, gradient_below, time):
            distance, normal, velocity = super().__call__(local, want_gradient, gradient_below, time)
            distance[2:] = np.inf
            if normal is not None:
                normal[1] = np.nan
            return distance, normal, velocity

    points = np.array([[0.0, 0.0, 2.0], [0.0, 3.0, 0.0], [4.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    for fields, row, field in ((["distance"], 2, "distance"), (["normal"], 1, "normal"),
                               (["contact"], 1, "contact"), (["collides"], None, None),
                               (["distance", "normal"], 1, "normal")):
        query = ModelQuery.build(points, fields)
        if row is None:  # booleans are always finite
            assert answer_model_query(query, 1.0, Overflowing(1.0)).collides.tolist() == [False] * 4
            continue
        with pytest.raises(QueryError) as refused:
            answer_model_query(query, 1.0, Overflowing(1.0), where="model 'far'")
        assert str(refused.value) == (f"points row {row} ({points[row].tolist()}) has no finite "
                                      f"{field}: it lies too far from model 'far' (world frame, with "
                                      "the pose given)")
        assert (refused.value.status, refused.value.code) == (422, "out-of-range")
    with pytest.raises(QueryError, match=re.escape("lies too far from the collider (world")):
        answer_model_query(ModelQuery.build(points), 1.0, Overflowing(1.0))


def test_check_finite_counts_rows_from_first_row():
    points = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    result = QueryResult(distance=np.array([0.0, 1.0], np.float32),
                         normal=np.array([[0.0, 0.0, 1.0], [np.inf, 0.0, 0.0]], np.float32),
                         collides=np.array([True, False]), collider=np.array([0, 1], np.int32))
    with pytest.raises(QueryError) as refused:
        check_finite(result, points, "the colliders", first_row=1000)
    assert str(refused.value) == ("points row 1001 ([1.0, 2.0, 3.0]) has no finite normal: it lies "
                                  "too far from the colliders (world frame, with the pose given)")
    result.normal[1, 0] = 0.0
    check_finite(result, points, "the colliders", first_row=1000)  # finite: nothing to say
    # every float field counts: a bad distance with finite normals
    result.distance[0] = np.nan
    with pytest.raises(QueryError, match=r"^points row 1000 \(\[0\.0, 0\.0, 0\.0\]\) has no finite distance"):
        check_finite(result, points, "the colliders", first_row=1000)
    result.normal[1, 2] = -np.inf
    with pytest.raises(QueryError, match=r"^points row 1000 "):
        check_finite(result, points, "the colliders", first_row=1000)
    check_finite(QueryResult(collides=np.array([True])), points[:1], "x")
    check_finite(QueryResult(distance=np.zeros(0, np.float32)), np.zeros((0, 3)), "x")


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # 1e300 -> float32
def test_a_velocity_that_overflows_is_named_not_the_point():
    # a surface so fast that its velocity overflows float32 (issue 35: --fps 1e300): the
    # distance is fine, and the refusal says the velocity is what has no finite value
    class Racing(Sphere):
        def __call__(self, local, want_gradient, gradient_below, time):
            distance, normal, _ = super().__call__(local, want_gradient, gradient_below, time)
            return distance, normal, None if normal is None else normal * 1e300

    points = np.array([[0.0, 0.0, 2.0], [0.0, 3.0, 0.0]])
    with pytest.raises(QueryError) as refused:
        answer_model_query(ModelQuery.build(points, ["distance", "velocity"], time=0.0), 1.0,
                           Racing(1.0), where="model 'fast'")
    assert str(refused.value) == ("points row 0 ([0.0, 0.0, 2.0]) has no finite velocity: the "
                                  "velocity of model 'fast' there overflows float32 (world units "
                                  "per second, with the pose and pose_velocity given)")
    assert refused.value.code == "out-of-range"


# -- the scene rule ----------------------------------------------------------------------------

def test_nearest_collider_is_the_smallest_distance_and_a_tie_goes_to_the_first():
    world_distance = np.array([[0.3, -0.1, 0.2, 0.5, -2.0],   # collider 0, metres
                               [0.3, -0.2, 0.1, 0.5, 1.0],    # collider 1
                               [0.1, 0.0, 0.1, 0.5, -1.0]])   # collider 2
    nearest = nearest_collider(world_distance)
    assert nearest.dtype == np.int32 and nearest.shape == (5,)
    np.testing.assert_array_equal(nearest, [2, 1, 1, 0, 0])
    np.testing.assert_array_equal(nearest_collider(world_distance[1:2]), np.zeros(5))
    # Compared in float64: 1e-12 m apart is not a tie.
    np.testing.assert_array_equal(nearest_collider([[0.05], [0.05 - 1e-12]]), [1])
    assert nearest_collider(np.array([[1.0, 2.0], [1.0, 1.0]], np.float32)).tolist() == [0, 1]
    assert nearest_collider(np.zeros((2, 0))).shape == (0,)


@pytest.mark.parametrize("world_distance", [np.zeros(3), np.zeros((0, 4)), np.zeros((2, 2, 2)),
                                            np.float64(1.0)])
def test_nearest_collider_needs_one_row_per_collider(world_distance):
    with pytest.raises(ValueError) as refused:
        nearest_collider(world_distance)
    assert str(refused.value) == (f"world_distance must be (k, n) with k >= 1, got "
                                  f"{np.shape(world_distance)}")


def _scene_points():
    # between two spheres: unit sphere at the origin (collider 0), radius-0.5 sphere at x = 3
    # turned a quarter about z, scaled 2 (world radius 1), in centimetres (collider 1)
    return np.array([[0.0, 0.0, 1.0005],    # 0: on sphere 0 (within its 1 mm)
                     [1.5, 0.0, 0.0],       # 1: equidistant (0.5 from both): the first
                     [1.6, 0.0, 0.0],       # 2: nearer sphere 1
                     [3.0, 1.05, 0.0],      # 3: on sphere 1, within its eps (0.1 cm x 2 = 0.2)
                     [-0.5, 0.0, 0.0],      # 4: inside sphere 0
                     [3.0, 0.0, 0.5]])      # 5: inside sphere 1


@pytest.mark.parametrize("only_colliding", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_scene_query_answers_per_point_the_nearest_collider(only_colliding, dtype):
    points = _scene_points().astype(dtype)
    second = pose_matrix(QUARTER_TURN, (3.0, 0.0, 0.0), 2.0)
    query = SceneQuery.build(points, [("unit", None), ("small", second)], ALL_FIELDS,
                             only_colliding=only_colliding)
    spheres = [Sphere(1.0), Sphere(0.5)]
    result = answer_scene_query(query, [1.0, 0.01], spheres)
    eps = [1e-3, 0.1 * 2.0]  # each collider's default, world units
    # each collider was asked for all the points, under its pose, with its own threshold
    assert spheres[1].calls[0][0] == pytest.approx(local_of(points, QUARTER_TURN, (3.0, 0, 0), 2.0),
                                                   abs=1e-12)
    assert [s.calls[0][2] for s in spheres] == ([None, None] if not only_colliding else [
        pytest.approx(1e-3 * (1 + 1e-9), rel=1e-15), pytest.approx(0.1 * (1 + 1e-9), rel=1e-15)])
    expected = [sphere_in_world(points, 1.0, eps=eps[0]),
                sphere_in_world(points, 0.5, QUARTER_TURN, (3.0, 0.0, 0.0), 2.0, eps=eps[1])]
    nearest = [0, 0, 1, 1, 0, 1]
    assert result.collider.dtype == np.int32 and result.collider.tolist() == nearest
    assert result.model is None
    rows = np.arange(6)
    want = {name: np.array([expected[k][name][i] for i, k in zip(rows, nearest)]) for name in ALL_FIELDS}
    assert result.collides.dtype == np.bool_
    assert result.collides.tolist() == [True, False, False, True, True, True] == want["collides"].tolist()
    assert result.distance.dtype == np.float32 and result.normal.dtype == np.float32
    assert result.contact.dtype == dtype
    np.testing.assert_allclose(result.distance, want["distance"], rtol=0, atol=1e-6)
    if only_colliding:
        free = ~want["collides"]
        want["normal"][free] = 0.0
        want["contact"][free] = points[free]
    np.testing.assert_allclose(result.normal, want["normal"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.contact, want["contact"], rtol=0, atol=1e-6)


def test_a_collider_nearest_to_no_point_adds_nothing():
    points = np.array([[0.0, 0.0, 2.0], [0.0, 0.5, 0.0]])
    far = pose_matrix(translation=(100.0, 0.0, 0.0))
    for colliders, index in (([("far", far), "unit"], 1), (["unit", ("far", far)], 0),
                             ([("far", far), "unit", ("far", far)], 1)):
        query = SceneQuery.build(points, colliders, ALL_FIELDS, eps=0.01)
        result = answer_scene_query(query, [1.0] * len(colliders), [Sphere(1.0)] * len(colliders))
        assert result.collider.tolist() == [index, index]
        assert result.distance.tolist() == [1.0, -0.5] and result.collides.tolist() == [False, True]
        assert result.normal.tolist() == [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]
        np.testing.assert_allclose(result.contact, [[0.0, 0.0, 1.01], [0.0, 1.01, 0.0]], rtol=0, atol=1e-15)


def test_a_scene_query_asks_only_the_fields_asked_for():
    points = np.array([[0.0, 0.0, 2.0]])
    result = answer_scene_query(SceneQuery.build(points, ["a", "b"], "collides"), [1.0, 1.0],
                                [Sphere(1.0), Sphere(1.5)])
    assert result.fields().keys() == {"collides"} and result.collides.tolist() == [False]
    assert result.collider.tolist() == [1] and result.distance is None and result.normal is None


@pytest.mark.parametrize("units, evaluate, animated", [
    ([1.0], [Sphere(1.0), Sphere(1.5)], None),  # one collider's units missing
    ([1.0, 1.0], [Sphere(1.0)], None),  # one evaluation missing
    ([1.0, 1.0, 1.0], [Sphere(1.0), Sphere(1.5), Sphere(2.0)], None),  # one too many
    ([1.0, 1.0], [Sphere(1.0), Sphere(1.5)], [False]),  # one animated flag missing
])
def test_a_scene_query_needs_one_of_each_per_collider(units, evaluate, animated):
    """Lists shorter or longer than the scene's colliders are an error, never a scene cut short."""
    query = SceneQuery.build(np.array([[0.0, 0.0, 2.0]]), ["a", "b"], "distance")
    with pytest.raises(ValueError, match="zip"):
        answer_scene_query(query, units, evaluate, animated)


def test_finish_scene_compares_world_distances_with_each_pose():
    # collider 0: distance 0.4 in units of a pose scaled 3 (1.2 m); collider 1: 1.0 unscaled
    points = np.zeros((1, 3))
    query = SceneQuery.build(points, [("a", pose_matrix(scale=3.0)), "b"], ["distance", "collides"], 1.1)
    result = finish_scene(query, [1.1, 1.1], [(np.array([0.4]), None), (np.array([1.0]), None)])
    assert result.collider.tolist() == [1] and result.distance.tolist() == [1.0]
    assert result.collides.tolist() == [True]
    # per collider eps
    result = finish_scene(query, [5.0, 0.5], [(np.array([0.4]), None), (np.array([1.0]), None)])
    assert result.collides.tolist() == [False]


def test_a_scene_answer_that_is_not_finite_is_refused():
    points = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])
    query = SceneQuery.build(points, ["a"], ["distance"])
    with pytest.raises(QueryError) as refused:
        finish_scene(query, [0.001], [(np.array([1.0, np.inf]), None)])
    assert str(refused.value) == ("points row 1 ([0.0, 0.0, 3.0]) has no finite distance: it lies too "
                                  "far from the colliders (world frame, with the pose given)")
    assert refused.value.code == "out-of-range"


def test_a_collide_only_scene_query_zeroes_the_normals_a_collider_gives_anyway():
    points = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.5], [7.0, 8.0, 9.0], [10.0, 0.0, 0.2]])
    far = pose_matrix(translation=(10.0, 0.0, 0.0), scale=2.0)  # the plane z = 0 too, but scaled
    query = SceneQuery.build(points, ["near", ("far", far)], ["normal", "contact", "collides"], 0.5, True)
    result = answer_scene_query(query, [1.0, 1.0], [HalfSpace(honour_threshold=False)] * 2)
    assert result.collider.tolist() == [0, 0, 0, 0]  # a tie goes to the first
    assert result.collides.tolist() == [True, False, False, True]
    assert result.normal.tolist() == [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    assert result.contact.tolist() == [[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [7.0, 8.0, 9.0], [10.0, 0.0, 0.5]]



# -- time and velocity -------------------------------------------------------------------------

MOTIONS = {
    "spin": {"spin": (0.0, 0.0, 2.0)},
    "tumble": {"spin": (0.3, -1.0, 0.5)},
    "drift": {"drift": (1.0, -2.0, 0.5)},
    "swell": {"scale_rate": 0.5},
    "growth": {"growth": 0.25},
    "all": {"spin": (0.3, -1.0, 0.5), "drift": (1.0, -2.0, 0.5), "scale_rate": -0.5, "growth": 0.25},
}


@pytest.mark.parametrize("motion", MOTIONS)
@pytest.mark.parametrize("fields", [ALL_FIELDS, ("velocity",), ("distance", "velocity")])
def test_velocity_is_the_frames_motion_at_the_contact_plus_the_surfaces_own(motion, fields):
    rotation, translation, scale, eps = rotation_z(37), np.array([1.0, -2.0, 0.5]), 2.0, 0.05
    motion = MOTIONS[motion]
    frame = {k: v for k, v in motion.items() if k != "growth"}
    points = np.random.default_rng(9).uniform(-3.0, 3.0, (25, 3)) + translation
    query = ModelQuery.build(points, fields, pose_matrix(rotation, translation, scale), eps,
                             pose_velocity=pose_rate(rotation, scale, **frame) if frame else None)
    result = answer_model_query(query, 1.0, Sphere(0.5, motion.get("growth")))
    expected = sphere_in_world(points, 0.5, rotation, translation, scale, eps, **motion)
    assert result.velocity.dtype == np.float32 and result.velocity.shape == (25, 3)
    assert np.abs(expected["velocity"]).max() > 0.1
    np.testing.assert_allclose(result.velocity, expected["velocity"], rtol=0, atol=2e-6)
    assert sorted(result.fields()) == sorted(fields)


def test_collide_only_velocity_is_zero_for_free_points():
    rotation, translation = QUARTER_TURN, np.array([0.0, 0.0, 1.0])
    points = np.array([[0.0, 0.0, 1.5], [0.9, 0.0, 1.0], [0.0, 3.0, 1.0], [0.0, -1.2, 1.0]])
    motion = {"spin": (0.0, 0.0, 1.0), "drift": (0.0, 0.0, 3.0)}
    query = ModelQuery.build(points, ["velocity", "collides"], pose_matrix(rotation, translation), 0.1,
                             True, pose_velocity=pose_rate(rotation, 1.0, **motion))
    result = answer_model_query(query, 1.0, Sphere(1.0, growth=1.0))
    expected = sphere_in_world(points, 1.0, rotation, translation, 1.0, 0.1, growth=1.0, **motion)
    assert result.collides.tolist() == [True, True, False, False]
    np.testing.assert_allclose(result.velocity[:2], expected["velocity"][:2], rtol=0, atol=1e-6)
    assert result.velocity[2:].tolist() == [[0.0, 0.0, 0.0]] * 2


def test_the_time_goes_to_the_collider():
    sphere = Sphere(1.0)
    query = ModelQuery.build(np.zeros((1, 3)) + 2.0, "distance", time=2.5)
    assert prepare(query, 1.0).time == 2.5
    answer_model_query(query, 1.0, sphere, animated=True)
    assert sphere.calls[0][3] == 2.5


def test_an_animated_collider_needs_a_time():
    untimed = ModelQuery.build(np.zeros((1, 3)) + 2.0, "distance")
    require_time(untimed, False, "x")
    require_time(ModelQuery.build(np.zeros((1, 3)), time=0.0), True, "x")
    sphere = Sphere(1.0)
    with pytest.raises(QueryError) as refused:
        answer_model_query(untimed, 1.0, sphere, where="model 'walker'", animated=True)
    assert str(refused.value) == "model 'walker' is animated: give the time (seconds) to ask it at"
    assert (refused.value.status, refused.value.code) == (422, "missing-time")
    assert sphere.calls == []  # refused before any evaluation
    assert answer_model_query(untimed, 1.0, sphere).distance.tolist() == [pytest.approx(np.sqrt(12) - 1)]


def test_a_scene_names_its_animated_collider_without_a_time():
    points = np.zeros((1, 3)) + 2.0
    spheres = [Sphere(1.0), Sphere(1.0)]
    untimed = SceneQuery.build(points, ["still", "walker", SceneCollider("dancer", time=1.0)])
    with pytest.raises(QueryError) as refused:
        answer_scene_query(untimed, [1.0] * 3, spheres + [Sphere(1.0)], animated=[False, True, True])
    assert str(refused.value) == "model 'walker' is animated: give the time (seconds) to ask it at"
    assert refused.value.code == "missing-time" and spheres[0].calls == []
    answer_scene_query(untimed, [1.0] * 3, spheres + [Sphere(1.0)], animated=[False, False, True])
    answer_scene_query(untimed, [1.0] * 3, spheres + [Sphere(1.0)])
    timed = SceneQuery.build(points, ["still", "walker", SceneCollider("dancer", time=1.0)], time=4.0)
    spheres = [Sphere(1.0), Sphere(1.0), Sphere(1.0)]
    answer_scene_query(timed, [1.0] * 3, spheres, animated=[True, True, True])
    assert [s.calls[-1][3] for s in spheres] == [4.0, 4.0, 1.0]


def test_a_scene_gives_each_point_the_velocity_of_its_nearest_colliders_frame():
    # two unit spheres, at x = -2 spinning about z, at x = +2 drifting up
    spin, drift = (0.0, 0.0, 3.0), (0.0, 0.0, 5.0)
    left, right = pose_matrix(translation=(-2.0, 0.0, 0.0)), pose_matrix(translation=(2.0, 0.0, 0.0))
    points = np.array([[-2.0, 1.5, 0.0], [2.0, 1.5, 0.0], [-0.5, 0.0, 0.0], [3.5, 0.0, 0.0]])
    colliders = [SceneCollider("a", left, pose_velocity=pose_rate(np.eye(3), 1.0, spin=spin)),
                 {"model": "b", "pose": right, "pose_velocity": pose_rate(np.eye(3), 1.0, drift=drift)}]
    result = answer_scene_query(SceneQuery.build(points, colliders, ["velocity"], 0.1), [1.0, 1.0],
                                [Sphere(1.0), Sphere(1.0)])
    expected = [sphere_in_world(points, 1.0, translation=(-2.0, 0.0, 0.0), eps=0.1, spin=spin),
                sphere_in_world(points, 1.0, translation=(2.0, 0.0, 0.0), eps=0.1, drift=drift)]
    assert result.collider.tolist() == [0, 1, 0, 1]
    want = [expected[k]["velocity"][i] for i, k in enumerate([0, 1, 0, 1])]
    np.testing.assert_allclose(result.velocity, want, rtol=0, atol=1e-6)
    assert result.velocity.dtype == np.float32


class SkinnedSphere(Sphere):
    """A :class:`Sphere` as a skinned collider's ``Evaluate``: it also takes the skeleton pose
    and records it (the geometry ignores it)."""

    def __init__(self, radius: float):
        super().__init__(radius)
        self.skeletons = []

    def __call__(self, local, want_gradient, gradient_below, time, skeleton=None):
        self.skeletons.append(skeleton)
        return super().__call__(local, want_gradient, gradient_below, time)


LEG = {"joints": ["hip", "knee"], "parents": [-1, 0], "loop": True,
       "clips": [{"name": "walk", "duration_s": 1.0, "max_surface_speed": 0.5}]}


def test_a_skinned_collider_gets_its_skeleton_pose_and_is_refused_one_that_does_not_fit():
    points = np.zeros((1, 3)) + 2.0
    sphere = SkinnedSphere(1.0)
    query = ModelQuery.build(points, "distance", time=0.5, clip="walk")
    answer_model_query(query, 1.0, sphere, "model 'leg'", skeleton=LEG)
    assert sphere.skeletons == [query.skeleton] and sphere.calls[0][3] == 0.5
    with pytest.raises(QueryError) as refused:
        answer_model_query(ModelQuery.build(points, "distance", clip="walk"), 1.0, sphere,
                           "model 'leg'", skeleton=LEG)
    assert refused.value.code == "missing-time" and len(sphere.calls) == 1
    with pytest.raises(QueryError) as refused:  # a skeleton pose for a model without a skeleton
        answer_model_query(query, 1.0, sphere, "model 'ball'")
    assert refused.value.code == "not-skinned" and len(sphere.calls) == 1


def test_a_scene_checks_and_passes_each_colliders_skeleton_pose():
    points = np.zeros((1, 3)) + 2.0
    scene = SceneQuery.build(points, [SceneCollider("leg", clip="walk"), "ball"], "distance", time=0.5)
    spheres = [SkinnedSphere(1.0), Sphere(2.0)]
    result = answer_scene_query(scene, [1.0, 1.0], spheres, skeletons=[LEG, {}])
    assert spheres[0].skeletons == [SkeletonPose(clip="walk")] and spheres[1].calls[0][3] == 0.5
    assert result.collider.tolist() == [1]
    untimed = SceneQuery.build(points, ["ball", SceneCollider("leg")], "distance")
    with pytest.raises(QueryError) as refused:  # the skinned leg needs a time, the ball none
        answer_scene_query(untimed, [1.0, 1.0], [Sphere(1.0), SkinnedSphere(1.0)], skeletons=[{}, LEG])
    assert str(refused.value).startswith("model 'leg' is skinned: give the time")
    answer_scene_query(untimed, [1.0, 1.0], [Sphere(1.0), SkinnedSphere(1.0)])  # no skeletons: none


def test_a_scene_refuses_per_collider_lists_of_another_length():
    """One entry per collider in every list given with a scene: a short one is a caller's error,
    never silently truncated."""
    points = np.zeros((1, 3)) + 2.0
    scene = SceneQuery.build(points, ["a", "b"], "distance")
    answer_scene_query(scene, [1.0, 1.0], [Sphere(1.0), Sphere(1.0)], [False, False], [{}, {}])
    for args in (([1.0], [Sphere(1.0), Sphere(1.0)]), ([1.0] * 3, [Sphere(1.0), Sphere(1.0)]),
                 ([1.0, 1.0], [Sphere(1.0)]), ([1.0, 1.0], [Sphere(1.0)] * 3),
                 ([1.0, 1.0], [Sphere(1.0), Sphere(1.0)], [False]),
                 ([1.0, 1.0], [Sphere(1.0), Sphere(1.0)], None, [{}])):
        with pytest.raises(ValueError, match="zip"):
            answer_scene_query(scene, *args)
    answer = (np.ones(1), None, None)
    finish_scene(scene, [0.1, 0.1], [answer, answer])
    for eps, answers in (([0.1], [answer, answer]), ([0.1, 0.1], [answer]), ([0.1, 0.1], [answer] * 3),
                         ([0.1], [answer])):
        with pytest.raises(ValueError, match="zip"):
            finish_scene(scene, eps, answers)
