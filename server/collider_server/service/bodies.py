"""Request and response bodies: media types, size limits, reading and encoding.

The bodies follow :mod:`collider_contract.wire` (msgpack maps of raw little-endian bytes, or JSON
nested lists); their query keys are read by the contract's :class:`ModelQuery` and
:class:`SceneQuery` (``from_body``), the same rules the SDK and the engine apply. Status codes:
400 a body that cannot be parsed, 413 too large, 415 a media type that is neither msgpack nor
JSON, 422 a parsed body whose values are wrong (a :class:`~collider_contract.QueryError`).
"""

from __future__ import annotations

import asyncio

from starlette.requests import Request
from starlette.responses import Response

from collider_contract import ModelQuery, SceneQuery, wire
from collider_contract.queries import check_number, read_deadline_ms

from .problems import Problem

DEADLINE_HEADER = "x-deadline-ms"


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
        # Closed after the answer: the unread body must not be taken for the next request.
        raise Problem(413, "body-too-large",
                      f"body of {int(declared)} bytes exceeds max_body_bytes={max_bytes}",
                      {"Connection": "close"})
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


def parse_deadline(body: dict, request: Request) -> float | None:
    """The smaller of the ``deadline_ms`` field and the ``X-Deadline-Ms`` header, milliseconds."""
    deadlines = [read_deadline_ms(body)]
    header = request.headers.get(DEADLINE_HEADER)
    if header is not None:
        try:
            value = float(header)
        except ValueError:
            raise Problem(422, "bad-deadline-ms", f"X-Deadline-Ms must be a number, got {header!r}") from None
        deadlines.append(check_number(value, "X-Deadline-Ms", positive=True, code="bad-deadline-ms"))
    given = [d for d in deadlines if d is not None]
    return min(given) if given else None


def parse_query(body: dict, request: Request, max_points: int) -> tuple[ModelQuery, float | None]:
    """The model query of a decoded body (the contract's rules: :meth:`ModelQuery.from_body`)
    and its deadline, ms or None."""
    return ModelQuery.from_body(body, max_points), parse_deadline(body, request)


def parse_scene(body: dict, request: Request, max_points: int,
                max_colliders: int) -> tuple[SceneQuery, float | None]:
    """The scene query of a decoded body (:meth:`SceneQuery.from_body`) and its deadline."""
    return SceneQuery.from_body(body, max_points, max_colliders), parse_deadline(body, request)
