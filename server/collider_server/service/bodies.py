"""Request and response bodies: media types, size limits, and the query fields' validation.

The arrays follow :mod:`collider_contract.wire` (msgpack maps of raw little-endian bytes, or JSON
nested lists). Status codes: 400 a body that cannot be parsed, 413 too large, 415 a media type
that is neither msgpack nor JSON, 422 a parsed body whose values are wrong.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass

import numpy as np
from starlette.requests import Request
from starlette.responses import Response

from collider_contract import Pose, PoseError, as_pose, wire

from ..engine.collider import check_fields, check_points
from .problems import Problem

DEADLINE_HEADER = "x-deadline-ms"
QUERY_KEYS = frozenset({"points", "fields", "pose", "eps", "deadline_ms", "only_colliding"})
SCENE_KEYS = frozenset({"points", "colliders", "fields", "eps", "deadline_ms", "only_colliding"})


def request_media_type(request: Request) -> str:
    """The body's media type (msgpack or JSON), else 415."""
    raw = request.headers.get("content-type", "")
    media = raw.split(";")[0].strip().lower()
    if media in wire.MSGPACK_TYPES or media == wire.JSON:
        return media
    raise Problem(415, "unsupported-media-type",
                  f"Content-Type {raw or '(none)'!r} is not supported; send "
                  f"{wire.MSGPACK} (or {', '.join(wire.MSGPACK_TYPES[1:])}) or {wire.JSON}")


def response_media_type(request: Request, request_media: str) -> str:
    """What the Accept header asks for among msgpack and JSON; else the request's own type."""
    accept = request.headers.get("accept", "").lower()
    for item in accept.split(","):
        media = item.split(";")[0].strip()
        if media in wire.MSGPACK_TYPES:
            return media
        if media == wire.JSON:
            return wire.JSON
    return request_media


async def read_body(request: Request, max_bytes: int, timeout_s: float) -> bytes:
    """The whole body, refusing (413) more than ``max_bytes`` before reading it where possible,
    and (408) a body whose next part has not arrived ``timeout_s`` seconds after the previous
    one (nginx's ``client_body_timeout``): a stalled upload must not hold its connection forever."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > max_bytes:
        raise Problem(413, "body-too-large",
                      f"body of {int(declared)} bytes exceeds max_body_bytes={max_bytes}")
    chunks, size = [], 0
    receive = request.receive
    while True:
        message = await _receive_within(receive, timeout_s, size)
        if message["type"] == "http.disconnect":  # a killed simulator mid-upload: not a 500
            raise Problem(499, "client-closed", f"the client disconnected after {size} bytes of "
                                                "the body")
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > max_bytes:
            raise Problem(413, "body-too-large", f"body exceeds max_body_bytes={max_bytes}",
                          {"Connection": "close"})
        chunks.append(chunk)
        if not message.get("more_body", False):
            return chunks[0] if len(chunks) == 1 else b"".join(chunks)


async def _receive_within(receive, timeout_s: float, size: int) -> dict:
    """The next ASGI message, or 408 after ``timeout_s``. A timer that cancels this task (not a
    ``wait_for`` task per chunk: the hot route reads most bodies in one message)."""
    task = asyncio.current_task()
    fired = []

    def expire():
        fired.append(True)
        task.cancel()

    timer = asyncio.get_running_loop().call_later(timeout_s, expire)
    try:
        return await receive()
    except asyncio.CancelledError:
        if not fired:
            raise
        if hasattr(task, "uncancel"):  # Python >= 3.11: this cancellation is handled here
            task.uncancel()
        raise Problem(408, "body-timeout", f"no part of the body arrived for {timeout_s:g} s "
                                           f"(after {size} bytes); body_timeout_s={timeout_s:g}",
                      {"Connection": "close"}) from None
    finally:
        timer.cancel()


def parse_body(data: bytes, media: str) -> dict:
    try:
        return wire.loads(data, media)
    except wire.WireError as exc:
        raise Problem(400, "malformed-body", str(exc)) from None


def encode_response(body: dict, media: str, status: int = 200) -> Response:
    """``body`` (numpy arrays allowed as values) as msgpack or JSON."""
    return Response(wire.dumps(body, media), status_code=status, media_type=media)


@dataclass
class QuerySpec:
    """A validated query. points : (n, 3) float32/float64 world frame; pose : collider -> world;
    eps : world units or None (the collider's default); deadline_ms : relative, or None."""

    points: np.ndarray
    fields: tuple[str, ...]
    pose: Pose
    eps: float | None
    deadline_ms: float | None
    only_colliding: bool = False  # normal/contact only where distance < eps (collider.py)


@dataclass
class SceneSpec:
    points: np.ndarray
    colliders: list[tuple[str, Pose]]
    fields: tuple[str, ...]
    eps: float | None
    deadline_ms: float | None
    only_colliding: bool = False


def _check_keys(body: dict, allowed: frozenset, required: tuple[str, ...]) -> None:
    unknown = sorted(set(body) - allowed)
    if unknown:
        raise Problem(422, "unknown-key", f"unknown key(s) {unknown}; valid keys are {sorted(allowed)}")
    for key in required:
        if key not in body:
            raise Problem(422, f"missing-{key}", f"the body has no {key!r}")


def parse_points(value, max_points: int) -> np.ndarray:
    """(n, 3) float32/float64, finite; 413 beyond ``max_points``."""
    try:
        array = wire.decode_array(value, "points")
    except wire.WireError as exc:
        raise Problem(422, "bad-points", str(exc)) from None
    if array.dtype.kind == "b" or (array.size and array.dtype not in (np.float32, np.float64)):
        raise Problem(422, "bad-points", f"points must be float32 or float64, got {array.dtype}")
    if array.ndim == 1 and array.size == 0:
        array = array.reshape(0, 3).astype(np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise Problem(422, "bad-points", f"points must have shape (n, 3), got {list(array.shape)}")
    if len(array) > max_points:
        raise Problem(413, "too-many-points",
                      f"{len(array)} points exceed max_request_points={max_points}")
    try:
        return check_points(array)
    except ValueError as exc:
        raise Problem(422, "bad-points", str(exc)) from None


def parse_pose(value, where: str = "pose") -> Pose:
    if value is None:
        return as_pose(None)
    try:
        matrix = wire.decode_array(value, where)
        if matrix.dtype.kind == "b":
            raise PoseError(f"must hold numbers, got {matrix.dtype}")
        return as_pose(matrix)
    except (wire.WireError, PoseError) as exc:
        message = str(exc)
        raise Problem(422, "bad-pose", message if message.startswith(where) else f"{where}: {message}") from None


def parse_fields(value) -> tuple[str, ...]:
    if value is None:
        return ("distance",)
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise Problem(422, "bad-fields", f"fields must be a list of strings, got {value!r}")
    try:
        return check_fields(value)
    except ValueError as exc:
        raise Problem(422, "unknown-field", str(exc)) from None


def parse_number(value, name: str, positive: bool = False, code: str | None = None) -> float | None:
    """``value`` as a finite float (``None`` stays ``None``); else 422 ``code`` (default
    ``bad-<name>``) naming ``name``."""
    if value is None:
        return None
    code = code or f"bad-{name.replace('_', '-')}"
    number = None
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        try:
            number = float(value)
        except OverflowError:  # a JSON integer with hundreds of digits
            number = None
    if number is None or not math.isfinite(number):
        raise Problem(422, code, f"{name} must be a finite number, got {value!r:.60}")
    if positive and number <= 0:
        raise Problem(422, code, f"{name} must be > 0, got {value!r}")
    return number


def parse_only_colliding(value) -> bool:
    """The ``only_colliding`` flag: absent is false; anything but a boolean is 422."""
    if value is None:
        return False
    if not isinstance(value, bool):
        raise Problem(422, "bad-only-colliding", f"only_colliding must be true or false, got {value!r:.60}")
    return value


def parse_deadline(body: dict, request: Request) -> float | None:
    """The smaller of the ``deadline_ms`` field and the ``X-Deadline-Ms`` header, milliseconds."""
    deadlines = [parse_number(body.get("deadline_ms"), "deadline_ms", positive=True)]
    header = request.headers.get(DEADLINE_HEADER)
    if header is not None:
        try:
            value = float(header)
        except ValueError:
            raise Problem(422, "bad-deadline-ms", f"X-Deadline-Ms must be a number, got {header!r}") from None
        deadlines.append(parse_number(value, "X-Deadline-Ms", positive=True, code="bad-deadline-ms"))
    given = [d for d in deadlines if d is not None]
    return min(given) if given else None


def parse_query(body: dict, request: Request, max_points: int) -> QuerySpec:
    _check_keys(body, QUERY_KEYS, ("points",))
    return QuerySpec(
        points=parse_points(body["points"], max_points),
        fields=parse_fields(body.get("fields")),
        pose=parse_pose(body.get("pose")),
        eps=parse_number(body.get("eps"), "eps"),
        deadline_ms=parse_deadline(body, request),
        only_colliding=parse_only_colliding(body.get("only_colliding")),
    )


def parse_scene(body: dict, request: Request, max_points: int, max_colliders: int) -> SceneSpec:
    _check_keys(body, SCENE_KEYS, ("points", "colliders"))
    items = body["colliders"]
    if not isinstance(items, list) or not items:
        raise Problem(422, "bad-colliders", "colliders must be a non-empty list of "
                                            "{\"model\": name, \"pose\": 4x4 (optional)}")
    if len(items) > max_colliders:
        raise Problem(413, "too-many-colliders",
                      f"{len(items)} colliders exceed max_scene_colliders={max_colliders}")
    colliders = []
    for i, item in enumerate(items):
        if not isinstance(item, dict) or not isinstance(item.get("model"), str) or (
                set(item) - {"model", "pose"}):
            raise Problem(422, "bad-colliders", f"colliders[{i}] must be {{\"model\": name, "
                                                f"\"pose\": 4x4 (optional)}}, got {item!r:.200}")
        colliders.append((item["model"], parse_pose(item.get("pose"), f"colliders[{i}].pose")))
    return SceneSpec(
        points=parse_points(body["points"], max_points),
        colliders=colliders,
        fields=parse_fields(body.get("fields")),
        eps=parse_number(body.get("eps"), "eps"),
        deadline_ms=parse_deadline(body, request),
        only_colliding=parse_only_colliding(body.get("only_colliding")),
    )
