"""The HTTP service (FastAPI): ``create_app(settings)`` and its settings.

Layout: ``settings`` (typed settings), ``app`` (wiring), ``routers/`` (HTTP <-> plain calls),
``bodies`` (wire decoding and validation), ``answers`` (queries through the batchers),
``registry`` (models loaded), ``metrics``, ``auth``, ``problems`` (problem+json errors).
"""

from .app import create_app
from .settings import ServiceSettings, load_settings

__all__ = ["ServiceSettings", "create_app", "load_settings"]
