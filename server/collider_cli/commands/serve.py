"""``collider serve``: the HTTP service over every model in a repository."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from ..net import is_loopback
from .options import add_device_argument, add_models_argument


def register(subparsers) -> None:
    serve = subparsers.add_parser(
        "serve", help="serve every model of a repository over HTTP (msgpack or JSON)",
        description="Settings come from, lowest priority first: defaults, --config FILE (TOML or "
                    "JSON), COLLIDER_* environment variables (COLLIDER_TOKEN, "
                    "COLLIDER_ADMIN_TOKEN, COLLIDER_MAX_WAIT_MS, ...), these flags.")
    serve.add_argument("--host", default=None, help="address to listen on (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=None, help="port (default 8000; 0 = any free)")
    add_models_argument(serve, "every model in it is served")
    add_device_argument(serve)
    serve.add_argument("--config", type=Path, default=None, help="settings file, .toml or .json")
    knobs = serve.add_argument_group("coalescing and limits")
    knobs.add_argument("--max-batch-points", type=int, default=None,
                       help="most points in one compute call (default 65536)")
    knobs.add_argument("--max-wait-ms", type=float, default=None,
                       help="longest wait for more points before a batch closes, ms (default 0: "
                            "a batch takes what queued while the previous one ran)")
    knobs.add_argument("--max-queue-points", type=int, default=None,
                       help="most points queued per model; beyond it 429 (default 4000000)")
    knobs.add_argument("--coalesce", action=argparse.BooleanOptionalAction, default=None,
                       help="join concurrent requests into one batch (default on)")
    knobs.add_argument("--max-request-points", type=int, default=None,
                       help="most points in one request; beyond it 413 (default 1000000)")
    knobs.add_argument("--max-body-bytes", type=int, default=None,
                       help="largest request body; beyond it 413 (default 64 MiB)")
    knobs.add_argument("--max-scene-colliders", type=int, default=None,
                       help="most colliders in one scene query (default 64)")
    knobs.add_argument("--default-deadline-ms", type=float, default=None,
                       help="deadline of requests that give none, ms (default none)")
    knobs.add_argument("--compute-threads", type=int, default=None,
                       help="CPU threads per compute call (default 0: all cores but one)")
    knobs.add_argument("--body-timeout-s", type=float, default=None,
                       help="longest wait for the next part of a request body; then 408 "
                            "(default 30)")
    knobs.add_argument("--header-timeout-s", type=float, default=None,
                       help="longest wait for a request's headers after a connection opens or "
                            "its previous response ends; then 408 and the connection is closed "
                            "(default 10)")
    knobs.add_argument("--max-connections", type=int, default=None,
                       help="most open connections; a new one beyond it is answered 503 and "
                            "closed (default 4096; the open-files limit is raised to fit)")
    knobs.add_argument("--graceful-shutdown-s", type=float, default=None,
                       help="on SIGTERM, longest wait for open requests (default 30)")
    serve.add_argument("--cors-origin", action="append", default=None, dest="cors_origins",
                       help="allow this CORS origin (repeatable; default CORS off)")
    serve.add_argument("--no-warmup", action="store_const", const=False, default=None,
                       dest="warmup", help="skip the warm-up query per model")
    serve.add_argument("--log-level", default=None, choices=["critical", "error", "warning",
                                                             "info", "debug"])
    serve.set_defaults(func=run_serve)


SETTING_FLAGS = ("host", "port", "models", "device", "max_batch_points", "max_wait_ms",
                 "max_queue_points", "coalesce", "max_request_points", "max_body_bytes",
                 "max_scene_colliders", "default_deadline_ms", "compute_threads", "cors_origins", "warmup",
                 "log_level", "body_timeout_s", "header_timeout_s", "max_connections",
                 "graceful_shutdown_s")
#: Descriptors the process needs besides its connections (model files, logs, torch's threads).
OTHER_FILES = 256


def run_serve(args) -> int:
    import uvicorn

    from collider_server.service import create_app, load_settings, uvicorn_config

    settings = load_settings(args.config, **{k: getattr(args, k) for k in SETTING_FLAGS})
    if settings.models is not None and not settings.models.is_dir():
        raise FileNotFoundError(f"model repository {settings.models} is not a folder")
    if not is_loopback(settings.host) and not settings.token:
        print(f"collider serve: warning: listening on {settings.host} without COLLIDER_TOKEN: "
              "anyone who can reach this port can query it", file=sys.stderr)
    logging.basicConfig(level=settings.log_level.upper(), format="%(levelname)s:     %(message)s")
    fit_open_files(settings.max_connections + OTHER_FILES)
    app = create_app(settings)
    config = uvicorn_config(app, settings.host, settings.port, log_level=settings.log_level,
                            access_log=False, timeout_graceful_shutdown=settings.graceful_shutdown_s)
    # uvicorn handles SIGINT/SIGTERM: it stops accepting, answers the open requests (for at most
    # graceful_shutdown_s, so a pod's termination grace period can be set above it), then runs
    # the app's shutdown (which drains the batchers) and returns; then it raises the signal again,
    # so the process ends by it (status 143 in a shell after SIGTERM, 130 after Ctrl-C).
    uvicorn.Server(config).run()
    return 0


def fit_open_files(needed: int) -> None:
    """Raise this process's open-files limit (``ulimit -n``) to ``needed`` where the hard limit
    allows, as nginx's ``worker_rlimit_nofile`` does; warn when it cannot."""
    try:
        import resource
    except ImportError:  # not on POSIX: nothing to raise
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= needed:
        return
    target = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
    resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    if target < needed:
        print(f"collider serve: warning: max_connections needs about {needed} open files but "
              f"this process may open {target} (ulimit -Hn); lower --max-connections or raise "
              "the limit", file=sys.stderr)
