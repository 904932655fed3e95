"""The I/O-free half of the clients: request building, response decoding, the retry policy.

:class:`~collider_client.Client` and :class:`~collider_client.AsyncClient` share all of this and
differ only in how the bytes travel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from email.utils import parsedate_to_datetime
from typing import Any, Sequence

import numpy as np

from collider_contract import ModelInfo, QueryResult, wire

from ._exceptions import ProtocolError, ServerError, error_for_status

#: Statuses worth another try after a pause: the server is busy or (re)starting.
RETRY_STATUSES = frozenset({429, 503})


class UseClientDefault:
    """Type of :data:`USE_CLIENT_DEFAULT`: "not given", which is not the same as ``None``
    (``eps=None`` asks for the model's own default of 1 mm)."""

    _instance = None

    def __new__(cls):
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "USE_CLIENT_DEFAULT"


USE_CLIENT_DEFAULT = UseClientDefault()


@dataclass(frozen=True)
class SceneCollider:
    """One collider of a scene query: a model name and its pose (4x4, collider -> world, or None)."""

    model: str
    pose: np.ndarray | None = None


@dataclass(frozen=True)
class RetryPolicy:
    """How often and how long to wait on 429/503 and on connection failures.

    max_retries : further tries after the first
    backoff_s : first pause; doubles per try up to ``max_backoff_s``; a server's ``Retry-After``
        (seconds) is honoured when longer than the backoff (capped at ``max_backoff_s`` too, so a
        caller is never parked for minutes)
    """

    max_retries: int = 3
    backoff_s: float = 0.05
    max_backoff_s: float = 5.0

    def __post_init__(self):
        if self.max_retries < 0:
            raise ValueError(f"max_retries must be >= 0, got {self.max_retries}")
        if not (self.backoff_s >= 0 and self.max_backoff_s >= 0):
            raise ValueError("backoff_s and max_backoff_s must be >= 0")

    def delay_s(self, attempt: int, retry_after_s: float | None) -> float:
        """Seconds to wait before try ``attempt + 1`` (``attempt`` counts from 0)."""
        delay = self.backoff_s * (2.0 ** attempt)
        if retry_after_s is not None:
            delay = max(delay, retry_after_s)
        return min(delay, self.max_backoff_s)


class Attempts:
    """The retry loop's decisions, shared by :class:`~collider_client.Client` and
    :class:`~collider_client.AsyncClient` (which only send and sleep): after each try, either
    the answer, or how long to wait before the next try, or the error to raise.

    A refused connection and a 429/503 answer are retried ``policy.max_retries`` times with
    backoff (``Retry-After`` honoured); other transport failures and errors are raised at once.
    """

    def __init__(self, policy: RetryPolicy, url: str):
        self.policy = policy
        self.url = url
        self.attempt = 0

    def _next_delay(self, retry_after_s: float | None) -> float | None:
        if self.attempt >= self.policy.max_retries:
            return None
        delay = self.policy.delay_s(self.attempt, retry_after_s)
        self.attempt += 1
        return delay

    def after_transport_error(self, exc: Exception, retryable: bool, error: Exception) -> float:
        """The pause before the next try after a transport failure ``exc``; raises ``error``
        when it is not ``retryable`` (only a refused connection is) or no try is left."""
        delay = self._next_delay(None) if retryable else None
        if delay is None:
            raise error from None
        return delay

    def after_answer(self, status: int, content: bytes, content_type: str,
                     retry_after: str | None) -> tuple[dict[str, Any] | None, float]:
        """``(body, 0)`` for a success; ``(None, pause)`` for a 429/503 worth another try;
        else raises the typed error (:func:`raise_for_problem`)."""
        if status < 400:
            return decode_body(content, content_type, self.url), 0.0
        try:
            raise_for_problem(status, content, content_type, retry_after)
        except ServerError as exc:
            delay = self._next_delay(exc.retry_after_s) if status in RETRY_STATUSES else None
            if delay is None:
                raise
            return None, delay
        raise AssertionError("raise_for_problem returned")  # pragma: no cover


def decode_body(content: bytes, content_type: str, where: str) -> dict[str, Any]:
    """A success response's body; ProtocolError when it does not parse."""
    try:
        return wire.loads(content, content_type)
    except wire.WireError as exc:
        raise ProtocolError(f"{where}: {exc}") from None


def parse_retry_after(value: str | None) -> float | None:
    """``Retry-After`` as seconds: delta-seconds or an HTTP date; ``None`` when absent/unreadable."""
    if not value:
        return None
    try:
        seconds = float(value)
    except ValueError:
        try:
            import datetime as _dt

            when = parsedate_to_datetime(value)
            seconds = (when - _dt.datetime.now(when.tzinfo)).total_seconds()
        except (TypeError, ValueError):
            return None
    return max(0.0, seconds) if math.isfinite(seconds) else None


def as_points(points) -> np.ndarray:
    """Points as float32/float64 numpy (ints become float64); shape is checked by the backend."""
    array = np.asarray(points)
    if array.dtype not in (np.float32, np.float64):
        array = array.astype(np.float64)
    return array


def as_scene(colliders: Sequence) -> list[SceneCollider]:
    """Scene colliders from :class:`SceneCollider`, ``(model, pose)`` pairs, dicts or names."""
    out = []
    for i, item in enumerate(colliders):
        if isinstance(item, SceneCollider):
            out.append(item)
        elif isinstance(item, str):
            out.append(SceneCollider(item))
        elif isinstance(item, dict):
            if "model" not in item:
                raise ValueError(f"colliders[{i}]: a dict needs a 'model' key, got {sorted(item)}")
            out.append(SceneCollider(item["model"], item.get("pose")))
        elif isinstance(item, (tuple, list)) and len(item) == 2:
            out.append(SceneCollider(item[0], item[1]))
        else:
            raise ValueError(f"colliders[{i}]: expected a model name, (model, pose) or "
                             f"{{'model': ..., 'pose': ...}}, got {type(item).__name__}")
    if not out:
        raise ValueError("a scene query needs at least one collider")
    return out


def query_body(points: np.ndarray, fields: list[str], pose, eps: float | None,
               deadline_ms: float | None, only_colliding: bool = False) -> dict[str, Any]:
    body: dict[str, Any] = {"points": points, "fields": fields}
    if only_colliding:  # sent only when set: a body without it is what older servers know
        body["only_colliding"] = True
    if pose is not None:
        body["pose"] = np.asarray(pose, dtype=np.float64)
    if eps is not None:
        body["eps"] = float(eps)
    if deadline_ms is not None:
        body["deadline_ms"] = float(deadline_ms)
    return body


def scene_body(points: np.ndarray, colliders: list[SceneCollider], fields: list[str],
               eps: float | None, deadline_ms: float | None,
               only_colliding: bool = False) -> dict[str, Any]:
    body = query_body(points, fields, None, eps, deadline_ms, only_colliding)
    # A pose nested in a list travels as nested lists: wire.dumps only encodes top-level arrays.
    body["colliders"] = [
        {"model": c.model} if c.pose is None
        else {"model": c.model, "pose": np.asarray(c.pose, dtype=np.float64).tolist()}
        for c in colliders
    ]
    return body


def raise_for_problem(status: int, content: bytes, content_type: str,
                      retry_after: str | None) -> None:
    """Raise the typed error for an error response (``application/problem+json`` or other)."""
    title, detail, type_ = "", "", "about:blank"
    if "json" in (content_type or ""):
        try:
            problem = wire.loads(content, wire.JSON)
            title = str(problem.get("title", ""))
            detail = str(problem.get("detail", ""))
            type_ = str(problem.get("type", type_))
        except wire.WireError:
            pass
    if not detail:
        detail = content[:500].decode("utf-8", "replace") or "(no message)"
    raise error_for_status(status, detail, title=title, type=type_,
                           retry_after_s=parse_retry_after(retry_after))


def decode_query(body: dict[str, Any], fields: list[str], scene: bool) -> QueryResult:
    """A :class:`QueryResult` from a decoded response body; ProtocolError if a field is missing."""
    result = QueryResult(model=body.get("model") if not scene else None)
    try:
        for name in fields:
            if name not in body:
                raise ProtocolError(f"response lacks the field {name!r} that was asked for")
            setattr(result, name, wire.decode_array(body[name], name))
        if scene:
            if "collider" not in body:
                raise ProtocolError("scene response lacks 'collider'")
            result.collider = wire.decode_array(body["collider"], "collider")
    except wire.WireError as exc:
        raise ProtocolError(str(exc)) from None
    # JSON answers come as nested lists; give them the dtypes the wire format promises.
    if result.collides is not None and result.collides.dtype != np.bool_:
        result.collides = result.collides.astype(bool)
    for name in ("distance", "normal"):
        value = getattr(result, name)
        if value is not None and value.dtype != np.float32:
            setattr(result, name, value.astype(np.float32))
    if result.collider is not None and result.collider.dtype != np.int32:
        result.collider = result.collider.astype(np.int32)
    return result


def decode_models(body: dict[str, Any]) -> list[ModelInfo]:
    models = body.get("models")
    if not isinstance(models, list):
        raise ProtocolError("GET /v1/models: the body lacks a 'models' list")
    return [ModelInfo.from_dict(m) for m in models]
