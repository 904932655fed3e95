"""Admin routes (admin token): load or reload, and unload, a model while others keep serving."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request

from ...engine.modelfile import ModelFileError
from ..auth import require_admin
from ..openapi import MODEL_INFO, problems
from ..problems import Problem
from ..state import get_state

router = APIRouter(prefix="/v1/admin", tags=["admin"], dependencies=[Depends(require_admin)])


@router.put("/models/{name}", summary="load (or reload) a model from the repository",
            responses={200: {"description": "OK", "content": {"application/json": {"schema": {
                "type": "object", "required": ["loaded", "info"],
                "properties": {"loaded": {"type": "string"}, "info": MODEL_INFO}}}}},
                **problems(401, 403, 404, 422)})
async def load_model(name: str, request: Request):
    registry = get_state(request).registry
    try:
        model = await registry.load(name)
    except FileNotFoundError as exc:
        raise Problem(404, "unknown-model", str(exc)) from None
    except ModelFileError as exc:
        raise Problem(422, "bad-model-file", str(exc)) from None
    except ValueError as exc:
        raise Problem(422, "bad-model-name", str(exc)) from None
    return {"loaded": name, "info": model.info.to_dict()}


@router.delete("/models/{name}", summary="unload a model (queued requests are still answered)",
               responses=problems(401, 403, 404))
async def unload_model(name: str, request: Request):
    if not await get_state(request).registry.unload(name):
        raise Problem(404, "unknown-model", f"no model named {name!r} is loaded")
    return {"unloaded": name}
