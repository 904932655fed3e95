"""The I/O-free half of the clients: the per-call defaults, the typed refusals, response
decoding and the retry policy.

:class:`~collider_client.Client` and :class:`~collider_client.AsyncClient` share all of this and
differ only in how the bytes travel. Queries are validated and their bodies written by the
contract (:class:`collider_contract.ModelQuery`, :class:`~collider_contract.SceneQuery`), the same
rules the service and the embedded backend apply.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from email.utils import parsedate_to_datetime
from typing import Any

from collider_contract import ModelInfo, QueryError, QueryResult, wire

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


#: How a try failed before an answer came, as the transport loops classify it:
#: ``REFUSED``: no connection was made, nothing was sent (safe to retry any request);
#: ``CUT``: the connection closed or was reset before the whole answer came (a replica killed
#: mid-answer, an idle keep-alive connection closed by a restart as the request went out): the
#: server may have acted on it, so only an idempotent request is retried;
#: ``OTHER``: anything else (a timeout, a TLS or proxy failure): raised at once.
REFUSED, CUT, OTHER = "refused", "cut", "other"


class Attempts:
    """The retry loop's decisions, shared by :class:`~collider_client.Client` and
    :class:`~collider_client.AsyncClient` (which only send and sleep): after each try, either
    the answer, or how long to wait before the next try, or the error to raise.

    A refused connection and a 429/503 answer are retried ``policy.max_retries`` times with
    backoff (``Retry-After`` honoured); so is a cut connection when the request is
    ``idempotent`` (queries and listings are; admin calls are not); other transport failures and
    errors are raised at once. All retries of one call share the same budget.
    """

    def __init__(self, policy: RetryPolicy, url: str, idempotent: bool):
        self.policy = policy
        self.url = url
        self.idempotent = idempotent
        self.attempt = 0

    def _next_delay(self, retry_after_s: float | None) -> float | None:
        if self.attempt >= self.policy.max_retries:
            return None
        delay = self.policy.delay_s(self.attempt, retry_after_s)
        self.attempt += 1
        return delay

    def after_transport_error(self, failure: str, error: Exception) -> float:
        """The pause before the next try after a transport ``failure`` (:data:`REFUSED`,
        :data:`CUT` or :data:`OTHER`); raises ``error`` when it is not worth another try or no
        try is left."""
        retryable = failure == REFUSED or (failure == CUT and self.idempotent)
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


def refusal(error: QueryError) -> ServerError:
    """The typed exception of a query the contract refused: the one the service's problem
    document for it raises (same class, status, title, type and message)."""
    return error_for_status(error.status, error.detail, title=error.title, type=error.code)


def decode_query(body: dict[str, Any], fields: Iterable[str], scene: bool) -> QueryResult:
    """A :class:`QueryResult` from a decoded response body; ProtocolError if a field is missing."""
    try:
        return QueryResult.from_body(body, fields, scene)
    except wire.WireError as exc:
        raise ProtocolError(str(exc)) from None


def decode_models(body: dict[str, Any]) -> list[ModelInfo]:
    models = body.get("models")
    if not isinstance(models, list):
        raise ProtocolError("GET /v1/models: the body lacks a 'models' list")
    return [ModelInfo.from_dict(m) for m in models]
