"""What an answer and a model are: QueryResult's fields and response body (msgpack views, JSON
lists given the promised dtypes), ModelInfo's dict form and domain box."""

from __future__ import annotations

import numpy as np
import pytest

from collider_contract import ModelInfo, QueryResult, wire
from collider_contract.wire import WireError

ALL_FIELDS = ["distance", "normal", "contact", "collides", "velocity"]


def full_result(points_dtype=np.float64) -> QueryResult:
    return QueryResult(distance=np.array([0.5, -0.25], np.float32),
                       normal=np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]], np.float32),
                       contact=np.array([[0.0, 0.0, 0.5], [1.5, 2.0, 0.0]], points_dtype),
                       collides=np.array([False, True]),
                       velocity=np.array([[0.0, 0.0, 0.0], [-1.5, 0.25, 3.0]], np.float32))


def test_fields_are_the_present_ones_in_canonical_order():
    result = QueryResult(velocity=np.zeros((1, 3), np.float32), collides=np.array([True]),
                         distance=np.array([0.1], np.float32), collider=np.array([0], np.int32), model="m")
    assert list(result.fields()) == ["distance", "collides", "velocity"]
    assert list(full_result().fields()) == ALL_FIELDS
    assert QueryResult().fields() == {}
    assert QueryResult(normal=np.zeros((1, 3))).fields().keys() == {"normal"}


def test_to_body_has_the_fields_and_the_model_or_the_collider():
    result = full_result()
    result.model = "bunny"
    body = result.to_body()
    assert list(body) == [*ALL_FIELDS, "model"]
    assert body["distance"] is result.distance and body["model"] == "bunny"
    scene = QueryResult(distance=np.array([1.0], np.float32), collider=np.array([2], np.int32))
    assert list(scene.to_body()) == ["distance", "collider"]
    assert scene.to_body()["collider"] is scene.collider
    assert QueryResult(collides=np.array([True])).to_body().keys() == {"collides"}


@pytest.mark.parametrize("points_dtype", [np.float32, np.float64])
def test_a_msgpack_response_reads_back_as_read_only_views_of_the_same_dtypes(points_dtype):
    sent = full_result(points_dtype)
    sent.model = "bunny"
    body = wire.loads(wire.dumps(sent.to_body()))
    got = QueryResult.from_body(body, ALL_FIELDS, scene=False)
    assert got.model == "bunny" and got.collider is None
    for name in ALL_FIELDS:
        value = getattr(got, name)
        assert value.dtype == getattr(sent, name).dtype, name
        assert value.tobytes() == getattr(sent, name).tobytes(), name
        assert not value.flags.writeable, name  # no copy was made


def test_a_json_response_gets_the_promised_dtypes():
    sent = full_result(np.float32)
    body = wire.loads(wire.dumps({**sent.to_body(), "collider": np.array([1, 0], np.int32)}, wire.JSON),
                      wire.JSON)
    got = QueryResult.from_body(body, ["velocity", "collides", "contact", "normal", "distance"], scene=True)
    assert got.distance.dtype == np.float32 and got.distance.tolist() == [0.5, -0.25]
    assert got.normal.dtype == np.float32 and got.normal.tolist() == sent.normal.tolist()
    assert got.collides.dtype == np.bool_ and got.collides.tolist() == [False, True]
    assert got.velocity.dtype == np.float32 and got.velocity.tolist() == sent.velocity.tolist()
    assert got.collider.dtype == np.int32 and got.collider.tolist() == [1, 0]
    # JSON numbers are float64: the contact stays float64 (the points' dtype is not on the wire)
    assert got.contact.dtype == np.float64 and got.contact.tolist() == sent.contact.tolist()
    assert got.model is None


def test_json_integers_get_the_promised_dtypes():
    body = {"collides": [1, 0], "collider": [0, 1], "velocity": [[0, 1, 2]], "distance": [3]}
    got = QueryResult.from_body(body, ["collides", "velocity", "distance"], scene=True)
    assert got.collides.dtype == np.bool_ and got.collides.tolist() == [True, False]
    assert got.collider.dtype == np.int32 and got.collider.tolist() == [0, 1]
    assert got.velocity.dtype == np.float32 and got.velocity.tolist() == [[0.0, 1.0, 2.0]]
    assert got.distance.dtype == np.float32 and got.distance.tolist() == [3.0]


def test_only_the_fields_asked_for_are_read():
    body = wire.loads(wire.dumps({**full_result().to_body(), "model": "m", "collider": np.zeros(2, np.int32)}))
    got = QueryResult.from_body(body, ("distance",), scene=False)
    assert got.fields().keys() == {"distance"} and got.collider is None and got.model == "m"
    got = QueryResult.from_body(body, ("normal",), scene=True)
    assert got.fields().keys() == {"normal"} and got.collider.tolist() == [0, 0] and got.model is None
    assert QueryResult.from_body({"distance": []}, ["distance"], scene=False).model is None


@pytest.mark.parametrize("body, fields, scene, message", [
    ({"distance": [1.0]}, ["distance", "normal"], False, "the response lacks 'normal', which was asked for"),
    ({}, ["collides"], False, "the response lacks 'collides', which was asked for"),
    ({"distance": [1.0]}, ["distance"], True, "the response lacks 'collider', which was asked for"),
    ({"distance": "1.0"}, ["distance"], False,
     "distance: expected an array (msgpack map or JSON list), got str"),
    ({"distance": [1.0], "collider": {"dtype": "<i4", "shape": [1], "data": b""}}, ["distance"], True,
     "collider: data has 0 bytes but dtype <i4 and shape [1] need 4"),
])
def test_a_malformed_response_is_a_wire_error_naming_the_field(body, fields, scene, message):
    with pytest.raises(WireError) as refused:
        QueryResult.from_body(body, fields, scene)
    assert str(refused.value) == message


# -- ModelInfo ---------------------------------------------------------------------------------

def test_model_info_defaults():
    info = ModelInfo("bunny", "voxel")
    assert (info.name, info.kind, info.units, info.meters_per_unit, info.bytes, info.approximate,
            info.device) == ("bunny", "voxel", "m", 1.0, 0, False, "cpu")
    assert info.domain_min.tolist() == [0.0, 0.0, 0.0] and info.domain_max.tolist() == [0.0, 0.0, 0.0]
    assert info.accuracy == info.source == info.settings == info.animation == info.extra == {}
    assert info.animated is False
    other = ModelInfo("spot", "mesh")
    other.accuracy["x"] = 1  # each instance has its own dicts
    assert info.accuracy == {}


def test_model_info_to_dict_is_json_ready_and_from_dict_reads_it_back():
    info = ModelInfo("bunny", "neural", units="cm", meters_per_unit=0.01,
                     domain_min=np.array([-1, -2, -3]), domain_max=[1, 2, 3], bytes=1234,
                     approximate=True, accuracy={"mae_m": 1e-4}, source={"mesh": "bunny.obj"},
                     settings={"grid": 64}, device="cuda", extra={"trained_at": "2024-01-01"},
                     animation={"frames": 24, "frame_rate_hz": 24.0, "duration_s": 1.0, "loop": True})
    assert info.animated is True
    data = info.to_dict()
    assert data == {"trained_at": "2024-01-01", "name": "bunny", "kind": "neural", "units": "cm",
                    "meters_per_unit": 0.01, "domain_min": [-1.0, -2.0, -3.0],
                    "domain_max": [1.0, 2.0, 3.0], "bytes": 1234, "approximate": True,
                    "accuracy": {"mae_m": 1e-4}, "source": {"mesh": "bunny.obj"},
                    "settings": {"grid": 64}, "device": "cuda",
                    "animation": {"frames": 24, "frame_rate_hz": 24.0, "duration_s": 1.0, "loop": True},
                    "skeleton": {}}
    # integer bounds are written as floats
    assert [type(v) for v in data["domain_min"] + data["domain_max"]] == [float] * 6
    back = ModelInfo.from_dict(wire.loads(wire.dumps(data, wire.JSON), wire.JSON))
    assert back.domain_min.dtype == back.domain_max.dtype == np.float64
    assert back.domain_min.shape == (3,) and back.domain_min.tolist() == [-1.0, -2.0, -3.0]
    assert back.to_dict() == data and back.extra == {"trained_at": "2024-01-01"} and back.animated
    assert (back.name, back.kind, back.units, back.meters_per_unit, back.bytes, back.approximate,
            back.device) == ("bunny", "neural", "cm", 0.01, 1234, True, "cuda")


def test_a_known_key_wins_over_an_extra_of_the_same_name():
    info = ModelInfo("bunny", "mesh", extra={"name": "old", "new_key": 1})
    assert info.to_dict()["name"] == "bunny" and info.to_dict()["new_key"] == 1


def test_from_dict_keeps_unknown_keys_and_defaults_the_missing_ones():
    info = ModelInfo.from_dict({"name": "spot", "kind": "voxel", "domain_max": [[1, 2, 3]], "future": [1]})
    assert info.domain_max.tolist() == [1.0, 2.0, 3.0] and info.domain_max.dtype == np.float64
    assert info.domain_min.tolist() == [0.0, 0.0, 0.0] and info.units == "m"
    assert info.extra == {"future": [1]}
    with pytest.raises(ValueError):
        ModelInfo.from_dict({"name": "x", "kind": "y", "domain_min": [1, 2]})
    # a newer server's key named "extra" is one more unknown key, not the field
    info = ModelInfo.from_dict({"name": "spot", "kind": "voxel", "extra": {"a": 1}, "device": "cuda"})
    assert info.extra == {"extra": {"a": 1}} and info.device == "cuda"
    assert info.to_dict()["extra"] == {"a": 1}


def test_the_domain_corners_are_the_boxes_eight_corners():
    info = ModelInfo("box", "mesh", domain_min=np.array([-1.0, -2.0, -3.0]), domain_max=np.array([1.0, 2.0, 3.0]))
    corners = info.domain_corners()
    assert corners.dtype == np.float64
    # In the one corner order (collider_contract.pose.CORNERS): x in bit 0, y in bit 1, z in bit 2.
    assert corners.tolist() == [[-1.0, -2.0, -3.0], [1.0, -2.0, -3.0], [-1.0, 2.0, -3.0], [1.0, 2.0, -3.0],
                                [-1.0, -2.0, 3.0], [1.0, -2.0, 3.0], [-1.0, 2.0, 3.0], [1.0, 2.0, 3.0]]
