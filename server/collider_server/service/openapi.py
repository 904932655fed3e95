"""The OpenAPI description, written to match what the server does (a schema fuzzer checks it in
the test suite: schema-valid bodies are answered, every status code sent is declared), and the
``/docs`` page served from the installed ``swagger-ui-bundle`` package (no CDN).

The query routes read their bodies themselves (msgpack arrays are decoded without copies), so
FastAPI cannot infer their schemas; they are written here once. What JSON Schema cannot say is
in the descriptions: a pose must be rigid (the fuzzer maps its generated matrices to rigid ones),
and a msgpack array map's ``data`` must hold exactly ``prod(shape) * itemsize`` bytes.

The document is OpenAPI 3.1 (JSON Schema 2020-12: ``prefixItems``, ``const``); the page is Swagger
UI 5, which reads it (Swagger UI 4 cannot: "Unable to render this definition").
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Depends, Request
from starlette.responses import FileResponse, HTMLResponse, JSONResponse

from collider_contract import FIELDS, MAX_COORDINATE_M, TITLES
from collider_contract.queries import COLLIDER_KEYS, MAX_TIME_S, QUERY_KEYS, SCENE_KEYS, TRANSPORT_KEYS
from collider_contract.skeleton import MAX_CLIP_NAME, MAX_JOINTS

from .auth import require_token
from .problems import PROBLEM_JSON

#: The request media types, JSON first: the /docs page's "Try it out" sends the first one, and
#: it can write JSON text only (msgpack bodies come from clients).
REQUEST_MEDIA = ("application/json", "application/msgpack")

_COORDINATE = {"type": "number", "minimum": -MAX_COORDINATE_M, "maximum": MAX_COORDINATE_M}


def _array_map(dtypes: list[str], shape: list[int | None], title: str) -> dict:
    """msgpack's array map ``{dtype, shape, data}`` for arrays of ``shape`` (None: any length)."""
    dims = [{"type": "integer", "minimum": 0} if d is None else {"const": d} for d in shape]
    return {"type": "object", "title": title, "required": ["dtype", "shape", "data"],
            "additionalProperties": False,
            "description": "data: the raw little-endian C-order bytes, exactly "
                           "prod(shape) * itemsize of them",
            "properties": {"dtype": {"enum": dtypes},
                           "shape": {"type": "array", "prefixItems": dims, "items": False,
                                     "minItems": len(shape), "maxItems": len(shape)},
                           "data": {"type": "string", "format": "binary"}}}


def _points(max_points: int, msgpack: bool) -> dict:
    lists = {"type": "array", "maxItems": max_points,
             "items": {"type": "array", "items": _COORDINATE, "minItems": 3, "maxItems": 3}}
    schema = {"title": "points: (n, 3), world frame, world units (|coordinate| <= "
                       f"{MAX_COORDINATE_M:g})", **lists}
    if msgpack:
        schema = {"title": schema["title"], "oneOf": [
            lists, _array_map(["<f4", "<f8"], [None, 3], "(n, 3) float32 or float64")]}
    return schema


def _pose(msgpack: bool) -> dict:
    lists = {"type": "array", "minItems": 4, "maxItems": 4,
             "items": {"type": "array", "items": _COORDINATE, "minItems": 4, "maxItems": 4}}
    title = ("pose: (4, 4) collider frame -> world frame: a rotation times a uniform scale "
             f"(1e-6 to 1e6), translation within +-{MAX_COORDINATE_M:g}, bottom row 0 0 0 1")
    if msgpack:
        return {"title": title, "oneOf": [lists, _array_map(["<f4", "<f8"], [4, 4], "(4, 4)")]}
    return {"title": title, **lists}


_TIME = {"type": "number", "minimum": -MAX_TIME_S, "maximum": MAX_TIME_S,
         "description": "seconds: when an animated collider is asked (required for one; a static "
                        "collider ignores it); a missing time for an animated model is 422 "
                        "missing-time"}


def _pose_velocity(msgpack: bool) -> dict:
    lists = {"type": "array", "minItems": 4, "maxItems": 4,
             "items": {"type": "array", "items": _COORDINATE, "minItems": 4, "maxItems": 4}}
    title = ("pose_velocity: (4, 4) the pose's time derivative, d(s R)/dt in 1/s and the "
             "translation's rate in world units/s, bottom row 0 0 0 0; the frame's motion in the "
             "velocity field (default: still)")
    if msgpack:
        return {"title": title, "oneOf": [lists, _array_map(["<f4", "<f8"], [4, 4], "(4, 4)")]}
    return {"title": title, **lists}


def _joint_arrays(key: str, msgpack: bool) -> dict:
    lists = {"type": "array", "minItems": 1, "maxItems": MAX_JOINTS,
             "items": {"type": "array", "minItems": 4, "maxItems": 4,
                       "items": {"type": "array", "items": _COORDINATE, "minItems": 4,
                                 "maxItems": 4}}}
    if key == "joint_transforms":
        title = ("joint_transforms: (J, 4, 4) a skinned model's joints' world transforms in the "
                 "collider frame (its skeleton's joint order), each a rotation times a uniform "
                 "scale, translation within the coordinate range, bottom row 0 0 0 1")
    else:
        title = ("joint_velocities: (J, 4, 4) the joint transforms' time derivatives (1/s, "
                 "collider units/s), bottom rows 0 0 0 0, for velocity (default: still)")
    if msgpack:
        return {"title": title, "oneOf": [lists, _array_map(["<f4", "<f8"], [None, 4, 4],
                                                            "(J, 4, 4)")]}
    return {"title": title, **lists}


def _skeleton(msgpack: bool) -> dict:
    """A skinned model's skeleton pose (:mod:`collider_contract.skeleton`)."""
    return {"clip": {"type": "string", "minLength": 1, "maxLength": MAX_CLIP_NAME,
                     "description": "a skinned model's clip, asked at time (default: its first "
                                    "clip); a model without a skeleton answers 422 not-skinned"},
            "joint_transforms": _joint_arrays("joint_transforms", msgpack),
            "joint_velocities": _joint_arrays("joint_velocities", msgpack)}


def _common(max_points: int, msgpack: bool) -> dict:
    return {
        "points": _points(max_points, msgpack),
        "fields": {"type": "array", "minItems": 1, "default": ["distance"],
                   "items": {"enum": list(FIELDS)}},
        "eps": {"type": "number", "minimum": 0, "maximum": MAX_COORDINATE_M,
                "description": "collision offset, world units; default 1 mm in the collider's "
                               "units times the pose's scale"},
        "deadline_ms": {"type": "number", "exclusiveMinimum": 0,
                        "description": "504 if no answer within this many ms (also the "
                                       "X-Deadline-Ms header; the smaller wins)"},
        "only_colliding": {"type": "boolean", "default": False,
                           "description": "compute normal, contact and velocity only for points with "
                                          "distance < eps (the gradient work of the others is "
                                          "skipped); the others get normal [0, 0, 0] and contact "
                                          "= the point itself; collides tells them apart"},
    }


def _keys(properties: dict, keys: tuple[str, ...]) -> dict:
    """``properties`` in the order of the contract's ``keys`` (plus the transport keys): the
    contract's reader is the one home of which keys a body may hold."""
    allowed = (*keys, *sorted(TRANSPORT_KEYS))
    if set(properties) != set(allowed):
        raise RuntimeError(f"the schema's keys {sorted(properties)} are not the contract's "
                           f"{sorted(allowed)}")
    return {key: properties[key] for key in allowed}


#: The examples' points (the origin and 0.5 above it, world units) at time 0 (a static model
#: ignores it): valid for any model, so the /docs page's "Try it out" answers 200 as it is.
EXAMPLE_POINTS = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]]
EXAMPLE_FIELDS = ["distance", "normal", "collides"]


def query_body(max_points: int) -> dict:
    def schema(msgpack: bool) -> dict:
        properties = {**_common(max_points, msgpack), "pose": _pose(msgpack),
                      "pose_velocity": _pose_velocity(msgpack), "time": _TIME,
                      **_skeleton(msgpack)}
        return {"type": "object", "required": ["points"], "additionalProperties": False,
                "properties": _keys(properties, QUERY_KEYS)}

    body = _body({media: schema(media != "application/json") for media in REQUEST_MEDIA})
    body["requestBody"]["content"]["application/json"]["example"] = {
        "points": EXAMPLE_POINTS, "fields": EXAMPLE_FIELDS, "time": 0.0}
    return body


def scene_body(max_points: int, max_colliders: int) -> dict:
    def schema(msgpack: bool) -> dict:
        collider = {"model": {"type": "string"}, "pose": _pose(msgpack),
                    "pose_velocity": _pose_velocity(msgpack), "time": _TIME, **_skeleton(msgpack)}
        collider = {"type": "object", "required": ["model"], "additionalProperties": False,
                    "properties": {key: collider[key] for key in COLLIDER_KEYS}}
        properties = {**_common(max_points, msgpack),
                      "time": {**_TIME, "description": "seconds: the time of the colliders that "
                                                       "give none of their own"},
                      "colliders": {"type": "array", "items": collider, "minItems": 1,
                                    "maxItems": max_colliders}}
        return {"type": "object", "required": ["points", "colliders"],
                "additionalProperties": False, "properties": _keys(properties, SCENE_KEYS)}

    return _body({media: schema(media != "application/json") for media in REQUEST_MEDIA})


def with_examples(schema: dict, model: str | None) -> dict:
    """``schema`` (a copy to change) with ``model`` as the example of the model name in paths and
    in the scene query's body, so the /docs page's "Try it out" asks a model that is served
    (None: no model is loaded; the examples are left out)."""
    if model is None:
        return schema
    for path, operations in schema["paths"].items():
        if path.startswith("/v1/models/{name}"):
            for operation in operations.values():
                for parameter in operation.get("parameters", []):
                    if parameter["name"] == "name" and parameter["in"] == "path":
                        parameter["example"] = model
    scene = schema["paths"]["/v1/scene/query"]["post"]["requestBody"]["content"]["application/json"]
    scene["example"] = {"points": EXAMPLE_POINTS, "fields": EXAMPLE_FIELDS, "time": 0.0,
                        "colliders": [{"model": model}]}
    return schema


def _body(schemas: dict[str, dict]) -> dict:
    return {"requestBody": {"required": True, "content": {
        media: {"schema": schema} for media, schema in schemas.items()}}}


_PROBLEM_SCHEMA = {"type": "object", "required": ["type", "title", "status", "detail"],
                   "properties": {"type": {"type": "string"}, "title": {"type": "string"},
                                  "status": {"type": "integer"}, "detail": {"type": "string"}}}


def problems(*codes: int) -> dict:
    """``responses=`` entries for error statuses, each an ``application/problem+json`` body."""
    return {code: {"description": TITLES.get(code, "Error"),
                   "content": {PROBLEM_JSON: {"schema": _PROBLEM_SCHEMA}}} for code in codes}


_FLOATS = {"type": "array", "items": {"type": "number"}}
_ROWS = {"type": "array", "items": {"type": "array", "items": {"type": "number"},
                                    "minItems": 3, "maxItems": 3}}
_ANSWER = {"type": "object", "properties": {
    "distance": _FLOATS, "normal": _ROWS, "contact": _ROWS,
    "collides": {"type": "array", "items": {"type": "boolean"}}, "velocity": _ROWS}}

_VECTOR = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
_ANIMATION = {"type": "object", "description": "empty for a static model; an animated one's "
              "timeline (its queries must give a time)", "properties": {
                  "frames": {"type": "integer", "minimum": 2,
                             "description": "keyframes, evenly spaced in time"},
                  "frame_rate_hz": {"type": "number", "exclusiveMinimum": 0,
                                    "description": "keyframes per second"},
                  "duration_s": {"type": "number", "minimum": 0,
                                 "description": "seconds from the first frame to the last"},
                  "loop": {"type": "boolean", "description": "beyond its ends the animation "
                           "wraps (true) or holds the end frame (false)"},
                  "max_surface_speed": {"type": "number", "minimum": 0,
                                        "description": "fastest surface point, collider units "
                                                       "per second (0: unknown)"}}}
_SKELETON = {"type": "object", "description": "empty for a model without one; a skinned model's "
             "skeleton (its queries give a clip and a time, or joint transforms)", "properties": {
                 "joints": {"type": "array", "items": {"type": "string"},
                            "description": "joint names, in the order of joint_transforms"},
                 "parents": {"type": "array", "items": {"type": "integer", "minimum": -1},
                             "description": "each joint's parent index, -1 for a root"},
                 "clips": {"type": "array", "description": "the model's clips", "items": {
                     "type": "object", "properties": {
                         "name": {"type": "string"},
                         "duration_s": {"type": "number", "minimum": 0},
                         "max_surface_speed": {
                             "type": "number", "minimum": 0,
                             "description": "the fastest any point of the skin moves in the "
                             "clip, collider units per second (measured; absent in models "
                             "made before it was recorded)"}}}},
                 "loop": {"type": "boolean", "description": "beyond a clip's ends time wraps "
                          "(true) or holds the end pose (false)"}}}
#: ``collider_contract.ModelInfo.to_dict()``: what ``GET /v1/models/{name}`` answers (keys a
#: newer server adds are allowed).
MODEL_INFO = {"type": "object", "required": ["name", "kind", "domain_min", "domain_max",
                                             "meters_per_unit", "animation"], "properties": {
    "name": {"type": "string"},
    "kind": {"type": "string", "description": "neural, voxel, mesh (exact) or kdtree"},
    "units": {"type": "string", "description": "the collider's length unit (m for the shipped "
                                               "models)"},
    "meters_per_unit": {"type": "number", "exclusiveMinimum": 0},
    "domain_min": {**_VECTOR, "description": "collider frame and units: the box where the "
                                             "model is defined"},
    "domain_max": _VECTOR,
    "bytes": {"type": "integer", "minimum": 0, "description": "size of the model file"},
    "approximate": {"type": "boolean", "description": "the kind is not a signed distance by "
                    "construction (kdtree: the nearest vertex, not the nearest surface point)"},
    "accuracy": {"type": "object", "description": "figures `collider eval` stored (empty if "
                                                  "none)"},
    "source": {"type": "object", "description": "what the model was made from"},
    "settings": {"type": "object", "description": "how it was made"},
    "device": {"type": "string", "description": "where it computes (cpu, cuda)"},
    "animation": _ANIMATION,
    "skeleton": _SKELETON}}


def model_info_responses(*codes: int, listed: bool = False) -> dict:
    """``responses=`` of a route answering one model's info (``listed``: ``{"models": [...]}``)."""
    schema = ({"type": "object", "required": ["models"],
               "properties": {"models": {"type": "array", "items": MODEL_INFO}}}
              if listed else MODEL_INFO)
    return {200: {"description": "OK", "content": {"application/json": {"schema": schema}}},
            **problems(*codes)}

#: Statuses every body-reading query route can answer.
QUERY_ERRORS = (400, 401, 404, 408, 413, 415, 422, 429, 503, 504)


def query_responses(extra: dict | None = None, description: str = "") -> dict:
    ok = {"description": description or (
        "one entry per field asked for, plus \"model\": distance (n,) float32, normal (n, 3) "
        "float32, contact (n, 3) dtype of points, collides (n,) bool, velocity (n, 3) float32 "
        "world units/s; world frame"),
        "content": {"application/msgpack": {}, "application/json": {"schema": {
            **_ANSWER, "properties": {**_ANSWER["properties"], **(extra or {})}}}}}
    return {200: ok, **problems(*QUERY_ERRORS)}


#: Routes open to anyone; the admin routes take the admin token; the rest the service token.
PUBLIC_PATHS = ("/livez", "/readyz")


def add_security(schema: dict) -> None:
    """Declare the bearer tokens (``COLLIDER_TOKEN``, ``COLLIDER_ADMIN_TOKEN``) and which
    operations need which (the service token only when one is set)."""
    schema.setdefault("components", {})["securitySchemes"] = {
        "token": {"type": "http", "scheme": "bearer",
                  "description": "COLLIDER_TOKEN; when the server has none, no auth"},
        "adminToken": {"type": "http", "scheme": "bearer", "description": "COLLIDER_ADMIN_TOKEN"},
    }
    for path, operations in schema["paths"].items():
        if path in PUBLIC_PATHS:
            continue
        scheme = "adminToken" if path.startswith("/v1/admin/") else "token"
        for operation in operations.values():
            operation["security"] = [{scheme: []}]


# -- the /docs page and the schema, behind the same token as the API --------------------------

router = APIRouter(tags=["docs"], include_in_schema=False)

_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>neural-collider API</title>
<link rel="stylesheet" href="/docs/assets/swagger-ui.css">
<link rel="icon" type="image/png" href="/docs/assets/favicon-32x32.png"></head>
<body><div id="swagger-ui"></div>
<script src="/docs/assets/swagger-ui-bundle.js"></script>
<script>
// The schema needs the service token when the server has one (the server says so below): ask
// for it first, then send it with every request the page makes (it stays in this tab's memory).
const NEEDS_TOKEN = __NEEDS_TOKEN__;
let token = null;
async function start() {
  let question = "Service token (COLLIDER_TOKEN):";
  while (true) {
    if (NEEDS_TOKEN) {
      token = window.prompt(question);
      if (token === null) {
        document.getElementById("swagger-ui").textContent = "The API description needs the "
          + "service token (COLLIDER_TOKEN); reload the page to enter it.";
        return;
      }
    }
    const headers = token ? {Authorization: "Bearer " + token} : {};
    var response = await fetch("/openapi.json", {headers: headers});
    if (response.status !== 401) break;
    question = "That token was refused. Service token (COLLIDER_TOKEN):";
  }
  SwaggerUIBundle({
    // validatorUrl null: no badge fetched from the public validator (nothing leaves the page).
    spec: await response.json(), dom_id: "#swagger-ui", validatorUrl: null,
    requestInterceptor: (request) => {
      if (token) request.headers.Authorization = "Bearer " + token;
      return request;
    },
  });
}
start();
</script></body></html>
"""
_ASSETS = ("swagger-ui.css", "swagger-ui-bundle.js", "favicon-32x32.png")


def _assets_dir() -> Path:
    import swagger_ui_bundle

    return Path(swagger_ui_bundle.swagger_ui_path)


@router.get("/openapi.json", dependencies=[Depends(require_token)])
async def openapi_schema(request: Request):
    return JSONResponse(request.app.openapi())


@router.get("/docs")
async def docs_page(request: Request):
    """The page and its assets are the installed package's static files (they hold nothing
    secret, and a browser cannot send a bearer token for a page load); the schema it loads
    needs the token, which the page asks for when the server has one."""
    needs_token = bool(request.app.state.collider.settings.token)
    return HTMLResponse(_PAGE.replace("__NEEDS_TOKEN__", "true" if needs_token else "false"))


@router.get("/docs/assets/{name}")
async def docs_asset(name: str):
    from .problems import Problem

    if name not in _ASSETS:
        raise Problem(404, "not-found", f"no docs asset {name!r}")
    return FileResponse(_assets_dir() / name)
