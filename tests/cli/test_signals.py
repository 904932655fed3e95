"""A long command's SIGTERM handler and the native extensions it loads."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("igl", reason="libigl (the serve extra) is not installed")

#: ``collider eval`` run with its work replaced by a probe that says, when the command starts,
#: whether libigl is loaded and SIGTERM handled (a fresh interpreter: nothing imported before).
PROBE = """
import importlib, signal, sys

m = importlib.import_module("collider_cli.main")  # the module (the package's ``main`` is its function)

build = m.build_parser


def probing_parser():
    parser = build()

    def probe(args):
        print("igl" in sys.modules, signal.getsignal(signal.SIGTERM) is m._raise_terminated)

    parser.commands["eval"].set_defaults(func=probe)
    return parser


m.build_parser = probing_parser
sys.exit(m.main(["eval", "some-model", "--mesh", "some.obj"]))
"""


def test_a_long_command_has_loaded_libigl_before_sigterm_can_interrupt_it():
    """A SIGTERM raised while libigl's bindings initialise ended ``collider eval`` in C++'s
    terminate (status -6) or with a traceback (status 1) instead of status 143: the bindings are
    loaded before the handler that raises the interrupt is installed."""
    result = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["True", "True"], result.stdout
