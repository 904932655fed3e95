"""The wire format: array maps in msgpack, nested lists in JSON, and the one-line refusal of
every malformed body or array, naming the field."""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest

from collider_contract import wire
from collider_contract.wire import WireError, decode_array, dumps, encode_array, loads


def test_the_media_types_and_dtypes():
    assert wire.MSGPACK_TYPES == ("application/msgpack", "application/x-msgpack",
                                  "application/vnd.msgpack")
    assert (wire.MSGPACK, wire.JSON) == ("application/msgpack", "application/json")
    assert wire.ARRAY_DTYPES == ("<f4", "<f8", "|b1", "<i4", "<i8")


@pytest.mark.parametrize("values, dtype, raw", [
    ([[1.0, -2.0, 0.5]], "<f4", b"\x00\x00\x80\x3f\x00\x00\x00\xc0\x00\x00\x00\x3f"),
    ([0.5, -1.0], "<f8", b"\x00\x00\x00\x00\x00\x00\xe0\x3f\x00\x00\x00\x00\x00\x00\xf0\xbf"),
    ([True, False, True], "|b1", b"\x01\x00\x01"),
    ([[1, -2]], "<i4", b"\x01\x00\x00\x00\xfe\xff\xff\xff"),
    ([258], "<i8", b"\x02\x01\x00\x00\x00\x00\x00\x00"),
])
def test_every_dtype_encodes_to_little_endian_bytes_and_back(values, dtype, raw):
    array = np.array(values, dtype=dtype)
    encoded = encode_array(array)
    assert encoded == {"dtype": dtype, "shape": list(array.shape), "data": raw}
    decoded = decode_array(encoded, "x")
    assert decoded.dtype == np.dtype(dtype) and decoded.shape == array.shape
    assert decoded.tolist() == values
    assert not decoded.flags.writeable  # a view on the body, not a copy


def test_big_endian_and_strided_arrays_are_sent_little_endian_in_c_order():
    big = np.array([[1.0, 2.0], [3.0, 4.0]], dtype=">f8")
    encoded = encode_array(big.T)  # Fortran order, big-endian
    assert encoded["dtype"] == "<f8" and encoded["shape"] == [2, 2]
    assert encoded["data"] == np.array([[1.0, 3.0], [2.0, 4.0]], "<f8").tobytes()
    assert encode_array(np.array([7], ">i4"))["data"] == b"\x07\x00\x00\x00"
    assert encode_array([[1.5, 2.5]]) == {"dtype": "<f8", "shape": [1, 2],
                                          "data": np.array([1.5, 2.5], "<f8").tobytes()}


@pytest.mark.parametrize("dtype", ["float16", "uint8", "int16", "complex64", ">u4"])
def test_dtypes_outside_the_list_cannot_be_sent(dtype):
    with pytest.raises(WireError) as refused:
        encode_array(np.zeros(2, dtype))
    assert str(refused.value) == (f"dtype {np.dtype(dtype).newbyteorder('<')} cannot be sent; "
                                  "use one of ['<f4', '<f8', '|b1', '<i4', '<i8']")


def test_the_decoded_array_is_a_view_on_the_body():
    data = bytearray(np.arange(6, dtype="<f4").tobytes())
    decoded = decode_array({"dtype": "<f4", "shape": (2, 3), "data": data}, "points")
    assert decoded.tolist() == [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]
    data[:4] = np.float32(9.0).tobytes()
    assert decoded[0, 0] == 9.0  # no copy was made
    view = decode_array({"dtype": "<i8", "shape": [1], "data": memoryview(b"\x05" + bytes(7))}, "n")
    assert view.tolist() == [5]


def _array_refusal(value, name="points") -> str:
    with pytest.raises(WireError) as refused:
        decode_array(value, name)
    return str(refused.value)


GOOD = {"dtype": "<f8", "shape": [1, 3], "data": bytes(24)}


@pytest.mark.parametrize("value, message", [
    ({"dtype": "<f8"}, "points: array map lacks ['data', 'shape']"),
    ({"shape": [1], "data": b""}, "points: array map lacks ['dtype']"),
    # the schema's additionalProperties: false, in the one reader every backend uses
    ({**GOOD, "x": 1}, ("points: array map has unknown key(s) ['x']; it holds exactly "
                        "['dtype', 'shape', 'data']")),
    ({**GOOD, 7: 1, "Data": b""}, ("points: array map has unknown key(s) ['7', 'Data']; it holds "
                                   "exactly ['dtype', 'shape', 'data']")),
    ({**GOOD, "dtype": "<f2"}, ("points: dtype '<f2' not supported; use one of "
                               "['<f4', '<f8', '|b1', '<i4', '<i8']")),
    ({**GOOD, "dtype": ">f8"}, ("points: dtype '>f8' not supported; use one of "
                               "['<f4', '<f8', '|b1', '<i4', '<i8']")),
    ({**GOOD, "shape": "1,3"}, "points: shape must be a list of non-negative integers, got '1,3'"),
    ({**GOOD, "shape": 3}, "points: shape must be a list of non-negative integers, got 3"),
    ({**GOOD, "shape": [1, 3.0]}, "points: shape must be a list of non-negative integers, got [1, 3.0]"),
    ({**GOOD, "shape": [True, 3]}, "points: shape must be a list of non-negative integers, got [True, 3]"),
    ({**GOOD, "shape": [-1, 3]}, "points: shape must be a list of non-negative integers, got [-1, 3]"),
    ({**GOOD, "data": "abc"}, "points: data must be binary, got str"),
    ({**GOOD, "data": [0] * 24}, "points: data must be binary, got list"),
    ({**GOOD, "data": bytes(23)}, "points: data has 23 bytes but dtype <f8 and shape [1, 3] need 24"),
    ({**GOOD, "data": bytes(25)}, "points: data has 25 bytes but dtype <f8 and shape [1, 3] need 24"),
    # 2**62 x 8 bytes wraps to 0 in int64: the product is taken in Python integers
    ({"dtype": "<f8", "shape": [2 ** 61, 2], "data": b""},
     "points: data has 0 bytes but dtype <f8 and shape [2305843009213693952, 2] need 36893488147419103232"),
    ([[0.0, 1.0], [2.0]], "points: nested lists are ragged"),
    ([["a", "b", "c"]], "points: must hold numbers, got <U1"),
    ([[0.0, None, 1.0]], "points: must hold numbers, got object"),
    # an integer beyond int64 is an object to numpy (a coordinate that large is out of range anyway)
    ([[2 ** 70, 0, 0]], "points: must hold numbers, got object"),
    ([[0, True, 0]], "points: must hold numbers only, got a boolean among them"),
    ([[0.5, 1.0, 2.0], [False, 1.0, 2.0]], "points: must hold numbers only, got a boolean among them"),
    ([[[1, 2, 3]], [[4, 5, False]]], "points: must hold numbers only, got a boolean among them"),
    ("0 0 0", "points: expected an array (msgpack map or JSON list), got str"),
    (None, "points: expected an array (msgpack map or JSON list), got NoneType"),
    ((0.0, 0.0, 0.0), "points: expected an array (msgpack map or JSON list), got tuple"),
    (b"\x00" * 24, "points: expected an array (msgpack map or JSON list), got bytes"),
])
def test_a_malformed_array_is_refused_naming_the_field(value, message):
    assert _array_refusal(value) == message


def test_an_empty_shape_numpy_cannot_index_is_refused():
    message = _array_refusal({"dtype": "<f4", "shape": [0, 2 ** 62, 2 ** 62], "data": b""}, "pose")
    assert message.startswith("pose: shape [0, 4611686018427387904, 4611686018427387904] is not a "
                              "valid array shape (")


def test_empty_shapes_and_tuples_decode():
    empty = decode_array({"dtype": "<f4", "shape": [0, 3], "data": b""}, "points")
    assert empty.shape == (0, 3) and empty.dtype == np.float32
    scalar = decode_array({"dtype": "<i4", "shape": [], "data": b"\x2a\x00\x00\x00"}, "n")
    assert scalar.shape == () and int(scalar) == 42


@pytest.mark.parametrize("value, dtype, expected", [
    ([[1, 2, 3]], np.float64, [[1.0, 2.0, 3.0]]),         # integers are numbers: float64
    ([[1, 2.5, 3]], np.float64, [[1.0, 2.5, 3.0]]),
    ([True, False], np.bool_, [True, False]),             # booleans alone stay booleans
    ([[True], [False]], np.bool_, [[True], [False]]),
    ([], np.float64, []),
    ([[], []], np.float64, [[], []]),
])
def test_json_lists_decode_to_float64_numbers_or_booleans(value, dtype, expected):
    array = decode_array(value, "points")
    assert array.dtype == dtype and array.tolist() == expected


def test_to_jsonable_gives_nested_lists():
    assert wire.to_jsonable(np.array([[1.5, 2.0]], np.float32)) == [[1.5, 2.0]]
    assert wire.to_jsonable(np.array([True])) == [True]


def test_dumps_msgpack_encodes_top_level_arrays_and_keeps_other_values():
    body = {"points": np.array([[1.0, 2.0, 3.0]], np.float32), "fields": ["distance"], "eps": 0.5,
            "nested": [np.float64(1.0).item()]}
    for media in wire.MSGPACK_TYPES:
        raw = dumps(body, media)
        assert msgpack.unpackb(raw, raw=False) == {
            "points": {"dtype": "<f4", "shape": [1, 3], "data": np.array([1, 2, 3], "<f4").tobytes()},
            "fields": ["distance"], "eps": 0.5, "nested": [1.0]}
        assert loads(raw, media)["points"]["data"] == np.array([1, 2, 3], "<f4").tobytes()
    assert dumps(body) == dumps(body, wire.MSGPACK)
    # bytes travel as msgpack bin (use_bin_type), not as str
    assert msgpack.unpackb(dumps({"b": b"\xff"}), raw=True) == {b"b": b"\xff"}


def test_dumps_json_writes_arrays_as_lists_and_never_nan():
    raw = dumps({"distance": np.array([0.5, -1.0], np.float32), "model": "bunny"}, wire.JSON)
    assert json.loads(raw) == {"distance": [0.5, -1.0], "model": "bunny"}
    assert isinstance(raw, bytes)
    for bad in (np.array([np.nan]), np.array([np.inf]), float("nan")):
        with pytest.raises(WireError) as refused:
            dumps({"distance": bad}, wire.JSON)
        assert str(refused.value) == "NaN or Infinity cannot be sent as JSON"


def test_dumps_json_leaves_values_other_than_arrays_as_they_are():
    body = {"fields": ["distance"], "eps": 1, "shape": [1, 2.5], "colliders": [["a"], ["b", None]],
            "only_colliding": True, "pose": np.eye(2, dtype=np.float32)}
    assert dumps(body, wire.JSON) == (b'{"fields": ["distance"], "eps": 1, "shape": [1, 2.5], '
                                      b'"colliders": [["a"], ["b", null]], "only_colliding": true, '
                                      b'"pose": [[1.0, 0.0], [0.0, 1.0]]}')


@pytest.mark.parametrize("media", ["text/plain", "application/JSON", "", "application/msgpack; x=1"])
def test_dumps_refuses_other_media_types(media):
    with pytest.raises(WireError) as refused:
        dumps({"a": 1}, media)
    assert str(refused.value) == (f"unsupported content type {media!r}; use application/msgpack "
                                  "or application/json")


def test_round_trip_through_both_encodings():
    points = np.array([[0.1, -0.2, 1e6], [3.0, 4.0, -1e-300]])
    for media in (wire.MSGPACK, wire.JSON):
        body = loads(dumps({"points": points, "eps": 1e-3}, media), media)
        assert body["eps"] == 1e-3
        decoded = decode_array(body["points"], "points")
        assert decoded.dtype == np.float64 and decoded.tobytes() == points.tobytes()


@pytest.mark.parametrize("media", ["application/json", "Application/JSON; charset=utf-8",
                                   " application/json ;q=1"])
def test_loads_reads_the_media_type_without_case_or_parameters(media):
    assert loads(b'{"points": [[1, 2, 3]]}', media) == {"points": [[1, 2, 3]]}


def test_loads_defaults_to_msgpack_and_its_aliases():
    raw = msgpack.packb({"a": [1, 2]})
    assert loads(raw) == {"a": [1, 2]}
    for media in ("application/x-msgpack", "APPLICATION/VND.MSGPACK"):
        assert loads(raw, media) == {"a": [1, 2]}


def _body_refusal(data, media=wire.MSGPACK) -> str:
    with pytest.raises(WireError) as refused:
        loads(data, media)
    return str(refused.value)


class _Undecodable(bytes):
    """Bytes whose decoding fails with an exception that has no message."""

    def decode(self, *args, **kwargs):
        raise RuntimeError()


@pytest.mark.parametrize("data, media, message", [
    (b"\xc1", wire.MSGPACK, ("malformed application/msgpack body: a byte that starts no msgpack "
                            "value (e.g. 0xc1)")),
    (b"\x91" * 100_000, wire.MSGPACK, "malformed application/msgpack body: nesting too deep"),
    (b"\x92\x01", wire.MSGPACK, "malformed application/msgpack body: Unpack failed: incomplete input"),
    (b"\x80\x80", wire.MSGPACK, "malformed application/msgpack body: unpack(b) received extra data."),
    (msgpack.packb({1: 2}), wire.MSGPACK,
     "malformed application/msgpack body: int is not allowed for map key when strict_map_key=True"),
    (b"\xa2\xff\xfe", wire.MSGPACK, ("malformed application/msgpack body: 'utf-8' codec can't decode "
                                    "byte 0xff in position 0: invalid start byte")),
    (b"{", wire.JSON, ("malformed application/json body: Expecting property name enclosed in double "
                      "quotes: line 1 column 2 (char 1)")),
    (b'{"a": NaN', "Application/Json", ("malformed application/json body: Expecting ',' delimiter: "
                                       "line 1 column 10 (char 9)")),
    (msgpack.packb([1, 2]), wire.MSGPACK, "body must be a map/object, got list"),
    (b"3", wire.JSON, "body must be a map/object, got int"),
    (b"{}", "text/plain; charset=x", ("unsupported content type 'text/plain'; use "
                                     "application/msgpack or application/json")),
    (b"{}", None, "unsupported content type ''; use application/msgpack or application/json"),
])
def test_a_malformed_body_is_refused_in_one_line(data, media, message):
    assert _body_refusal(data, media) == message


def test_an_error_without_a_message_is_named_by_its_type():
    assert _body_refusal(_Undecodable(b"{}"), wire.JSON) == "malformed application/json body: RuntimeError"


def test_msgpack_strings_are_text_and_binaries_bytes():
    body = loads(msgpack.packb({"model": "bunny", "data": b"\x00\x01"}, use_bin_type=True))
    assert body == {"model": "bunny", "data": b"\x00\x01"}


def test_json_reads_big_integers_and_keeps_null():
    body = loads(b'{"eps": 1' + b"0" * 400 + b', "pose": null}', wire.JSON)
    assert body["eps"] == 10 ** 400 and body["pose"] is None
