"""``GET /v1/models``, ``GET /v1/models/{name}``, ``POST /v1/models/{name}/query``."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request

from ...engine.repository import served_models
from ..auth import require_token
from ..bodies import (
    encode_response,
    parse_body,
    parse_query,
    read_body,
    request_media_type,
    response_media_type,
)
from ..openapi import model_info_responses, query_responses
from ..query_jobs import absolute_deadline, answer_query, unless_disconnected
from ..state import get_state, serving_model

router = APIRouter(prefix="/v1/models", tags=["models"], dependencies=[Depends(require_token)])


@router.get("", summary="the models being served", responses=model_info_responses(401, listed=True))
async def list_models(request: Request):
    return {"models": [info.to_dict() for info in served_models(get_state(request).registry.models)]}


@router.get("/{name}", summary="one model: kind, units, domain box, size, recorded accuracy, "
                               "animation", responses=model_info_responses(401, 404, 503))
async def model_info(name: str, request: Request):
    return serving_model(get_state(request), name).info.to_dict()


# ``{name:path}``: a name with "/" in it (a file path given as a name) reaches the model lookup
# and is refused as an unknown model, as the scene route and the SDK's embedded backend refuse it.
@router.post("/{name:path}/query", summary="distance / normal / contact / collides of points",
             responses=query_responses({"model": {"type": "string"}}))
async def query(name: str, request: Request):
    """Points in the world frame, an optional pose (collider -> world), the fields to return and
    eps (world units). The response holds one entry per field plus ``"model"``."""
    state = get_state(request)
    settings = state.settings
    media = request_media_type(request)
    serving_model(state, name)  # 404 / 503 before reading what may be a large body
    body = parse_body(await read_body(request, settings.max_body_bytes, settings.body_timeout_s), media)
    query, deadline_ms = parse_query(body, request, settings.max_request_points)
    # Look the model up again now: a reload while the body was arriving swapped in a new batcher
    # and closed the old one (queueing on it would answer 503). From here to the queue no await.
    model = serving_model(state, name)
    deadline = absolute_deadline(deadline_ms, settings.default_deadline_ms)
    result = await unless_disconnected(request.receive, answer_query(model, query, deadline))
    return encode_response({**result, "model": name}, response_media_type(request, media))
