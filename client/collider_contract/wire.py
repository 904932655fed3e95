"""The wire format: how bodies and arrays travel (numpy + msgpack only, no torch).

Bodies are msgpack maps (``application/msgpack``) or JSON objects (``application/json``).

An array in msgpack is a map of exactly three keys, ``{"dtype": "<f4", "shape": [n, 3], "data":
<bin>}``: ``data`` holds the raw C-order bytes, little-endian, of the numpy dtype string ``dtype``
(one of ``<f4``, ``<f8``, ``|b1``, ``<i4``, ``<i8``), and ``len(data) == prod(shape) * itemsize``.
It decodes with no copy (``numpy.frombuffer``). In JSON an array is a nested list of numbers (or
booleans).

The keys of query bodies and what each holds are :mod:`.queries`' (``QUERY_KEYS``,
``SCENE_KEYS``, ``COLLIDER_KEYS``); the answers' are :mod:`.results`'. docs/service.md describes
both for client writers.
"""

from __future__ import annotations

import json
import math
from typing import Any

import msgpack
import numpy as np

MSGPACK_TYPES = ("application/msgpack", "application/x-msgpack", "application/vnd.msgpack")
MSGPACK = MSGPACK_TYPES[0]
JSON = "application/json"
ARRAY_DTYPES = ("<f4", "<f8", "|b1", "<i4", "<i8")
#: The keys of an array map, all required, no other.
ARRAY_MAP_KEYS = ("dtype", "shape", "data")

#: Messages for parser errors that carry none.
_REASONS = {"FormatError": "a byte that starts no msgpack value (e.g. 0xc1)",
            "StackError": "nesting too deep", "OutOfData": "the body ends inside a value",
            "ExtraData": "bytes after the end of the body's value"}


class WireError(ValueError):
    """A body or array that does not follow the wire format; the message names the field."""


def encode_array(array: np.ndarray) -> dict:
    """A numpy array as the msgpack array map (little-endian, C order)."""
    array = np.asarray(array)
    if array.dtype == np.bool_:
        array = array.astype("|b1", copy=False)
    else:
        array = array.astype(array.dtype.newbyteorder("<"), copy=False)
    if array.dtype.str not in ARRAY_DTYPES:
        raise WireError(f"dtype {array.dtype} cannot be sent; use one of {list(ARRAY_DTYPES)}")
    return {
        "dtype": array.dtype.str,
        "shape": list(array.shape),
        "data": np.ascontiguousarray(array).tobytes(),
    }


def decode_array(value: Any, name: str) -> np.ndarray:
    """The array map (msgpack) or nested list (JSON) ``value`` of field ``name`` as numpy.

    msgpack arrays are read-only views on the body (no copy). Raises :class:`WireError`.
    """
    if isinstance(value, dict):
        missing = set(ARRAY_MAP_KEYS) - set(value)
        if missing:
            raise WireError(f"{name}: array map lacks {sorted(missing)}")
        extra = set(value) - set(ARRAY_MAP_KEYS)
        if extra:  # a misspelt or foreign key is a mistake to name, not to drop silently
            raise WireError(f"{name}: array map has unknown key(s) {sorted(map(str, extra))}; "
                            f"it holds exactly {list(ARRAY_MAP_KEYS)}")
        dtype, shape, data = value["dtype"], value["shape"], value["data"]
        if dtype not in ARRAY_DTYPES:
            raise WireError(f"{name}: dtype {dtype!r} not supported; use one of {list(ARRAY_DTYPES)}")
        if not isinstance(shape, (list, tuple)) or not all(
            isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape
        ):
            raise WireError(f"{name}: shape must be a list of non-negative integers, got {shape!r}")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise WireError(f"{name}: data must be binary, got {type(data).__name__}")
        # Python integers: a product of wire-given dimensions must not wrap around (2**62 x 4
        # is 0 in int64, which would "match" an empty data field).
        expected = math.prod(shape) * np.dtype(dtype).itemsize
        if len(data) != expected:
            raise WireError(
                f"{name}: data has {len(data)} bytes but dtype {dtype} and shape {list(shape)} "
                f"need {expected}"
            )
        try:
            return np.frombuffer(data, dtype=dtype).reshape(shape)
        except ValueError as exc:  # an empty array with a dimension numpy cannot index
            raise WireError(f"{name}: shape {list(shape)} is not a valid array shape ({exc})") from None
    if isinstance(value, list):
        try:
            array = np.asarray(value)
        except ValueError:
            raise WireError(f"{name}: nested lists are ragged") from None
        if array.size and array.dtype.kind not in "fiub":
            raise WireError(f"{name}: must hold numbers, got {array.dtype}")
        if array.dtype.kind in "iuf" and _holds_bool(value):
            # numpy reads [0, true, 0] as numbers; true is not a coordinate.
            raise WireError(f"{name}: must hold numbers only, got a boolean among them")
        return array.astype(np.float64) if array.dtype.kind in "iu" else array
    raise WireError(f"{name}: expected an array (msgpack map or JSON list), got {type(value).__name__}")


def _holds_bool(value: list) -> bool:
    """Whether the nested list ``value`` holds ``true`` or ``false`` anywhere."""
    stack = [value]
    while stack:
        for item in stack.pop():
            if item is True or item is False:
                return True
            if isinstance(item, list):
                stack.append(item)
    return False


def to_jsonable(array: np.ndarray) -> list:
    """A numpy array as nested lists for JSON (NaN-free arrays only)."""
    return np.asarray(array).tolist()


def dumps(body: dict, content_type: str = MSGPACK) -> bytes:
    """Serialise ``body`` (numpy arrays allowed as values) for ``content_type``."""
    if content_type in MSGPACK_TYPES:
        return msgpack.packb(
            {k: encode_array(v) if isinstance(v, np.ndarray) else v for k, v in body.items()},
            use_bin_type=True,
        )
    if content_type == JSON:
        # NaN and Infinity are not JSON (JSON.parse refuses them): never write them.
        try:
            return json.dumps(
                {k: to_jsonable(v) if isinstance(v, np.ndarray) else v for k, v in body.items()},
                allow_nan=False,
            ).encode()
        except ValueError:
            raise WireError("NaN or Infinity cannot be sent as JSON") from None
    raise WireError(f"unsupported content type {content_type!r}; use {MSGPACK} or {JSON}")


def loads(data: bytes, content_type: str = MSGPACK) -> dict:
    """Parse a body; the result is a dict whose arrays are still wire values (see decode_array)."""
    content_type = (content_type or "").split(";")[0].strip().lower()
    try:
        if content_type in MSGPACK_TYPES:
            body = msgpack.unpackb(data, raw=False, strict_map_key=True)
        elif content_type == JSON:
            body = json.loads(data)
        else:
            raise WireError(f"unsupported content type {content_type!r}; use {MSGPACK} or {JSON}")
    except WireError:
        raise
    except Exception as exc:  # noqa: BLE001 -- msgpack and json raise several types for malformed bodies
        # Some (msgpack's FormatError) carry no message: say at least what kind of error it is.
        reason = str(exc) or _REASONS.get(type(exc).__name__, type(exc).__name__)
        raise WireError(f"malformed {content_type} body: {reason}") from None
    if not isinstance(body, dict):
        raise WireError(f"body must be a map/object, got {type(body).__name__}")
    return body
