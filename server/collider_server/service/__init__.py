"""The HTTP service (FastAPI): ``create_app(settings)`` and its settings.

Layout: ``settings`` (typed settings), ``app`` (wiring), ``routers/`` (HTTP <-> plain calls),
``bodies`` (wire decoding and validation), ``query_jobs`` (queries as jobs on the batchers),
``registry`` (models loaded), ``metrics``, ``auth``, ``problems`` (problem+json errors),
``connections`` (the HTTP server's connection limits: ``uvicorn_config``).
"""

from .app import create_app
from .connections import uvicorn_config
from .settings import ServiceSettings, load_settings

__all__ = ["ServiceSettings", "create_app", "load_settings", "uvicorn_config"]
