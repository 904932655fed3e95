"""What a query is: fields, points, eps, pose, time, pose velocity, colliders and mode, validated
by ``build`` (the Python API) and ``from_body`` (a decoded wire body) in the same order, each
refusal with its exact message, HTTP status and problem code; ``to_body`` -> wire -> ``from_body``
gives the query back bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from collider_contract import (
    FIELDS,
    GRADIENT_FIELDS,
    IDENTITY,
    ModelQuery,
    QueryError,
    SceneCollider,
    SceneQuery,
    as_pose,
    check_eps,
    check_fields,
    check_points,
    queries,
    wire,
)
from collider_contract.queries import (
    COLLIDER_KEYS,
    DEFAULT_FIELDS,
    MAX_POINTS,
    MAX_TIME_S,
    TRANSPORT_KEYS,
    Placed,
    check_colliders,
    check_number,
    check_pose,
    check_pose_velocity,
    check_time,
    read_deadline_ms,
)

RANGE_ONE_ABOVE = np.nextafter(1e6, np.inf)
ALL_FIELDS = ["distance", "normal", "contact", "collides", "velocity"]


def refusal(call, *args, **kwargs) -> tuple[str, int, str]:
    """``(message, status, code)`` of the QueryError that ``call(*args, **kwargs)`` raises."""
    with pytest.raises(QueryError) as refused:
        call(*args, **kwargs)
    error = refused.value
    assert error.detail == str(error)
    return str(error), error.status, error.code


def moved(tx=0.5, scale=1.0) -> np.ndarray:
    """A 4x4 pose: +90 degrees about z, times ``scale``, then translated by ``tx`` along x."""
    m = np.eye(4)
    m[:3, :3] = scale * np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    m[0, 3] = tx
    return m


SHEAR = np.eye(4)
SHEAR[0, 1] = 0.5
RIGID_MESSAGE = ("pose is not rigid: its 3x3 block is not a rotation times a uniform scale "
                 "(shear or non-uniform scale)")


# -- constants ---------------------------------------------------------------------------------

def test_the_fields_and_limits():
    assert FIELDS == ("distance", "normal", "contact", "collides", "velocity")
    assert GRADIENT_FIELDS == {"normal", "contact", "velocity"} and DEFAULT_FIELDS == ("distance",)
    assert MAX_POINTS == 200_000_000 and TRANSPORT_KEYS == {"deadline_ms"} and MAX_TIME_S == 1e9
    assert COLLIDER_KEYS == ("model", "pose", "time", "pose_velocity", "clip", "joint_transforms",
                             "joint_velocities")


# -- fields ------------------------------------------------------------------------------------

@pytest.mark.parametrize("given, expected", [
    ("normal", ("normal",)),
    (["collides", "distance"], ("distance", "collides")),
    (("contact", "normal", "contact"), ("normal", "contact")),
    (ALL_FIELDS[::-1], tuple(ALL_FIELDS)),
])
def test_fields_come_back_once_each_in_canonical_order(given, expected):
    assert check_fields(given) == expected


def test_any_iterable_of_fields_is_read_once():
    assert check_fields(name for name in ["collides", "normal"]) == ("normal", "collides")


@pytest.mark.parametrize("given, message", [
    (["distance", "speed", "Normal"], ("unknown field(s) ['speed', 'Normal']; valid fields are "
                                      "['distance', 'normal', 'contact', 'collides', 'velocity']")),
    ("normals", ("unknown field(s) ['normals']; valid fields are "
                "['distance', 'normal', 'contact', 'collides', 'velocity']")),
    ([], "no fields asked for; choose from ['distance', 'normal', 'contact', 'collides', 'velocity']"),
    ("", "unknown field(s) ['']; valid fields are ['distance', 'normal', 'contact', 'collides', 'velocity']"),
])
def test_bad_fields_are_refused(given, message):
    assert refusal(check_fields, given) == (message, 422, "unknown-field")


# -- points ------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float_points_pass_as_they_are(dtype):
    points = np.array([[0.0, -1e6, 1e6], [1.5, 2.5, -3.5]], dtype)
    assert check_points(points) is points


@pytest.mark.parametrize("given", [
    [[1, 2, 3]], np.array([[1, 2, 3]], np.int32), np.array([[1, 2, 3]], np.uint8),
    np.array([[1, 2, 3]], np.float16), ((1.0, 2.0, 3.0),),
])
def test_other_numbers_become_float64(given):
    checked = check_points(given)
    assert checked.dtype == np.float64 and checked.tolist() == [[1.0, 2.0, 3.0]]


@pytest.mark.parametrize("given", [[], np.zeros(0, np.int64), np.zeros((0, 3), np.float32)])
def test_no_points_is_an_empty_n_by_3_array(given):
    checked = check_points(given)
    assert checked.shape == (0, 3)
    assert checked.dtype == (np.float32 if getattr(given, "dtype", None) == np.float32 else np.float64)


@pytest.mark.parametrize("given, message", [
    (np.array([["a", "b", "c"]]), "points must be float32, float64 or integers, got <U1"),
    (np.array([[1 + 2j, 0, 0]]), "points must be float32, float64 or integers, got complex128"),
    (np.array([[True, False, True]]), "points must be float32, float64 or integers, got bool"),
    (np.array([[None, 0, 0]]), "points must be float32, float64 or integers, got object"),
    (np.zeros((4, 2)), "points must have shape (n, 3), got [4, 2]"),
    (np.zeros(3), "points must have shape (n, 3), got [3]"),
    (np.zeros((2, 3, 3)), "points must have shape (n, 3), got [2, 3, 3]"),
    (np.zeros((0, 2)), "points must have shape (n, 3), got [0, 2]"),
    (np.float64(1.0), "points must have shape (n, 3), got []"),
    (np.array([[0, 0, 0], [1, np.nan, 0], [np.inf, 0, 0]]),
     "points contain NaN or Inf (first at row 1: [1.0, nan, 0.0])"),
    (np.array([[0, 0, -np.inf]], np.float32), "points contain NaN or Inf (first at row 0: [0.0, 0.0, -inf])"),
    (np.array([[0, 0, 0], [0, 0, 0], [0, RANGE_ONE_ABOVE, 0], [-2e6, 0, 0]]),
     ("points outside the coordinate range +-1e+06 (world units; first at row 2: "
     "[0.0, 1000000.0000000001, 0.0])")),
    (np.array([[-1.5e6, 0, 0]], np.float32), ("points outside the coordinate range +-1e+06 "
                                             "(world units; first at row 0: [-1500000.0, 0.0, 0.0])")),
    ([[2 * 10 ** 6, 0, 0]], ("points outside the coordinate range +-1e+06 (world units; first at "
                            "row 0: [2000000.0, 0.0, 0.0])")),
])
def test_bad_points_are_refused_naming_the_first_bad_row(given, message):
    assert refusal(check_points, given) == (message, 422, "bad-points")


def test_ragged_points_are_refused():
    message, status, code = refusal(check_points, [[0.0, 0.0, 0.0], [1.0, 2.0]])
    assert message.startswith("points must be an (n, 3) array of numbers: ")
    assert message.removeprefix("points must be an (n, 3) array of numbers: ") and "\n" not in message
    assert (status, code) == (422, "bad-points")


def test_the_coordinate_range_itself_is_inside():
    points = np.array([[1e6, -1e6, 0.0], [-1e6, 1e6, 1e6]])
    assert check_points(points) is points


def test_too_many_points_is_a_413_before_the_values_are_read():
    assert MAX_POINTS == 200_000_000  # (a broadcast view: the rows cost no memory)
    points = np.broadcast_to(np.array([np.nan, 0.0, 0.0]), (MAX_POINTS + 1, 3))
    assert refusal(check_points, points) == ("too many points in one call: 200000001 > 200000000",
                                             413, "too-many-points")


def test_max_points_itself_is_allowed(monkeypatch):
    monkeypatch.setattr(queries, "MAX_POINTS", 4)
    assert check_points(np.zeros((4, 3))).shape == (4, 3)
    assert refusal(check_points, np.zeros((5, 3))) == ("too many points in one call: 5 > 4",
                                                       413, "too-many-points")
    # the size is checked before the shape's values, after the shape
    assert refusal(check_points, np.zeros((5, 2)))[2] == "bad-points"
    assert refusal(check_points, np.full((5, 3), np.nan))[2] == "too-many-points"


# -- numbers, eps and the deadline -------------------------------------------------------------

@pytest.mark.parametrize("given, expected", [
    (0, 0.0), (0.0, 0.0), (-0.0, 0.0), (1e6, 1e6), (3, 3.0), (np.float32(0.25), 0.25),
    (np.int64(7), 7.0), (np.float64(1e-3), 1e-3), (5e-324, 5e-324),
])
def test_eps_in_the_range_is_a_float(given, expected):
    checked = check_eps(given)
    assert type(checked) is float and checked == expected


def test_no_eps_is_the_default():
    assert check_eps(None) is None


@pytest.mark.parametrize("given, message, code", [
    (RANGE_ONE_ABOVE, "eps=1000000.0000000001 is outside [0, 1e+06] (world units)", "eps-out-of-range"),
    (1000001, "eps=1000001.0 is outside [0, 1e+06] (world units)", "eps-out-of-range"),
    (-5e-324, "eps=-5e-324 is outside [0, 1e+06] (world units)", "eps-out-of-range"),
    (-1e-3, "eps=-0.001 is outside [0, 1e+06] (world units)", "eps-out-of-range"),
    (np.float32(-1), "eps=-1.0 is outside [0, 1e+06] (world units)", "eps-out-of-range"),
    (float("nan"), "eps must be a finite number, got nan", "bad-eps"),
    (float("-inf"), "eps must be a finite number, got -inf", "bad-eps"),
    (np.float64("inf"), "eps must be a finite number, got np.float64(inf)", "bad-eps"),
    (True, "eps must be a finite number, got True", "bad-eps"),
    (False, "eps must be a finite number, got False", "bad-eps"),
    (np.bool_(True), "eps must be a finite number, got np.True_", "bad-eps"),
    ("0.1", "eps must be a finite number, got '0.1'", "bad-eps"),
    ([0.1], "eps must be a finite number, got [0.1]", "bad-eps"),
    (10 ** 400, "eps must be a finite number, got " + "1" + "0" * 59, "bad-eps"),
    (-(10 ** 400), "eps must be a finite number, got -" + "1" + "0" * 58, "bad-eps"),
])
def test_bad_eps_is_refused_with_the_value_as_given(given, message, code):
    assert refusal(check_eps, given) == (message, 422, code)


def test_check_number_names_its_field_and_code():
    assert check_number(2, "deadline_ms", positive=True) == 2.0
    assert refusal(check_number, 0, "deadline_ms", positive=True) == (
        "deadline_ms must be > 0, got 0", 422, "bad-deadline-ms")
    assert refusal(check_number, -0.5, "deadline_ms", positive=True) == (
        "deadline_ms must be > 0, got -0.5", 422, "bad-deadline-ms")
    assert check_number(-0.5, "offset") == -0.5 and check_number(0, "offset") == 0.0
    assert refusal(check_number, "x", "the_time_ms", code="bad-time") == (
        "the_time_ms must be a finite number, got 'x'", 422, "bad-time")
    assert refusal(check_number, 0, "t", positive=True, code="bad-time")[2] == "bad-time"
    assert refusal(check_number, "a" * 100, "x")[0] == "x must be a finite number, got '" + "a" * 59


@pytest.mark.parametrize("body, expected", [({}, None), ({"deadline_ms": 250}, 250.0),
                                            ({"deadline_ms": 0.5}, 0.5)])
def test_the_deadline_is_an_optional_positive_number(body, expected):
    assert read_deadline_ms(body) == expected


@pytest.mark.parametrize("value, message", [
    (None, "deadline_ms must not be null (leave it out for its default)"),
    (0, "deadline_ms must be > 0, got 0"),
    (-1, "deadline_ms must be > 0, got -1"),
    (True, "deadline_ms must be a finite number, got True"),
    ("5", "deadline_ms must be a finite number, got '5'"),
])
def test_a_bad_deadline_is_refused(value, message):
    assert refusal(read_deadline_ms, {"deadline_ms": value}) == (message, 422, "bad-deadline-ms")


# -- poses and colliders -----------------------------------------------------------------------

def test_a_pose_refusal_names_where_it_was_given():
    assert check_pose(None) is IDENTITY
    assert refusal(check_pose, SHEAR) == (RIGID_MESSAGE, 422, "bad-pose")
    assert refusal(check_pose, SHEAR, "colliders[2].pose") == (
        "colliders[2].pose: " + RIGID_MESSAGE, 422, "bad-pose")
    assert refusal(check_pose, np.eye(3), "colliders[0].pose")[0] == (
        "colliders[0].pose: pose must be a 4x4 matrix, got shape (3, 3)")
    pose = as_pose(moved())
    assert check_pose(pose, "x") is pose


def test_every_form_of_collider_gives_a_name_and_a_validated_pose():
    given = [SceneCollider("a"), SceneCollider("b", moved(2.0)), "c", {"model": "d"},
             {"model": "e", "pose": moved(3.0)}, ("f", None), ["g", moved(4.0)]]
    checked = check_colliders(given)
    assert all(isinstance(placed, Placed) for placed in checked)
    assert [placed.model for placed in checked] == list("abcdefg")
    assert [placed.pose.translation[0] for placed in checked] == [0.0, 2.0, 0.0, 0.0, 3.0, 0.0, 4.0]
    assert [placed.pose is IDENTITY for placed in checked] == [True, False, True, True, False, True, False]
    assert [(placed.time, placed.pose_velocity) for placed in checked] == [(None, None)] * 7
    assert check_colliders(("a",)) == (Placed("a", IDENTITY, None, None),)


COLLIDER_FORM = ('{"model": name} with optional "pose", "time", "pose_velocity", "clip", "joint_transforms", '
                 '"joint_velocities"')
LIST_FORM = f"colliders must be a non-empty list of {COLLIDER_FORM}, got "


@pytest.mark.parametrize("given, got", [
    ([], "[]"), ((), "()"), ("sphere", "'sphere'"), (b"sphere", "b'sphere'"),
    ({"model": "sphere"}, "{'model': 'sphere'}"), (5, "5"), (None, "None"),
    (np.array(["a"]), "array(['a'], dtype='<U1')"), (iter, "<built-in function iter>"),
    ("x" * 300, "'" + "x" * 199),
])
def test_colliders_must_be_a_non_empty_list(given, got):
    assert refusal(check_colliders, given) == (LIST_FORM + got, 422, "bad-colliders")


ITEM_FORM = f"must be {COLLIDER_FORM}, got "


@pytest.mark.parametrize("item, got", [
    ({"model": "a", "extra": 1}, "a map with keys ['extra', 'model']"),
    ({"pose": None}, "a map with keys ['pose']"),
    ({"model": 3}, "a map with keys ['model']"),
    ({1: "a"}, "a map with keys ['1']"),
    (("a",), "('a',)"), (("a", None, None), "('a', None, None)"), ((3, None), "(3, None)"),
    (SceneCollider(None), "SceneCollider(model=None, pose=None, time=None, pose_velocit"),  # 60
    (SceneCollider(3, time=1.0), "SceneCollider(model=3, pose=None, time=1.0, pose_velocity=No"),
    ({"model": "a", "velocity": 1}, "a map with keys ['model', 'velocity']"), (7, "7"),
    ("y" * 100 + "z", None),
])
def test_a_bad_collider_is_refused_naming_its_index(item, got):
    if got is None:  # a name is always accepted
        assert check_colliders(["a", item])[1][0] == item
        return
    assert refusal(check_colliders, ["a", item]) == (f"colliders[1] {ITEM_FORM}{got}", 422,
                                                     "bad-colliders")


def test_a_long_bad_collider_is_cut_at_60_characters():
    item = ("m" * 100, None, None)
    assert refusal(check_colliders, [item])[0] == f"colliders[0] {ITEM_FORM}('" + "m" * 58


def test_a_colliders_bad_pose_is_refused_naming_it():
    assert refusal(check_colliders, ["a", "b", ("c", SHEAR)]) == (
        "colliders[2].pose: " + RIGID_MESSAGE, 422, "bad-pose")


# -- ModelQuery --------------------------------------------------------------------------------

def test_build_defaults():
    query = ModelQuery.build([[1, 2, 3]])
    assert query.fields == ("distance",) and query.pose is IDENTITY
    assert query.eps is None and query.only_colliding is False
    assert query.points.dtype == np.float64 and query.points.tolist() == [[1.0, 2.0, 3.0]]


def test_build_keeps_what_it_validated():
    points = np.zeros((2, 3), np.float32)
    query = ModelQuery.build(points, ["collides", "normal"], moved(), 1, only_colliding=1)
    assert query.points is points and query.fields == ("normal", "collides")
    assert query.pose.source.tolist() == moved().tolist()
    assert query.eps == 1.0 and type(query.eps) is float
    assert query.only_colliding is True
    assert ModelQuery.build(points, only_colliding=0).only_colliding is False


@pytest.mark.parametrize("fields, want", [
    (["distance"], False), (["collides"], False), (["distance", "collides"], False),
    (["normal"], True), (["contact"], True), (["distance", "contact"], True), (ALL_FIELDS, True)])
def test_the_gradient_is_wanted_for_normal_or_contact(fields, want):
    assert ModelQuery.build(np.zeros((1, 3)), fields).want_gradient is want
    scene = SceneQuery.build(np.zeros((1, 3)), ["a"], fields)
    assert scene.want_gradient is want and scene.of_collider(0).want_gradient is want


def test_build_checks_fields_then_points_then_pose_then_eps():
    bad = {"points": np.array([[np.nan, 0, 0]]), "fields": ["speed"], "pose": SHEAR, "eps": -1}
    assert refusal(ModelQuery.build, **bad)[2] == "unknown-field"
    assert refusal(ModelQuery.build, **{**bad, "fields": "distance"})[2] == "bad-points"
    assert refusal(ModelQuery.build, **{**bad, "fields": "distance", "points": [[0, 0, 0]]})[2] == "bad-pose"
    assert refusal(ModelQuery.build, np.zeros((1, 3)), "distance", None, -1)[2] == "eps-out-of-range"


def test_to_body_leaves_the_defaults_out():
    points = np.zeros((1, 3), np.float32)
    body = ModelQuery.build(points).to_body()
    assert body.keys() == {"points", "fields"}
    assert body["points"] is points and body["fields"] == ["distance"]
    # a given identity matrix travels: the caller gave it
    body = ModelQuery.build(points, ["contact", "normal"], np.eye(4), 0.0, True).to_body()
    assert body.keys() == {"points", "fields", "pose", "eps", "only_colliding"}
    assert body["fields"] == ["normal", "contact"] and body["pose"].tolist() == np.eye(4).tolist()
    assert body["eps"] == 0.0 and body["only_colliding"] is True


@pytest.mark.parametrize("media", [wire.MSGPACK, wire.JSON])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_model_query_round_trip_is_bit_identical(media, dtype):
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    m = np.eye(4)
    m[:3, :3] = (q if np.linalg.det(q) > 0 else -q) * 1.7
    m[:3, 3] = [1e5 / 3, -1.0 / 7, 2.0 ** -30]
    points = rng.uniform(-1e3, 1e3, (5, 3)).astype(dtype)
    sent = ModelQuery.build(points, ["collides", "contact"], m, 1e-3 / 3, True)
    got = ModelQuery.from_body(wire.loads(wire.dumps(sent.to_body(), media), media))
    # JSON numbers are float64: float32 points come back as the same values in float64
    assert got.points.dtype == (dtype if media == wire.MSGPACK else np.float64)
    assert got.points.tolist() == sent.points.tolist()
    assert got.fields == sent.fields and got.eps == sent.eps and got.only_colliding is True
    assert got.pose.source.tobytes() == m.tobytes()
    assert got.pose.rotation.tobytes() == sent.pose.rotation.tobytes()
    assert got.pose.translation.tobytes() == sent.pose.translation.tobytes()
    assert got.pose.scale == sent.pose.scale


def test_a_default_query_round_trips_to_the_defaults():
    got = ModelQuery.from_body(wire.loads(wire.dumps(ModelQuery.build([[1, 2, 3]]).to_body())))
    assert (got.fields, got.eps, got.only_colliding) == (("distance",), None, False)
    assert got.pose is IDENTITY and got.points.tolist() == [[1.0, 2.0, 3.0]]


POINTS = wire.encode_array(np.zeros((2, 3)))


@pytest.mark.parametrize("body, expected", [
    ({"points": [[0, 0, 0]]}, ("distance",)),
    ({"points": POINTS, "fields": ["normal", "distance"]}, ("distance", "normal")),
    ({"points": POINTS, "deadline_ms": 5}, ("distance",)),
])
def test_from_body_reads_fields_or_their_default(body, expected):
    assert ModelQuery.from_body(body).fields == expected


def test_from_body_reads_eps_pose_and_mode():
    query = ModelQuery.from_body({"points": POINTS, "eps": 2, "pose": wire.encode_array(moved(1.0)),
                                  "only_colliding": False})
    assert query.eps == 2.0 and query.only_colliding is False
    assert query.pose.translation.tolist() == [1.0, 0.0, 0.0]
    assert ModelQuery.from_body({"points": POINTS, "only_colliding": True}).only_colliding is True
    json_pose = ModelQuery.from_body({"points": POINTS, "pose": moved(1.0).tolist()}).pose
    assert json_pose.source.tolist() == moved(1.0).tolist()


@pytest.mark.parametrize("body, message, status, code", [
    ({"points": POINTS, "pose_": 1, "Eps": 2},
     ("unknown key(s) ['Eps', 'pose_']; valid keys are ['clip', 'deadline_ms', 'eps', 'fields', "
     "'joint_transforms', 'joint_velocities', 'only_colliding', 'points', 'pose', 'pose_velocity', "
     "'time']"), 422,
     "unknown-key"),
    ({"fields": ["distance"]}, "the body has no 'points'", 422, "missing-points"),
    ({"colliders": []}, ("unknown key(s) ['colliders']; valid keys are ['clip', 'deadline_ms', 'eps', "
                        "'fields', 'joint_transforms', 'joint_velocities', 'only_colliding', 'points', "
                        "'pose', 'pose_velocity', 'time']"), 422,
     "unknown-key"),
    # null is not absent
    ({"points": POINTS, "fields": None}, "fields must not be null (leave it out for its default)",
     422, "bad-fields"),
    ({"points": POINTS, "eps": None}, "eps must not be null (leave it out for its default)", 422, "bad-eps"),
    ({"points": POINTS, "only_colliding": None},
     "only_colliding must not be null (leave it out for its default)", 422, "bad-only-colliding"),
    ({"points": POINTS, "pose": None},
     "pose must be a 4x4 matrix, got null (leave it out for the identity)", 422, "bad-pose"),
    ({"points": None}, "points: expected an array (msgpack map or JSON list), got NoneType", 422,
     "bad-points"),
    # the wire's types
    ({"points": POINTS, "fields": "distance"}, "fields must be a list of strings, got 'distance'",
     422, "bad-fields"),
    ({"points": POINTS, "fields": ["distance", 1]}, "fields must be a list of strings, got ['distance', 1]",
     422, "bad-fields"),
    ({"points": POINTS, "fields": {"distance": 1}}, ("fields must be a list of strings, got "
                                                    "{'distance': 1}"), 422, "bad-fields"),
    ({"points": POINTS, "fields": []}, ("no fields asked for; choose from ['distance', 'normal', "
                                       "'contact', 'collides', 'velocity']"), 422, "unknown-field"),
    ({"points": POINTS, "only_colliding": 1}, "only_colliding must be true or false, got 1", 422,
     "bad-only-colliding"),
    ({"points": POINTS, "only_colliding": "true"}, "only_colliding must be true or false, got 'true'",
     422, "bad-only-colliding"),
    ({"points": POINTS, "eps": True}, "eps must be a finite number, got True", 422, "bad-eps"),
    ({"points": POINTS, "eps": 10 ** 400}, "eps must be a finite number, got 1" + "0" * 59, 422, "bad-eps"),
    ({"points": POINTS, "eps": -1}, "eps=-1.0 is outside [0, 1e+06] (world units)", 422, "eps-out-of-range"),
    ({"points": POINTS, "pose": wire.encode_array(SHEAR)}, RIGID_MESSAGE, 422, "bad-pose"),
    ({"points": POINTS, "pose": [[1, 0, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
     RIGID_MESSAGE, 422, "bad-pose"),
    ({"points": POINTS, "pose": wire.encode_array(np.eye(4, dtype=bool))},
     "pose: must hold numbers, got bool", 422, "bad-pose"),
    ({"points": POINTS, "pose": [[True, False, False, False]] * 4}, "pose: must hold numbers, got bool",
     422, "bad-pose"),
    ({"points": POINTS, "pose": {"dtype": "<f8", "shape": [4, 4], "data": b""}},
     "pose: data has 0 bytes but dtype <f8 and shape [4, 4] need 128", 422, "bad-pose"),
    ({"points": POINTS, "pose": "eye"}, "pose: expected an array (msgpack map or JSON list), got str",
     422, "bad-pose"),
    ({"points": POINTS, "pose": wire.encode_array(np.eye(3))},
     "pose must be a 4x4 matrix, got shape (3, 3)", 422, "bad-pose"),
])
def test_a_bad_body_is_refused_as_the_service_answers_it(body, message, status, code):
    assert refusal(ModelQuery.from_body, body) == (message, status, code)


@pytest.mark.parametrize("points, message", [
    ({"dtype": "<i4", "shape": [1, 3], "data": bytes(12)}, "points must be float32 or float64, got int32"),
    ({"dtype": "<i8", "shape": [1, 3], "data": bytes(24)}, "points must be float32 or float64, got int64"),
    ({"dtype": "|b1", "shape": [1, 3], "data": bytes(3)}, "points must be float32 or float64, got bool"),
    ({"dtype": "|b1", "shape": [0, 3], "data": b""}, "points must be float32 or float64, got bool"),
    ({"dtype": "|b1", "shape": [0], "data": b""}, "points must be float32 or float64, got bool"),
    ([[True], [False]], "points must be float32 or float64, got bool"),
    ([[True, False, True]], "points must be float32 or float64, got bool"),
    ([[0, True, 0]], "points: must hold numbers only, got a boolean among them"),
    ({"dtype": "<f8", "shape": [3], "data": bytes(24)}, "points must have shape (n, 3), got [3]"),
    ({"dtype": "<f4", "shape": [1, 3], "data": b""}, ("points: data has 0 bytes but dtype <f4 and "
                                                     "shape [1, 3] need 12")),
    ([[0.0, 0.0, 1e300]], ("points outside the coordinate range +-1e+06 (world units; first at row 0: "
                          "[0.0, 0.0, 1e+300])")),
    ([[0, 0, 0], [0, 0]], "points: nested lists are ragged"),
])
def test_bad_wire_points_are_refused(points, message):
    assert refusal(ModelQuery.from_body, {"points": points}) == (message, 422, "bad-points")


@pytest.mark.parametrize("points, shape, dtype", [
    ([], (0, 3), np.float64),
    ([[1, 2, 3]], (1, 3), np.float64),
    ({"dtype": "<i4", "shape": [0, 3], "data": b""}, (0, 3), np.float64),
    ({"dtype": "<f4", "shape": [0], "data": b""}, (0, 3), np.float64),
    ({"dtype": "<f4", "shape": [2, 3], "data": bytes(24)}, (2, 3), np.float32),
])
def test_wire_points_are_float32_or_float64(points, shape, dtype):
    query = ModelQuery.from_body({"points": points})
    assert query.points.shape == shape and query.points.dtype == dtype


def test_more_than_max_points_in_a_body_is_a_413():
    body = {"points": wire.encode_array(np.zeros((5, 3)))}
    assert ModelQuery.from_body(body, max_points=5).points.shape == (5, 3)
    assert refusal(ModelQuery.from_body, body, max_points=4) == (
        "5 points exceed max_request_points=4", 413, "too-many-points")
    # a body of the wrong shape is a shape error, whatever its size
    assert refusal(ModelQuery.from_body, {"points": np.zeros((5, 2)).tolist()}, max_points=4) == (
        "points must have shape (n, 3), got [5, 2]", 422, "bad-points")
    assert refusal(ModelQuery.from_body, {"points": np.zeros((5, 3, 1)).tolist()}, max_points=4)[1] == 422
    # the size before the values
    nan = {"points": wire.encode_array(np.full((5, 3), np.nan))}
    assert refusal(ModelQuery.from_body, nan, max_points=4)[1] == 413
    assert refusal(ModelQuery.from_body, nan)[2] == "bad-points"


def test_from_body_checks_the_keys_then_as_build_then_the_mode():
    assert refusal(ModelQuery.from_body, {"speed": 1, "points": None})[2] == "unknown-key"
    body = {"points": [[np.nan, 0, 0]], "fields": ["speed"], "pose": None, "eps": -1,
            "only_colliding": None, "time": None, "pose_velocity": None}
    for key, good, code in (("fields", ["distance"], "unknown-field"), ("points", POINTS, "bad-points"),
                            ("pose", np.eye(4).tolist(), "bad-pose"), ("eps", 0, "eps-out-of-range"),
                            ("time", 0, "bad-time"), ("pose_velocity", np.zeros((4, 4)).tolist(),
                                                      "bad-pose-velocity"),
                            ("only_colliding", True, "bad-only-colliding")):
        assert refusal(ModelQuery.from_body, body)[2] == code
        body[key] = good
    assert ModelQuery.from_body(body).only_colliding is True


BAD_RATE = [[0, 0, 0, 0]] * 3 + [[0, 0, 0, 1]]  # a pose velocity whose bottom row is not zero

#: Inputs with several errors each (JSON forms): points, fields, pose, eps, time, pose velocity.
SEVERAL_ERRORS = [
    ([[np.nan, 0, 0]], ["speed"], SHEAR.tolist(), -1, True, BAD_RATE),
    ([[np.nan, 0, 0]], ["normal"], SHEAR.tolist(), -1, True, BAD_RATE),
    ([[0, 0]], [], [[1, 0], [0, 1]], float("inf"), "now", [[1]]),
    ([[0, 0, 2e6]], ["contact"], np.full((4, 4), np.nan).tolist(), 2e6, 2e9, BAD_RATE),
    ([[0, 0, 0]], ["contact"], np.diag([1.0, 1.0, 1.0, 2.0]).tolist(), True, 1.0, None),
    ([[0, 0, 0]], ["collides"], None, -1e-9, None, BAD_RATE),
    ([[0, 0, 0]], ["velocity"], None, 0.5, -2e9, BAD_RATE),
    ([[0, 0, 0]], ["velocity"], None, None, 0.5, BAD_RATE),
    ([[0, 0, 0]], ["velocity"], None, None, None, [[np.inf] * 4] * 4),
]


@pytest.mark.parametrize("points, fields, pose, eps, time, rate", SEVERAL_ERRORS)
def test_build_and_from_body_refuse_the_same_input_alike(points, fields, pose, eps, time, rate):
    """The Python API (embedded) and a wire body (the service) give the same first refusal."""
    body = {"points": points, "fields": fields, "eps": eps, "pose": pose, "time": time,
            "pose_velocity": rate}
    body = {key: value for key, value in body.items() if value is not None}
    assert refusal(ModelQuery.from_body, body) == refusal(ModelQuery.build, points, fields, pose, eps,
                                                          False, time, rate)
    item = {"model": "b", "pose": pose, "time": time, "pose_velocity": rate}
    colliders = [{"model": "a"}, {key: value for key, value in item.items() if value is not None}]
    scene = {"points": points, "fields": fields, "eps": eps, "colliders": colliders}
    scene = {key: value for key, value in scene.items() if value is not None}
    assert refusal(SceneQuery.from_body, scene) == refusal(SceneQuery.build, points, colliders, fields, eps)
    if time is not None:  # a scene-wide time is checked before the colliders
        scene["time"] = time
        assert refusal(SceneQuery.from_body, scene) == refusal(SceneQuery.build, points, colliders,
                                                               fields, eps, time=time)
    for bad in ([], [{"model": 1}], [{"model": "a", "extra": 0}]):
        scene["colliders"] = bad
        assert refusal(SceneQuery.from_body, scene) == refusal(SceneQuery.build, points, bad, fields, eps,
                                                               time=scene.get("time"))


# -- SceneQuery --------------------------------------------------------------------------------

def test_scene_build_defaults_and_order_of_checks():
    scene = SceneQuery.build([[0, 0, 1]], ["a", ("b", moved())])
    assert scene.fields == ("distance",) and scene.eps is None and scene.only_colliding is False
    assert [placed.model for placed in scene.colliders] == ["a", "b"]
    assert scene.colliders[0].pose is IDENTITY
    assert SceneQuery.build([[0, 0, 1]], ["a"], "normal", 0, 1).only_colliding is True
    bad = {"points": [[np.nan, 0, 0]], "colliders": [], "fields": "speed", "eps": -1, "time": "t"}
    for key, good, code in (("fields", "normal", "unknown-field"), ("time", 1.0, "bad-time"),
                            ("colliders", ["a"], "bad-colliders"), ("points", [[0, 0, 0]], "bad-points"),
                            ("eps", 0.0, "eps-out-of-range")):
        assert refusal(SceneQuery.build, **bad)[2] == code
        bad[key] = good
    assert SceneQuery.build(**bad).colliders[0].time == 1.0


def test_of_collider_is_the_scene_query_under_that_colliders_pose():
    points = np.zeros((3, 3), np.float32)
    scene = SceneQuery.build(points, ["a", ("b", moved(7.0))], ["contact"], 0.25, True)
    part = scene.of_collider(1)
    assert isinstance(part, ModelQuery) and part.points is points
    assert part.fields == ("contact",) and part.eps == 0.25 and part.only_colliding is True
    assert part.pose is scene.colliders[1][1] and part.pose.translation[0] == 7.0
    assert scene.of_collider(0).pose is IDENTITY


def test_scene_to_body_sends_poses_given_as_nested_lists():
    points = np.zeros((1, 3))
    body = SceneQuery.build(points, ["a", ("b", moved(7.0)), ("c", np.eye(4))]).to_body()
    assert body.keys() == {"points", "fields", "colliders"} and body["points"] is points
    assert body["colliders"] == [{"model": "a"}, {"model": "b", "pose": moved(7.0).tolist()},
                                 {"model": "c", "pose": np.eye(4).tolist()}]
    body = SceneQuery.build(points, ["a"], "collides", 0.5, True).to_body()
    assert (body["fields"], body["eps"], body["only_colliding"]) == (["collides"], 0.5, True)


@pytest.mark.parametrize("media", [wire.MSGPACK, wire.JSON])
def test_scene_round_trip_is_bit_identical(media):
    a = moved(1.0 / 3.0, scale=0.3)
    points = np.random.default_rng(4).normal(size=(4, 3))
    sent = SceneQuery.build(points, [("a", a), "b"], ALL_FIELDS, 0.1, True)
    got = SceneQuery.from_body(wire.loads(wire.dumps(sent.to_body(), media), media))
    assert got.points.tobytes() == points.tobytes() and got.fields == tuple(ALL_FIELDS)
    assert (got.eps, got.only_colliding) == (0.1, True)
    assert [placed.model for placed in got.colliders] == ["a", "b"]
    assert got.colliders[0][1].source.tobytes() == a.tobytes()
    assert got.colliders[0][1].rotation.tobytes() == sent.colliders[0][1].rotation.tobytes()
    assert got.colliders[0][1].scale == sent.colliders[0][1].scale
    assert got.colliders[1][1] is IDENTITY


def test_scene_from_body_reads_defaults():
    got = SceneQuery.from_body({"points": POINTS, "colliders": [{"model": "a"}], "deadline_ms": 3})
    assert (got.fields, got.eps, got.only_colliding) == (("distance",), None, False)
    assert got.colliders == (Placed("a", IDENTITY, None, None),)


@pytest.mark.parametrize("body, message, code", [
    ({"points": POINTS, "colliders": [{"model": "a"}], "pose": None},
     ("unknown key(s) ['pose']; valid keys are ['colliders', 'deadline_ms', 'eps', 'fields', "
     "'only_colliding', 'points', 'time']"), "unknown-key"),
    ({"colliders": [{"model": "a"}]}, "the body has no 'points'", "missing-points"),
    ({"points": POINTS}, "the body has no 'colliders'", "missing-colliders"),
    ({"points": POINTS, "colliders": []}, LIST_FORM + "[]", "bad-colliders"),
    ({"points": POINTS, "colliders": "a"}, LIST_FORM + "'a'", "bad-colliders"),
    ({"points": POINTS, "colliders": {"model": "a"}}, LIST_FORM + "{'model': 'a'}", "bad-colliders"),
    ({"points": POINTS, "colliders": None}, LIST_FORM + "None", "bad-colliders"),
    ({"points": POINTS, "colliders": ["a"]}, f"colliders[0] {ITEM_FORM}'a'", "bad-colliders"),
    ({"points": POINTS, "colliders": [{"model": "a"}, ["b", None]]},
     f"colliders[1] {ITEM_FORM}['b', None]", "bad-colliders"),
    ({"points": POINTS, "colliders": [{"model": 1}]},
     f"colliders[0] {ITEM_FORM}a map with keys ['model']", "bad-colliders"),
    ({"points": POINTS, "colliders": [{"pose": [[1]]}]},
     f"colliders[0] {ITEM_FORM}a map with keys ['pose']", "bad-colliders"),
    ({"points": POINTS, "colliders": [{"model": "a", "extra": 1}]},
     f"colliders[0] {ITEM_FORM}a map with keys ['extra', 'model']", "bad-colliders"),
    ({"points": POINTS, "colliders": [{"model": "a"}, {"model": "b", "pose": None}]},
     "colliders[1].pose must be a 4x4 matrix, got null (leave it out for the identity)", "bad-pose"),
    ({"points": POINTS, "colliders": [{"model": "a", "pose": SHEAR.tolist()}]},
     "colliders[0].pose: " + RIGID_MESSAGE, "bad-pose"),
    ({"points": POINTS, "colliders": [{"model": "a", "pose": "eye"}]},
     "colliders[0].pose: expected an array (msgpack map or JSON list), got str", "bad-pose"),
    ({"points": POINTS, "colliders": [{"model": "a", "pose": [[True] * 4] * 4}]},
     "colliders[0].pose: must hold numbers, got bool", "bad-pose"),
    ({"points": POINTS, "colliders": [{"model": "a"}], "fields": None},
     "fields must not be null (leave it out for its default)", "bad-fields"),
    ({"points": POINTS, "colliders": [{"model": "a"}], "eps": None},
     "eps must not be null (leave it out for its default)", "bad-eps"),
    ({"points": POINTS, "colliders": [{"model": "a"}], "only_colliding": 0},
     "only_colliding must be true or false, got 0", "bad-only-colliding"),
])
def test_a_bad_scene_body_is_refused(body, message, code):
    assert refusal(SceneQuery.from_body, body) == (message, 422, code)


def test_more_colliders_than_allowed_is_a_413_checked_before_each_collider():
    three = {"points": POINTS, "colliders": [{"model": "a"}, {"model": "b"}, "c"]}
    assert refusal(SceneQuery.from_body, three, max_colliders=2) == (
        "3 colliders exceed max_scene_colliders=2", 413, "too-many-colliders")
    assert refusal(SceneQuery.from_body, three, max_colliders=3)[2] == "bad-colliders"
    assert refusal(SceneQuery.from_body, three)[2] == "bad-colliders"
    two = {"points": POINTS, "colliders": [{"model": "a"}, {"model": "b"}]}
    assert len(SceneQuery.from_body(two, max_colliders=2).colliders) == 2
    assert refusal(SceneQuery.from_body, {"points": POINTS, "colliders": []}, max_colliders=0)[2] == (
        "bad-colliders")
    many = {"points": [[0, 0, 0]] * 5, "colliders": [{"model": "a"}]}
    assert refusal(SceneQuery.from_body, many, max_points=4) == (
        "5 points exceed max_request_points=4", 413, "too-many-points")


def test_scene_from_body_checks_the_keys_then_as_build_then_the_mode():
    body = {"points": [[np.nan, 0, 0]], "colliders": [{"model": 1}], "fields": ["speed"], "eps": -1,
            "only_colliding": None, "pose": None}
    assert refusal(SceneQuery.from_body, body)[2] == "unknown-key"
    del body["pose"]
    body["time"] = None
    for key, good, code in (("fields", ["normal"], "unknown-field"), ("time", 2.0, "bad-time"),
                            ("colliders", [{"model": "a"}], "bad-colliders"),
                            ("points", POINTS, "bad-points"), ("eps", 0, "eps-out-of-range"),
                            ("only_colliding", False, "bad-only-colliding")):
        assert refusal(SceneQuery.from_body, body)[2] == code
        body[key] = good
    assert SceneQuery.from_body(body).colliders == (Placed("a", IDENTITY, 2.0, None),)


# -- time and pose velocity --------------------------------------------------------------------

@pytest.mark.parametrize("given, expected", [(0, 0.0), (-0.0, 0.0), (2.5, 2.5), (1e9, 1e9), (-1e9, -1e9),
                                             (np.float32(0.5), 0.5), (np.int32(-3), -3.0)])
def test_a_time_within_a_billion_seconds_is_a_float(given, expected):
    checked = check_time(given)
    assert type(checked) is float and checked == expected


@pytest.mark.parametrize("given, where, message", [
    (np.nextafter(1e9, np.inf), "time", "time=1000000000.0000001 is outside +-1e+09 s"),
    (-2e9, "time", "time=-2000000000.0 is outside +-1e+09 s"),
    (-2e9, "colliders[3].time", "colliders[3].time=-2000000000.0 is outside +-1e+09 s"),
    (True, "time", "time must be a finite number, got True"),
    (float("nan"), "time", "time must be a finite number, got nan"),
    ("1.5", "colliders[0].time", "colliders[0].time must be a finite number, got '1.5'"),
    (10 ** 400, "time", "time must be a finite number, got 1" + "0" * 59),
])
def test_a_bad_time_is_refused(given, where, message):
    assert refusal(check_time, given, where) == (message, 422, "bad-time")


def test_no_time_is_a_static_query():
    assert check_time(None) is None and check_time(None, "colliders[0].time") is None


def rate(spin_z=0.0, drift=(0.0, 0.0, 0.0)) -> list:
    """A pose velocity (4x4 nested lists): turning about z at ``spin_z``, moving at ``drift``."""
    m = [[0.0, -spin_z, 0.0, drift[0]], [spin_z, 0.0, 0.0, drift[1]], [0.0, 0.0, 0.0, drift[2]],
         [0.0, 0.0, 0.0, 0.0]]
    return m


def test_a_pose_velocity_is_a_float64_copy():
    assert check_pose_velocity(None) is None
    given = np.array(rate(2.0, (1.0, 0.0, -1.0)))
    checked = check_pose_velocity(given)
    assert checked.dtype == np.float64 and checked.tolist() == rate(2.0, (1.0, 0.0, -1.0))
    given[0, 3] = 9.0
    assert checked[0, 3] == 1.0
    ints = check_pose_velocity([[0, 1, 0, 5], [-1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])
    assert ints.dtype == np.float64 and ints[0, 3] == 5.0
    edge = np.zeros((4, 4))
    edge[:3] = 1e6
    assert check_pose_velocity(-edge)[0, 0] == -1e6


def _rate_with(row, col, value):
    m = np.zeros((4, 4))
    m[row, col] = value
    return m


@pytest.mark.parametrize("given, message", [
    (np.zeros((3, 3)), "pose_velocity must be a 4x4 matrix, got shape (3, 3)"),
    ([[0.0] * 4] * 3, "pose_velocity must be a 4x4 matrix, got shape (3, 4)"),
    (np.full((3, 4), np.nan), "pose_velocity must be a 4x4 matrix, got shape (3, 4)"),
    (_rate_with(1, 2, np.nan), "pose_velocity must hold finite numbers within +-1e+06"),
    (_rate_with(0, 3, -np.inf), "pose_velocity must hold finite numbers within +-1e+06"),
    (_rate_with(2, 3, np.nextafter(1e6, np.inf)), "pose_velocity must hold finite numbers within +-1e+06"),
    (_rate_with(3, 3, np.nan), "pose_velocity must hold finite numbers within +-1e+06"),
    (_rate_with(3, 3, 1.0), ("pose_velocity bottom row must be [0, 0, 0, 0] (a pose's bottom row does "
                            "not change), got [0.0, 0.0, 0.0, 1.0]")),
    (_rate_with(3, 0, -1e-300), ("pose_velocity bottom row must be [0, 0, 0, 0] (a pose's bottom row "
                                "does not change), got [-1e-300, 0.0, 0.0, 0.0]")),
])
def test_a_bad_pose_velocity_is_refused(given, message):
    assert refusal(check_pose_velocity, given) == (message, 422, "bad-pose-velocity")


def test_a_pose_velocity_refusal_names_where_it_was_given():
    message, status, code = refusal(check_pose_velocity, [["a"] * 4] * 4, "colliders[1].pose_velocity")
    assert message.startswith("colliders[1].pose_velocity must be a 4x4 matrix of numbers: ")
    assert (status, code) == (422, "bad-pose-velocity")
    assert refusal(check_pose_velocity, [[0.0], [0.0, 1.0]])[0].startswith(
        "pose_velocity must be a 4x4 matrix of numbers: ")
    assert refusal(check_pose_velocity, np.eye(2), "colliders[0].pose_velocity")[0] == (
        "colliders[0].pose_velocity must be a 4x4 matrix, got shape (2, 2)")


def test_a_model_query_carries_its_time_and_pose_velocity_to_the_wire_and_back():
    query = ModelQuery.build([[0, 0, 1]], "velocity", moved(), time=2, pose_velocity=rate(1.0 / 3.0))
    assert query.time == 2.0 and type(query.time) is float
    assert query.pose_velocity.tolist() == rate(1.0 / 3.0)
    body = query.to_body()
    assert body["time"] == 2.0 and body["pose_velocity"] is query.pose_velocity
    assert ModelQuery.build([[0, 0, 1]], time=0.0).to_body()["time"] == 0.0
    assert ModelQuery.build([[0, 0, 1]], pose_velocity=np.zeros((4, 4))).to_body().keys() == {
        "points", "fields", "pose_velocity"}
    defaults = ModelQuery.build([[0, 0, 1]])
    assert (defaults.time, defaults.pose_velocity) == (None, None)
    assert defaults.to_body().keys() == {"points", "fields"}
    for media in (wire.MSGPACK, wire.JSON):
        got = ModelQuery.from_body(wire.loads(wire.dumps(body, media), media))
        assert got.time == 2.0 and got.pose_velocity.tobytes() == query.pose_velocity.tobytes()
        assert got.fields == ("velocity",)
    absent = ModelQuery.from_body({"points": POINTS})
    assert (absent.time, absent.pose_velocity) == (None, None)


@pytest.mark.parametrize("extra, message, code", [
    ({"time": None}, "time must not be null (leave it out for its default)", "bad-time"),
    ({"time": "0"}, "time must be a finite number, got '0'", "bad-time"),
    ({"time": 1e10}, "time=10000000000.0 is outside +-1e+09 s", "bad-time"),
    ({"pose_velocity": None}, "pose_velocity must not be null (leave it out for its default)",
     "bad-pose-velocity"),
    ({"pose_velocity": "still"}, "pose_velocity: expected an array (msgpack map or JSON list), got str",
     "bad-pose-velocity"),
    ({"pose_velocity": wire.encode_array(np.zeros((4, 4), bool))}, "pose_velocity: must hold numbers, got bool",
     "bad-pose-velocity"),
    ({"pose_velocity": [[False] * 4] * 4}, "pose_velocity: must hold numbers, got bool", "bad-pose-velocity"),
    ({"pose_velocity": wire.encode_array(np.zeros((4, 3)))}, ("pose_velocity must be a 4x4 matrix, got "
                                                             "shape (4, 3)"), "bad-pose-velocity"),
    ({"pose_velocity": {"dtype": "<f8", "shape": [4, 4], "data": b""}},
     "pose_velocity: data has 0 bytes but dtype <f8 and shape [4, 4] need 128", "bad-pose-velocity"),
])
def test_a_bad_time_or_pose_velocity_in_a_body_is_refused(extra, message, code):
    assert refusal(ModelQuery.from_body, {"points": POINTS, **extra}) == (message, 422, code)


def test_every_form_of_scene_collider_carries_its_time_and_pose_velocity():
    given = [SceneCollider("a", moved(), time=1.5, pose_velocity=rate(2.0)),
             {"model": "b", "time": 0.0}, {"model": "c", "pose_velocity": rate(drift=(1, 0, 0))},
             "d", ("e", None), SceneCollider("f")]
    checked = check_colliders(given, 7.0)
    assert [p.time for p in checked] == [1.5, 0.0, 7.0, 7.0, 7.0, 7.0]  # a time of 0 is a time
    assert [None if p.pose_velocity is None else p.pose_velocity.tolist() for p in checked] == [
        rate(2.0), None, rate(drift=(1, 0, 0)), None, None, None]
    assert checked[0].pose.source.tolist() == moved().tolist()
    assert [p.time for p in check_colliders(given)] == [1.5, 0.0, None, None, None, None]


def test_a_scene_colliders_checks_run_time_then_pose_then_pose_velocity():
    item = {"model": "a", "time": "t", "pose": SHEAR, "pose_velocity": np.eye(4)}
    for key, good, message, code in (
            ("time", 1.0, "colliders[1].time must be a finite number, got 't'", "bad-time"),
            ("pose", None, "colliders[1].pose: " + RIGID_MESSAGE, "bad-pose"),
            ("pose_velocity", None, ("colliders[1].pose_velocity bottom row must be [0, 0, 0, 0] (a "
                                    "pose's bottom row does not change), got [0.0, 0.0, 0.0, 1.0]"),
             "bad-pose-velocity")):
        assert refusal(check_colliders, ["z", item]) == (message, 422, code)
        wire_item = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in item.items()
                     if v is not None}
        assert refusal(SceneQuery.from_body, {"points": POINTS, "colliders": [{"model": "z"}, wire_item]}) == (
            message, 422, code)
        item[key] = good
    assert check_colliders(["z", item])[1] == Placed("a", IDENTITY, 1.0, None)


def test_a_scene_query_gives_each_collider_its_time_and_pose_velocity():
    points = np.zeros((2, 3))
    scene = SceneQuery.build(points, [SceneCollider("a", time=0.0, pose_velocity=rate(1.0)),
                                      ("b", moved()), {"model": "c", "time": -4.0}], "velocity", 0.5,
                             time=3)
    parts = [scene.of_collider(i) for i in range(3)]
    assert [part.time for part in parts] == [0.0, 3.0, -4.0]
    assert parts[0].pose_velocity.tolist() == rate(1.0) and parts[1].pose_velocity is None
    assert parts[1].pose is scene.colliders[1].pose and parts[1].eps == 0.5
    body = scene.to_body()
    assert "time" not in body  # each collider's own, resolved
    assert body["colliders"] == [{"model": "a", "time": 0.0, "pose_velocity": rate(1.0)},
                                 {"model": "b", "pose": moved().tolist(), "time": 3.0},
                                 {"model": "c", "time": -4.0}]
    for media in (wire.MSGPACK, wire.JSON):
        got = SceneQuery.from_body(wire.loads(wire.dumps(body, media), media))
        assert [p.time for p in got.colliders] == [0.0, 3.0, -4.0]
        assert got.colliders[0].pose_velocity.tolist() == rate(1.0)
        assert got.colliders[1].pose.source.tobytes() == moved().tobytes()


def test_a_scene_bodys_time_is_that_of_the_colliders_that_give_none():
    body = {"points": POINTS, "time": 5, "colliders": [{"model": "a"}, {"model": "b", "time": 0},
                                                       {"model": "c", "time": 2.5}]}
    assert [p.time for p in SceneQuery.from_body(body).colliders] == [5.0, 0.0, 2.5]
    del body["time"]
    assert [p.time for p in SceneQuery.from_body(body).colliders] == [None, 0.0, 2.5]


@pytest.mark.parametrize("body, message, code", [
    ({"time": None, "colliders": [{"model": "a"}]}, "time must not be null (leave it out for its default)",
     "bad-time"),
    ({"colliders": [{"model": "a"}, {"model": "b", "time": None}]},
     "colliders[1].time must not be null (leave it out for its default)", "bad-time"),
    ({"colliders": [{"model": "a", "time": 2e9}]}, "colliders[0].time=2000000000.0 is outside +-1e+09 s",
     "bad-time"),
    ({"colliders": [{"model": "a", "pose_velocity": None}]},
     "colliders[0].pose_velocity must not be null (leave it out for its default)", "bad-pose-velocity"),
    ({"colliders": [{"model": "a", "pose_velocity": "x"}]},
     "colliders[0].pose_velocity: expected an array (msgpack map or JSON list), got str", "bad-pose-velocity"),
    ({"colliders": [{"model": "a", "pose_velocity": [[True] * 4] * 4}]},
     "colliders[0].pose_velocity: must hold numbers, got bool", "bad-pose-velocity"),
    ({"colliders": [{"model": "a", "pose_velocity": [[0.0] * 4] * 3}]},
     "colliders[0].pose_velocity must be a 4x4 matrix, got shape (3, 4)", "bad-pose-velocity"),
])
def test_a_bad_time_or_pose_velocity_in_a_scene_body_is_refused(body, message, code):
    assert refusal(SceneQuery.from_body, {"points": POINTS, **body}) == (message, 422, code)
