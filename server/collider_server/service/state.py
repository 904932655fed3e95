"""What one server process holds (the only global state, and it lives on ``app.state``)."""

from __future__ import annotations

from dataclasses import dataclass

from fastapi import Request

from collider_contract import unknown_model

from .batching import DeviceWorkers
from .metrics import ServiceMetrics
from .problems import Problem
from .registry import LoadedModel, ModelRegistry
from .settings import ServiceSettings


@dataclass
class ServiceState:
    """The app's settings, metrics, compute threads and models; ``shutting_down`` turns true when
    uvicorn has stopped accepting (new queries then get 503)."""

    settings: ServiceSettings
    metrics: ServiceMetrics
    workers: DeviceWorkers
    registry: ModelRegistry
    shutting_down: bool = False


def get_state(request: Request) -> ServiceState:
    return request.app.state.collider


def serving_model(state: ServiceState, name: str) -> LoadedModel:
    """The loaded model ``name``, else 503 while starting or stopping, else 404."""
    if state.shutting_down:
        raise Problem(503, "shutting-down", "the server is shutting down", {"Retry-After": "5"})
    model = state.registry.get(name)
    if model is not None:
        return model
    if not state.registry.ready:
        raise Problem(503, "not-ready", "models are still loading; retry shortly",
                      {"Retry-After": "1"})
    raise unknown_model(name, state.registry.models)
