"""Bearer-token checks (FastAPI dependencies). Tokens are compared in constant time."""

from __future__ import annotations

import hmac

from fastapi import Request

from .problems import Problem


def _bearer(request: Request) -> str | None:
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def _check(request: Request, expected: str, what: str) -> None:
    token = _bearer(request)
    if token is None:
        raise Problem(401, "unauthorized", f"{what}: send 'Authorization: Bearer <token>'",
                      {"WWW-Authenticate": "Bearer"})
    if not hmac.compare_digest(token.encode(), expected.encode()):
        raise Problem(401, "unauthorized", f"{what}: the bearer token is not valid",
                      {"WWW-Authenticate": 'Bearer error="invalid_token"'})


async def require_token(request: Request) -> None:
    """The service token (``COLLIDER_TOKEN``), when one is set. (``async`` so FastAPI runs it on
    the event loop: a plain ``def`` dependency costs a thread hop per request.)"""
    expected = request.app.state.collider.settings.token
    if expected:
        _check(request, expected, "this route needs the service token")


async def require_admin(request: Request) -> None:
    """The admin token (``COLLIDER_ADMIN_TOKEN``); admin routes are off when it is unset."""
    expected = request.app.state.collider.settings.admin_token
    if not expected:
        raise Problem(403, "admin-disabled",
                      "admin routes are disabled; start the server with COLLIDER_ADMIN_TOKEN set")
    _check(request, expected, "admin routes need the admin token")
