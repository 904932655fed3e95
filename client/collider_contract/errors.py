"""Why a query is refused: :class:`QueryError`, one type for every backend.

A refusal carries what the HTTP service answers (``status`` and the problem ``code``, an RFC 9457
``application/problem+json`` document with :data:`TITLES`' title) and the one-line ``detail``
saying what is wrong and where. The service turns it into that document; the SDK turns it, or the
document, into the same typed exception (``collider_client.InvalidValueError`` for 422); the
engine raises it as it is (a ``ValueError``).
"""

from __future__ import annotations

#: Titles of problem documents by HTTP status, as the service sends them.
TITLES = {
    400: "Malformed request",
    401: "Unauthorized",
    403: "Forbidden",
    404: "Not found",
    405: "Method not allowed",
    408: "Request timeout",
    409: "Conflict",
    413: "Request too large",
    415: "Unsupported media type",
    422: "Invalid request",
    429: "Too many requests",
    499: "Client closed request",
    500: "Internal server error",
    503: "Service unavailable",
    504: "Deadline exceeded",
}


class QueryError(ValueError):
    """A query that cannot be answered.

    detail : what is wrong and where (the field, the row), one line
    status : the HTTP status the service answers it with (422 for values, 413 for sizes,
        404 for an unknown model)
    code : the problem type, a short code such as ``"bad-points"``
    """

    def __init__(self, detail: str, *, status: int = 422, code: str = "invalid-request"):
        super().__init__(detail)
        self.detail = detail
        self.status = status
        self.code = code

    @property
    def title(self) -> str:
        return TITLES.get(self.status, "Error")


def unknown_model(name: str, known) -> QueryError:
    """The refusal of a query for model ``name`` that is not among ``known`` (names)."""
    listed = ", ".join(sorted(known)) or "none"
    return QueryError(f"no model named {name!r} (models: {listed})", status=404, code="unknown-model")
