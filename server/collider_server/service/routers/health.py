"""``/livez``, ``/readyz`` (no auth) and ``/metrics`` (Prometheus text format)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from starlette.responses import JSONResponse, Response

from ..auth import require_token
from ..state import get_state

router = APIRouter(tags=["health"])


@router.get("/livez", summary="the process is up")
async def livez():
    return {"status": "ok"}


@router.get("/readyz", summary="ready once every model is loaded and warmed up")
async def readyz(request: Request):
    state = get_state(request)
    registry = state.registry
    body = {"models": sorted(registry.models), "errors": registry.errors}
    if state.shutting_down:
        return JSONResponse({"status": "shutting-down", **body}, 503, {"Retry-After": "5"})
    if not registry.ready:
        return JSONResponse({"status": "loading", **body}, 503, {"Retry-After": "1"})
    return {"status": "ready", **body}


@router.get("/metrics", summary="Prometheus metrics", dependencies=[Depends(require_token)])
async def metrics(request: Request):
    data, content_type = get_state(request).metrics.render()
    return Response(data, media_type=content_type)
