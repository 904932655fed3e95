"""``/livez``, ``/readyz`` (no auth) and ``/metrics`` (Prometheus text format)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from starlette.responses import JSONResponse, PlainTextResponse, Response

from ..auth import require_token
from ..openapi import problems
from ..state import get_state

router = APIRouter(tags=["health"])

_READY = {"type": "object", "required": ["status", "models", "errors"], "properties": {
    "status": {"enum": ["ready", "loading", "shutting-down"]},
    "models": {"type": "array", "items": {"type": "string"}},
    "errors": {"type": "object", "additionalProperties": {"type": "string"}}}}


@router.get("/livez", summary="the process is up", responses={200: {"content": {
    "application/json": {"schema": {"type": "object", "properties": {"status": {"const": "ok"}}}}}}})
async def livez():
    return {"status": "ok"}


@router.get("/readyz", summary="ready once every model is loaded and warmed up", responses={
    200: {"content": {"application/json": {"schema": _READY}}},
    503: {"description": "loading or shutting down (Retry-After)",
          "content": {"application/json": {"schema": _READY}}}})
async def readyz(request: Request):
    state = get_state(request)
    registry = state.registry
    body = {"models": sorted(registry.models), "errors": registry.errors}
    if state.shutting_down:
        return JSONResponse({"status": "shutting-down", **body}, 503, {"Retry-After": "5"})
    if not registry.ready:
        return JSONResponse({"status": "loading", **body}, 503, {"Retry-After": "1"})
    return {"status": "ready", **body}


@router.get("/metrics", summary="Prometheus metrics (text format)",
            dependencies=[Depends(require_token)], response_class=PlainTextResponse,
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}},
                       **problems(401)})
async def metrics(request: Request):
    data, content_type = get_state(request).metrics.render()
    return Response(data, media_type=content_type)
