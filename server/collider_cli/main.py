"""The ``collider`` command line: one entry point, one module per subcommand group.

Each module in :data:`COMMAND_MODULES` has ``register(subparsers)``, which adds its subcommands
and sets ``func`` (taking the parsed arguments, returning an exit code) on each. User errors
(ValueError, FileNotFoundError, ...) print one line on stderr and exit 2; no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMAND_MODULES = [
    "collider_cli.commands.models",
    "collider_cli.commands.animate",
    "collider_cli.commands.training",
    "collider_cli.commands.simulate",
    "collider_cli.commands.serve",
    "collider_cli.commands.view",
    "collider_cli.commands.bench",
]

USER_ERRORS = (ValueError, FileNotFoundError, IsADirectoryError, PermissionError, KeyError)

#: Packages of the optional extras (pyproject) and the extra that brings each: a command whose
#: extra is not installed says what to install instead of showing an ImportError traceback.
EXTRA_OF_MODULE = {"torch": "serve", "scipy": "serve", "igl": "serve", "safetensors": "serve",
                   "fastapi": "serve", "uvicorn": "serve", "trimesh": "train", "skimage": "train",
                   "tqdm": "train", "matplotlib": "sim"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="collider",
        description="Neural, voxel and exact signed-distance colliders: bake, train, query, serve.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    # No command takes NaN or infinity for a number (`--max-minutes nan` meant "no limit").
    from .commands.options import require_finite

    require_finite(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except USER_ERRORS as exc:
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"collider {args.command}: error: {message}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:
        extra = EXTRA_OF_MODULE.get((exc.name or "").partition(".")[0])
        if extra is None:
            raise
        print(f"collider {args.command}: error: {exc.name} is not installed; install the "
              f"'{extra}' extra: pip install 'neural-collider[{extra}]'", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"collider {args.command}: interrupted", file=sys.stderr)
        return 130

