"""Hints: the commands a ``collider`` command suggests next, written so that pasting them works.

Every suggested command is built here from the options the user gave (the model repository, the
mesh placement, the cache), quoted for a POSIX shell. A hint is printed either as a line
``next: collider ...`` or inside a sentence between backticks; ``tests/test_hints.py`` runs
every hint each command prints, as pasted.
"""

from __future__ import annotations

import argparse
import shlex


def command(*words) -> str:
    """``collider WORD ...`` quoted for a POSIX shell."""
    return shlex.join(["collider", *(str(w) for w in words)])


def placement_options(args: argparse.Namespace) -> list[str]:
    """The placement options ``args`` were given (none when they are the defaults)."""
    out = []
    if getattr(args, "z_up", False):
        out.append("--z-up")
    if getattr(args, "fit_size", None) is not None:
        out += ["--fit-size", repr(args.fit_size)]
    elif getattr(args, "scale", None) not in (None, 1.0):
        out += ["--scale", repr(args.scale)]
    if getattr(args, "units", "m") not in (None, "m"):
        out += ["--units", args.units]
    if getattr(args, "meters_per_unit", None) is not None:
        out += ["--meters-per-unit", repr(args.meters_per_unit)]
    return out


def models_options(args: argparse.Namespace) -> list[str]:
    """``--models DIR`` when the user named one (else the default repository is found again)."""
    return ["--models", str(args.models)] if getattr(args, "models", None) is not None else []


def again_with(args: argparse.Namespace, *options: str) -> str:
    """The command the user ran (``args.argv``, set by :func:`collider_cli.main.main`) with
    ``options`` added (``"--flag"``, or ``"--option", "value"``), replacing the same options
    given before."""
    argv = list(getattr(args, "argv", None) or [])
    takes_value = {o: i + 1 < len(options) and not options[i + 1].startswith("--")
                   for i, o in enumerate(options) if o.startswith("--")}
    kept, skip = [], False
    for word in argv:
        if skip:
            skip = False
            continue
        name = word.split("=", 1)[0]
        if name in takes_value:
            skip = takes_value[name] and "=" not in word
            continue
        kept.append(word)
    return command(*kept, *options)
