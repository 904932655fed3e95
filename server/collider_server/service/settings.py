"""The service's settings: defaults < config file < ``COLLIDER_*`` environment < CLI flags,
merged by pydantic-settings' own sources (TOML is read with ``tomllib``, or ``tomli`` on
Python 3.10, by pydantic-settings)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from pydantic import Field, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    JsonConfigSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from .batching import BatchSettings

LOG_LEVELS = ("critical", "error", "warning", "info", "debug")
#: Tokens that examples and templates use as placeholders: a server holding one would be open to
#: anyone who read them, so it refuses to start.
PLACEHOLDER_TOKENS = frozenset({"change-me", "change-me-too", "changeme", "replace-me", "secret",
                                "token"})


class ServiceSettings(BaseSettings):
    """Everything ``collider serve`` can be told. Environment variables are the field names in
    upper case prefixed ``COLLIDER_`` (``COLLIDER_MAX_WAIT_MS=2``)."""

    model_config = SettingsConfigDict(env_prefix="COLLIDER_", extra="forbid")

    host: str = Field("127.0.0.1", description="address to listen on; loopback only by default")
    port: int = Field(8000, ge=0, le=65535)
    models: Path | None = Field(None, description="model repository (default: ./models)")
    device: str = Field("auto", description="cpu, cuda, cuda:N or auto")
    token: str | None = Field(None, description="bearer token required on every route but "
                                                "/livez and /readyz; unset: no auth")
    admin_token: str | None = Field(None, description="bearer token of the admin routes; "
                                                      "unset: admin routes disabled")
    cors_origins: list[str] = Field(default_factory=list, description="allowed CORS origins; "
                                                                      "empty: CORS off")
    # Coalescing (see collider_server.service.batching).
    max_batch_points: int = Field(65_536, ge=1, description="most points in one compute call")
    # 0 as in Triton's dynamic batcher: whatever queued while the worker was busy forms the next
    # batch, and a lone request pays no timer (measured: 1 ms cost +2.4 ms p50 at K=1 on 2 cores).
    max_wait_ms: float = Field(0.0, ge=0, description="longest wait for more points, ms")
    max_queue_points: int = Field(4_000_000, ge=1, description="most points queued per model")
    coalesce: bool = Field(True, description="False computes every request on its own")
    # Limits of one request.
    max_request_points: int = Field(1_000_000, ge=1, description="most points in one request")
    max_body_bytes: int = Field(64 * 1024 * 1024, ge=1024, description="largest body, bytes")
    max_scene_colliders: int = Field(64, ge=1, description="most colliders in a scene query")
    default_deadline_ms: float | None = Field(None, gt=0, description="deadline of requests "
                                                                      "that give none, ms")
    compute_threads: int = Field(0, ge=0, description="CPU threads of one compute call; 0: "
                                                      "auto, all cores but one (the event loop's)")
    body_timeout_s: float = Field(30.0, gt=0, description="longest wait for the next part of "
                                                          "a request body, s; then 408")
    header_timeout_s: float = Field(10.0, gt=0, description="longest wait for a request's "
                                                            "headers from a connection's opening "
                                                            "or its previous response, s; then "
                                                            "408 and the connection is closed")
    max_connections: int = Field(4096, ge=1, description="most open connections; a new one "
                                                         "beyond it gets 503 and is closed")
    graceful_shutdown_s: float = Field(30.0, gt=0, description="on SIGTERM, longest wait for "
                                                               "open requests, s; then they are "
                                                               "cancelled")
    query_fast_path: bool = Field(True, description="serve POST /v1/models/{name}/query from "
                                                    "ASGI directly (off: through FastAPI's "
                                                    "router; same answers, more overhead)")
    warmup: bool = Field(True, description="run one small query per model before ready")
    hold_freed_memory: bool = Field(True, description="keep memory a batch frees for the next "
                                                      "batch (glibc): no page faults on its "
                                                      "arrays; the process keeps its peak")
    log_level: str = Field("info", description=f"one of {', '.join(LOG_LEVELS)}")

    @field_validator("log_level", mode="before")
    @classmethod
    def _known_log_level(cls, value: Any) -> Any:
        # uvicorn knows lower-case names only; COLLIDER_LOG_LEVEL=DEBUG is meant the same way.
        level = value.lower() if isinstance(value, str) else value
        if level not in LOG_LEVELS:
            raise ValueError(f"must be one of {', '.join(LOG_LEVELS)}, got {value!r}")
        return level

    @field_validator("token", "admin_token")
    @classmethod
    def _not_a_placeholder(cls, value: str | None) -> str | None:
        if value is not None and value.strip().lower() in PLACEHOLDER_TOKENS:
            raise ValueError(f"{value!r} is a placeholder, not a secret; set a token of your "
                             "own, e.g. $(openssl rand -hex 24)")
        return value

    @model_validator(mode="after")
    def _request_fits_queue(self) -> ServiceSettings:
        if self.max_request_points > self.max_queue_points:
            raise ValueError(
                f"max_request_points ({self.max_request_points}) must not exceed "
                f"max_queue_points ({self.max_queue_points}): such a request could never queue"
            )
        return self

    def resolved_compute_threads(self) -> int:
        if self.compute_threads:
            return self.compute_threads
        # Leave a core to the event loop: on a busy CPU, compute threads that spin-wait on each
        # other while the loop needs the core cost ~10x (measured on 2 cores, docs/service.md).
        return max(1, (os.cpu_count() or 2) - 1)

    def batch_settings(self) -> BatchSettings:
        return BatchSettings(self.max_batch_points, self.max_wait_ms, self.max_queue_points,
                             self.coalesce)


class _ServeTomlSource(TomlConfigSettingsSource):
    """A TOML settings file whose keys may sit under a ``[serve]`` table."""

    def _read_file(self, file_path) -> dict[str, Any]:
        data = super()._read_file(file_path)
        serve = data.get("serve")
        return serve if isinstance(serve, dict) else data


def config_file_source(path: str | Path) -> type[PydanticBaseSettingsSource]:
    """The pydantic-settings source class reading ``path`` (.toml or .json); ValueError names
    a file that is missing or of another kind."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: cannot read config file (no such file)")
    if path.suffix == ".toml":
        return lambda cls: _ServeTomlSource(cls, toml_file=path)
    if path.suffix == ".json":
        return lambda cls: JsonConfigSettingsSource(cls, json_file=path)
    raise ValueError(f"{path}: config file must be .toml or .json")


def load_settings(config_file: str | Path | None = None, **overrides: Any) -> ServiceSettings:
    """Settings from, lowest priority first: defaults, ``config_file``, ``COLLIDER_*``
    environment variables, ``overrides`` (the CLI flags that were given; ``None`` = not given).

    Raises ValueError naming the bad setting, or the config file that cannot be read."""
    from pydantic import ValidationError

    file_source = config_file_source(config_file) if config_file else None

    class FromSources(ServiceSettings):
        @classmethod
        def settings_customise_sources(cls, settings_cls, init_settings, env_settings,
                                       dotenv_settings, file_secret_settings):
            # Earlier sources win: flags (init), environment, then the file.
            return (init_settings, env_settings) + ((file_source(settings_cls),) if file_source
                                                    else ())

    try:
        merged = FromSources(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'settings'}: {e['msg']}" for e in exc.errors()
        )
        raise ValueError(f"invalid settings: {problems}") from None
    except ValueError as exc:  # a malformed TOML or JSON file
        raise ValueError(f"{config_file}: malformed config file ({exc})") from None
    # A plain ServiceSettings (the subclass only chose the sources); values already validated.
    return ServiceSettings.model_construct(**merged.model_dump())
