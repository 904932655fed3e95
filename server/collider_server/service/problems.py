"""Errors as RFC 9457 problem documents: ``application/problem+json`` bodies
``{"type": short-code, "title": ..., "status": N, "detail": what is wrong and where}``."""

from __future__ import annotations

import json
import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import Response

from collider_contract import TITLES, QueryError

PROBLEM_JSON = "application/problem+json"
log = logging.getLogger("collider_server.service")

class Problem(Exception):
    """An error answer: ``status`` code, ``type`` short code (e.g. ``"bad-points"``), ``detail``
    saying what is wrong and where, and extra response ``headers`` (``Retry-After``)."""

    def __init__(self, status: int, type: str, detail: str, headers: dict[str, str] | None = None):
        super().__init__(detail)
        self.status = status
        self.type = type
        self.detail = detail
        self.headers = headers or {}

    @classmethod
    def of(cls, error: QueryError) -> Problem:
        """The problem document of a query the contract refused (same status, code, detail)."""
        return cls(error.status, error.code, error.detail)

    @property
    def title(self) -> str:
        return TITLES.get(self.status, "Error")

    def document(self) -> bytes:
        """The ``application/problem+json`` body."""
        return json.dumps({"type": self.type, "title": self.title, "status": self.status,
                           "detail": self.detail}).encode()

    def response(self) -> Response:
        return Response(self.document(), status_code=self.status, headers=self.headers,
                        media_type=PROBLEM_JSON)


def allowed_methods(request: Request) -> list[str]:
    """Every method some route serves at the request's path (for a 405's ``Allow``): Starlette
    names only the methods of the first route matching the path."""
    from starlette.routing import Match

    routes = request.app.router.routes
    return [method for method in ("GET", "HEAD", "POST", "PUT", "DELETE", "PATCH")
            if any(route.matches({**request.scope, "method": method})[0] == Match.FULL
                   for route in routes)]


def install_handlers(app: FastAPI) -> None:
    """Every error the app can produce, including unknown routes and crashes, as a problem."""

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem):
        return exc.response()

    @app.exception_handler(QueryError)
    async def _refused(request: Request, exc: QueryError):
        return Problem.of(exc).response()

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        code = {404: "not-found", 405: "method-not-allowed"}.get(exc.status_code, "http-error")
        detail = exc.detail if isinstance(exc.detail, str) else json.dumps(exc.detail)
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"no route {request.method} {request.url.path}"
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            # Starlette names the methods of the first route matching the path only.
            allowed = allowed_methods(request)
            headers["Allow"] = ", ".join(allowed)
            detail = f"{request.method} is not allowed on {request.url.path}; use {', '.join(allowed)}"
        return Problem(exc.status_code, code, detail, headers).response()

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        detail = "; ".join(
            f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        return Problem(422, "invalid-request", detail).response()

    @app.exception_handler(Exception)
    async def _crash(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return Problem(500, "internal-error", f"{type(exc).__name__}: {exc}").response()
