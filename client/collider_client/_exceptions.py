"""Every error the client raises, under one root.

The tree::

    ColliderError                  root: catch this to catch everything below
    ├── TransportError             no usable HTTP answer came back
    │   ├── ConnectError           the server could not be reached
    │   └── RequestTimeoutError    a step of a request took longer than the client's timeout_s
    ├── ProtocolError              an answer that does not follow the wire format
    └── ServerError                the server answered with an error status (has .status, .title,
        │                          .detail, .type, .retry_after_s)
        ├── BadRequestError        400  malformed body
        ├── UnauthorizedError      401  missing or wrong ``Authorization: Bearer`` token
        ├── ModelNotFoundError     404  no model of that name (also raised by the embedded backend)
        ├── PayloadTooLargeError   413  too many points in one request
        ├── UnsupportedMediaTypeError 415  content type neither msgpack nor JSON
        ├── InvalidValueError      422  values the server rejects (shape, NaN, fields, pose, eps);
        │                               the embedded backend raises it for the same inputs
        ├── QueueFullError         429  the server is saturated; retried with backoff
        ├── ServiceUnavailableError 503  not ready or shutting down; retried with backoff
        └── DeadlineExceededError  504  the request's ``deadline_ms`` passed before an answer

Statuses without a class of their own (500, ...) raise :class:`ServerError` itself.
"""

from __future__ import annotations

__all__ = [
    "BadRequestError",
    "ColliderError",
    "ConnectError",
    "DeadlineExceededError",
    "InvalidValueError",
    "ModelNotFoundError",
    "PayloadTooLargeError",
    "ProtocolError",
    "QueueFullError",
    "RequestTimeoutError",
    "ServerError",
    "ServiceUnavailableError",
    "TransportError",
    "UnauthorizedError",
    "UnsupportedMediaTypeError",
    "error_for_status",
]


class ColliderError(Exception):
    """Root of every error raised by :mod:`collider_client`."""


class TransportError(ColliderError):
    """No usable HTTP answer came back (connection refused, reset, timed out)."""


class ConnectError(TransportError):
    """The server could not be reached at the client's URL."""


class RequestTimeoutError(TransportError):
    """One step of a request took longer than the client's ``timeout_s``: connecting, sending,
    waiting for the answer's next bytes, or waiting for a free pooled connection (httpx's
    ``TimeoutException``: ``ConnectTimeout``, ``WriteTimeout``, ``ReadTimeout``,
    ``PoolTimeout``). Each step has the limit on its own, so a whole request may take longer.
    Not retried: the server may still be at work. (Not Python's builtin ``TimeoutError``, which
    this package does not shadow.)"""


class ProtocolError(ColliderError):
    """The server's answer does not follow the wire format (wrong content type, missing field)."""


class ServerError(ColliderError):
    """The server answered with an error status; carries its ``problem+json`` body.

    status : int, the HTTP status code
    title : short summary (``problem+json`` "title")
    detail : the server's message saying what is wrong and where ("detail")
    type : problem type URI ("type"), "about:blank" when the server gave none
    retry_after_s : seconds the server asked the client to wait (429/503), or None
    """

    status: int = 500

    def __init__(self, detail: str, *, status: int | None = None, title: str = "",
                 type: str = "about:blank", retry_after_s: float | None = None):
        if status is not None:
            self.status = status
        self.detail = detail
        self.title = title
        self.type = type
        self.retry_after_s = retry_after_s
        super().__init__(f"{self.status} {title}: {detail}" if title else f"{self.status}: {detail}")


class BadRequestError(ServerError):
    """400: the body is malformed (not msgpack/JSON, or a field of the wrong type)."""

    status = 400


class UnauthorizedError(ServerError):
    """401: the server wants ``Authorization: Bearer <token>`` (give ``token=`` to the client)."""

    status = 401


class ModelNotFoundError(ServerError):
    """404: no model of the requested name in the server's (or the embedded) repository."""

    status = 404


class PayloadTooLargeError(ServerError):
    """413: too many points in one request; split the points."""

    status = 413


class UnsupportedMediaTypeError(ServerError):
    """415: the request's content type is neither msgpack nor JSON."""

    status = 415


class InvalidValueError(ServerError):
    """422: values that cannot be answered (points not (n, 3), NaN, unknown field, bad pose, eps)."""

    status = 422


class QueueFullError(ServerError):
    """429: the server's queue is full; ``retry_after_s`` says when to come back."""

    status = 429


class ServiceUnavailableError(ServerError):
    """503: the server is not ready yet or is shutting down; ``retry_after_s`` as sent."""

    status = 503


class DeadlineExceededError(ServerError):
    """504: the request's ``deadline_ms`` passed before the server could answer."""

    status = 504


STATUS_ERRORS: dict[int, type[ServerError]] = {
    cls.status: cls
    for cls in (BadRequestError, UnauthorizedError, ModelNotFoundError, PayloadTooLargeError,
                UnsupportedMediaTypeError, InvalidValueError, QueueFullError,
                ServiceUnavailableError, DeadlineExceededError)
}


def error_for_status(status: int, detail: str, *, title: str = "", type: str = "about:blank",
                     retry_after_s: float | None = None) -> ServerError:
    """The typed exception for an HTTP error ``status`` (unknown codes give :class:`ServerError`)."""
    cls = STATUS_ERRORS.get(status, ServerError)
    return cls(detail, status=status, title=title, type=type, retry_after_s=retry_after_s)
