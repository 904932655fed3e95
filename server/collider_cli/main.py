"""The ``collider`` command line: one entry point, one module per subcommand group.

Each module in :data:`COMMAND_MODULES` has ``register(subparsers)``, which adds its subcommands
and sets ``func`` (taking the parsed arguments, returning an exit code) on each. User errors
(ValueError, FileNotFoundError, ...) and options argparse refuses print one line on stderr and
exit 2; no traceback, no usage block. Ctrl-C ends a command with status 130 and SIGTERM (for the
long commands of :data:`LONG_COMMANDS`) with 143, each after the command has written what it
made so far (they catch ``KeyboardInterrupt``, which SIGTERM raises there too).
"""

from __future__ import annotations

import argparse
import importlib
import signal
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
                   "tqdm": "train", "pygltflib": "train", "pxr": "train", "matplotlib": "sim"}


#: Commands that run long enough to be stopped: SIGTERM ends them like Ctrl-C (what they made is
#: written), with status 143.
LONG_COMMANDS = ("simulate", "train", "bench", "bake", "eval")


class OneLineParser(argparse.ArgumentParser):
    """An argparse parser whose refusals are one line (``collider bake: error: ...``) and
    exit status 2, like every other user error of the command."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (`{self.prog} --help` lists the options)\n")


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread as Ctrl-C's KeyboardInterrupt is."""


#: Set by the SIGTERM handler: a command that catches the interrupt to write what it made and
#: raises KeyboardInterrupt again still exits with SIGTERM's status.
_terminated = False


def _raise_terminated(signum, frame):
    global _terminated
    _terminated = True
    raise Terminated()


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="collider",
        description="Neural, voxel and exact signed-distance colliders: bake, train, query, serve.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    parser.commands = subparsers.choices  # name -> its parser (refusals name the command)
    # No command takes NaN or infinity for a number (`--max-minutes nan` meant "no limit").
    from .commands.options import require_finite

    require_finite(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # said by the command's parser: "collider bake: error: unrecognized arguments: ..."
        parser.commands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    args.argv = argv  # the command as typed: hints repeat it (commands.hints.again_with)
    global _terminated
    _terminated = False
    if args.command in LONG_COMMANDS:
        # The interrupt raised while libigl's bindings initialise ended the process in C++'s
        # terminate (status -6) or with a traceback (status 1), not with 143.
        from collider_server.engine.meshes import load_libigl  # one distribution: always there

        load_libigl()
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
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
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated) or _terminated
        print(f"collider {args.command}: {'terminated (SIGTERM)' if terminated else 'interrupted'}",
              file=sys.stderr)
        return 143 if terminated else 130
    finally:
        if args.command in LONG_COMMANDS:
            signal.signal(signal.SIGTERM, previous)

