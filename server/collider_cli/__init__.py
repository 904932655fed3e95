"""The ``collider`` command and what only it runs: the benchmark (:mod:`.bench`) and the browser
views (:mod:`.views`). It sits above both sides of the project: the engine, model making and the
service (:mod:`collider_server`) and the SDK with its cloth simulator (:mod:`collider_client`).

``commands/`` holds one module per subcommand group; :func:`main` is the entry point.
"""

from .main import build_parser, main

__all__ = ["build_parser", "main"]
