"""A shortcut for the hot route: ``POST /v1/models/{name}/query`` handled straight from ASGI.

The route's own function (:func:`routers.models.query`) answers it, with the same auth check;
only FastAPI's per-request machinery (route matching over every route, dependency solving, the
exit stack) is skipped. With 1,000-point voxel queries that machinery is a sizeable part of the
event loop's time per request, and the event loop's time per request is what limits coalescing
on a CPU. The FastAPI route stays registered for the OpenAPI page.
"""

from __future__ import annotations

import re
from types import SimpleNamespace

from starlette.requests import Request

from .auth import require_token
from .problems import Problem
from .routers import models

QUERY_PATH = re.compile(r"^/v1/models/([^/]+)/query$")
ROUTE = SimpleNamespace(path="/v1/models/{name}/query")


class QueryFastPath:
    """ASGI middleware: serve the model query route directly, pass everything else on."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        match = QUERY_PATH.match(scope["path"]) if scope["type"] == "http" else None
        if match is None or scope["method"] != "POST":
            return await self.app(scope, receive, send)
        scope["route"] = ROUTE  # metrics label these requests like the FastAPI route's
        request = Request(scope, receive)
        try:
            await require_token(request)
            response = await models.query(match.group(1), request)
        except Problem as exc:
            response = exc.response()
        await response(scope, receive, send)
