"""A shortcut for the hot route: ``POST /v1/models/{name}/query`` handled straight from ASGI.

The route's own function (:func:`routers.models.query`) answers it, with the same auth check;
only FastAPI's per-request machinery (route matching over every route, dependency solving, the
exit stack) is skipped. With 1,000-point voxel queries that machinery is a sizeable part of the
event loop's time per request, and the event loop's time per request is what limits coalescing
on a CPU. The FastAPI route stays registered for the OpenAPI page and answers when the fast path
is off (``query_fast_path=False``).

Equivalence is guarded twice: the app refuses to start when the route has dependencies other
than the ones this shortcut runs (so a dependency added to the router is never silently skipped
here), and a test sends the same requests through both paths and compares the answers.
"""

from __future__ import annotations

import re
from types import SimpleNamespace

from starlette.requests import Request

from collider_contract import QueryError

from .auth import require_token
from .problems import Problem
from .routers import models

QUERY_PATH = re.compile(r"^/v1/models/(.+)/query$")  # as the route's {name:path}
ROUTE = SimpleNamespace(path_format="/v1/models/{name}/query")


#: The dependencies the shortcut runs, in order, exactly as the router declares them.
FAST_PATH_DEPENDENCIES = (require_token,)


def check_equivalent(router=models.router) -> None:
    """RuntimeError unless the query route's dependencies are :data:`FAST_PATH_DEPENDENCIES`."""
    route = next(r for r in router.routes if getattr(r, "path_format", "").endswith("/{name}/query"))
    declared = tuple(d.dependency for d in route.dependencies)  # the router's come first
    if declared != FAST_PATH_DEPENDENCIES:
        names = [getattr(d, "__name__", repr(d)) for d in declared]
        raise RuntimeError(
            f"the query route's dependencies are {names}, but service/fastpath.py runs "
            f"{[d.__name__ for d in FAST_PATH_DEPENDENCIES]}: teach the fast path the new ones")


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
            for dependency in FAST_PATH_DEPENDENCIES:
                await dependency(request)
            response = await models.query(match.group(1), request)
        except Problem as exc:
            response = exc.response()
        except QueryError as exc:
            response = Problem.of(exc).response()
        await response(scope, receive, send)
