"""The FastAPI application: wiring only (routers, error handlers, metrics, lifespan)."""

from __future__ import annotations

import asyncio
import contextlib
import copy
import functools
import logging

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from ..engine.devices import resolve_device
from ..engine.memory import hold_freed_memory
from ..engine.repository import ModelRepository
from .batching import DeviceWorkers
from .connections import ConnectionGuard
from .fastpath import QueryFastPath, check_equivalent
from .heap import settle_heap
from .metrics import RequestObserver, ServiceMetrics
from .openapi import add_security, query_body, scene_body, with_examples
from .openapi import router as docs_router
from .problems import install_handlers
from .query_jobs import answer_batch
from .registry import ModelRegistry
from .routers import admin, health, models, scene
from .settings import ServiceSettings
from .state import ServiceState

log = logging.getLogger("collider_server.service")

DESCRIPTION = """Signed distance, normal, contact and collision answers for batches of points.

Bodies are msgpack (`application/msgpack`, the fast path) or JSON. Arrays in msgpack are maps
`{dtype, shape, data}` with raw little-endian bytes; in JSON, nested lists. Lengths are in the
collider's units (metres for the shipped models), points and answers in the world frame, a pose
maps the collider frame to the world frame. Errors are `application/problem+json`."""


def set_compute_threads(threads: int) -> None:
    """torch's CPU thread count (for the calling thread, and torch's default)."""
    import torch

    torch.set_num_threads(threads)


def openapi_schema(app: FastAPI, settings: ServiceSettings) -> dict:
    """The OpenAPI document, with the hand-written query bodies sized by ``settings`` and, as
    examples, the first model served now (models load and unload while the server runs)."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description,
                             routes=app.routes)
        paths = schema["paths"]
        paths["/v1/models/{name}/query"]["post"].update(query_body(settings.max_request_points))
        paths["/v1/scene/query"]["post"].update(
            scene_body(settings.max_request_points, settings.max_scene_colliders))
        add_security(schema)
        app.openapi_schema = schema
    state = getattr(app.state, "collider", None)
    served = sorted(state.registry.models) if state is not None else []
    return with_examples(copy.deepcopy(app.openapi_schema), served[0] if served else None)


def create_app(settings: ServiceSettings | None = None) -> FastAPI:
    """The service for ``settings``. Models load in the background after start-up;
    ``/readyz`` answers 200 once all are loaded and warmed up."""
    settings = settings or ServiceSettings()
    metrics = ServiceMetrics()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        if settings.hold_freed_memory:
            held = hold_freed_memory()
            if held:
                log.info("freed arrays up to %d MiB are kept for the next batches (glibc)", held >> 20)
            else:
                log.info("freed memory goes back to the system (not glibc, or MALLOC_* / GLIBC_TUNABLES set)")
        threads = settings.resolved_compute_threads()
        # Set from the compute thread itself: with OpenMP the count can be a per-thread setting.
        workers = DeviceWorkers(functools.partial(set_compute_threads, threads))
        registry = ModelRegistry(ModelRepository(settings.models), resolve_device(settings.device),
                                 settings.batch_settings(), workers, metrics, answer_batch,
                                 settings.warmup)
        state = ServiceState(settings, metrics, workers, registry)
        app.state.collider = state
        # What is alive once the models are loaded lives as long as the process (.heap).
        loading = asyncio.create_task(registry.load_all(before_ready=settle_heap))
        try:
            yield
        finally:
            # uvicorn has stopped accepting and answered every open request by now.
            state.shutting_down = True
            loading.cancel()
            await registry.close()
            await asyncio.to_thread(workers.shutdown)
            log.info("stopped")

    # /docs and /openapi.json are routes of our own: the schema behind the token, the page's
    # script and styles from the installed swagger-ui-bundle (no CDN).
    app = FastAPI(title="neural-collider", version="1", description=DESCRIPTION, lifespan=lifespan,
                  docs_url=None, redoc_url=None, openapi_url=None)
    app.openapi = functools.partial(openapi_schema, app, settings)
    # Read by the HTTP server's protocol (connections.uvicorn_config), before any request.
    app.state.connections = ConnectionGuard(settings.max_connections, settings.header_timeout_s,
                                            metrics)
    install_handlers(app)
    for router in (health.router, models.router, scene.router, admin.router, docs_router):
        app.include_router(router)
    if settings.query_fast_path:
        check_equivalent()  # here, not when Starlette builds the stack at the first request
        app.add_middleware(QueryFastPath)
    if settings.cors_origins:
        from fastapi.middleware.cors import CORSMiddleware

        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "POST", "PUT", "DELETE"],
                           allow_headers=["Authorization", "Content-Type", "X-Deadline-Ms"])
    app.add_middleware(RequestObserver, metrics=metrics)
    return app
