"""OpenAPI descriptions of the raw (msgpack or JSON) query bodies, for the ``/docs`` page.

The routes read their bodies themselves (msgpack arrays are decoded without copies), so FastAPI
cannot infer these schemas; they are written here once."""

from __future__ import annotations

_ARRAY = {
    "description": "JSON: nested lists. msgpack: a map {dtype: '<f4'|'<f8'|'|b1'|'<i4'|'<i8', "
                   "shape: [..], data: raw little-endian C-order bytes}",
    "oneOf": [{"type": "array", "items": {}},
              {"type": "object", "properties": {"dtype": {"type": "string"},
                                                "shape": {"type": "array", "items": {"type": "integer"}},
                                                "data": {"type": "string", "format": "binary"}}}],
}
_FIELDS = {"type": "array", "items": {"enum": ["distance", "normal", "contact", "collides"]},
           "default": ["distance"]}
_COMMON = {
    "points": {**_ARRAY, "title": "points: (n, 3) float32/float64, world frame, world units"},
    "fields": _FIELDS,
    "eps": {"type": "number", "description": "collision offset, world units, in [0, domain "
                                             "diagonal]; default 1 mm"},
    "deadline_ms": {"type": "number", "description": "504 if no answer within this many ms "
                                                     "(also the X-Deadline-Ms header)"},
    "only_colliding": {"type": "boolean", "default": False,
                       "description": "compute normal and contact only for points with distance < "
                                      "eps (the gradient work of the others is skipped); the others "
                                      "get normal [0, 0, 0] and contact = the point itself; "
                                      "collides tells them apart"},
}
_QUERY_SCHEMA = {"type": "object", "required": ["points"], "properties": {
    **_COMMON, "pose": {**_ARRAY, "title": "pose: (4, 4) collider frame -> world frame, rigid"}}}
_SCENE_SCHEMA = {"type": "object", "required": ["points", "colliders"], "properties": {
    **_COMMON,
    "colliders": {"type": "array", "items": {"type": "object", "required": ["model"], "properties": {
        "model": {"type": "string"}, "pose": {**_ARRAY, "title": "(4, 4) collider -> world"}}}}}}


def _body(schema: dict) -> dict:
    return {"requestBody": {"required": True, "content": {
        "application/msgpack": {"schema": schema}, "application/json": {"schema": schema}}}}


QUERY_BODY = _body(_QUERY_SCHEMA)
SCENE_BODY = _body(_SCENE_SCHEMA)

_PROBLEM = {"content": {"application/problem+json": {"schema": {"type": "object", "properties": {
    "type": {"type": "string"}, "title": {"type": "string"}, "status": {"type": "integer"},
    "detail": {"type": "string"}}}}}}
QUERY_RESPONSES = {
    200: {"description": "one entry per field asked for: distance (n,) float32, normal (n, 3) "
                         "float32, contact (n, 3) dtype of points, collides (n,) bool; world frame",
          "content": {"application/msgpack": {}, "application/json": {}}},
    **{code: {"description": text, **_PROBLEM} for code, text in {
        400: "malformed body", 401: "missing or bad bearer token", 404: "unknown model",
        413: "body too large or too many points", 415: "unsupported media type",
        422: "bad values: shape, dtype, NaN/Inf, non-rigid pose, unknown field, eps out of range",
        429: "queue full (Retry-After)", 503: "not ready or shutting down (Retry-After)",
        504: "deadline exceeded"}.items()},
}
