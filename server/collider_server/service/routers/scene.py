"""``POST /v1/scene/query``: several colliders, each with its own pose; per point the nearest."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request

from ..auth import require_token
from ..bodies import (
    encode_response,
    parse_body,
    parse_scene,
    read_body,
    request_media_type,
    response_media_type,
)
from ..openapi import query_responses
from ..query_jobs import absolute_deadline, answer_scene, unless_disconnected
from ..state import get_state, serving_model

router = APIRouter(prefix="/v1/scene", tags=["scene"], dependencies=[Depends(require_token)])


@router.post("/query", summary="per point, the fields of the nearest collider and its index",
             responses=query_responses({"collider": {"type": "array",
                                                     "items": {"type": "integer"}}}))
async def scene_query(request: Request):
    state = get_state(request)
    settings = state.settings
    media = request_media_type(request)
    body = parse_body(await read_body(request, settings.max_body_bytes, settings.body_timeout_s), media)
    query, deadline_ms = parse_scene(body, request, settings.max_request_points,
                                     settings.max_scene_colliders)
    models = [serving_model(state, placed.model) for placed in query.colliders]
    deadline = absolute_deadline(deadline_ms, settings.default_deadline_ms)
    result = await unless_disconnected(request.receive, answer_scene(models, query, deadline))
    return encode_response(result.to_body(), response_media_type(request, media))
