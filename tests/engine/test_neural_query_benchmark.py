"""benchmarks/neural_query.py times the shipped bunny, another grid kernel and the exact mesh in one
interleaved run and prints medians, spreads, the load and the ratios."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

#: A stand-in for an older kernel: the engine's own, counting its calls in a file.
COUNTING_KERNEL = """
from pathlib import Path
from collider_server.engine.kinds import grid_kernels
_own = grid_kernels.network_query

def network_query(*args):
    marks = Path({marks!r})
    mark = "g" if args[12] else "d"  # want_gradient
    marks.write_text(marks.read_text() + mark if marks.exists() else mark)
    return _own(*args)
"""


@pytest.mark.slow
def test_the_benchmark_times_every_candidate_in_turn_and_prints_the_ratios(tmp_path):
    marks = tmp_path / "calls.txt"
    kernel = tmp_path / "kernel_before.py"
    kernel.write_text(COUNTING_KERNEL.format(marks=str(marks)))
    result = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "neural_query.py"), "--points", "2000", "--rounds", "2",
         "--threads", "1", "--kernel-from", str(kernel)],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    out = result.stdout
    assert "2 interleaved rounds" in out and re.search(r"load average \(1, 5, 15 min\) [0-9.]+/", out)
    number = r"[0-9]+\.[0-9]{3} \([0-9]+\.[0-9]{3}-[0-9]+\.[0-9]{3}\)"
    for label in ("neural bunny", r"neural bunny \(kernel_before\.py\)", r"mesh \(exact, libigl\) for bunny"):
        assert re.search(rf"^{label}\s+{number}\s+{number}$", out, re.MULTILINE), (label, out)
    assert re.search(r"exact mesh / neural \(d\+n\+c, medians\) = [0-9.]+x", out)
    assert re.search(r"kernel_before\.py / engine kernel \(d\+n\+c, medians\) = [0-9.]+x", out)
    # The other kernel really answered its rows: a warm-up call plus 2 rounds x (d+n+c, d only),
    # one call per 65,536-point chunk (2,000 points: one), and where the shipped bunny's gradient
    # vanishes at some of the points (a plateau), one distance call more per d+n+c call.
    marks = marks.read_text()
    assert marks.count("g") == 3 and marks.count("d") in (2, 5), marks


@pytest.mark.slow
def test_two_models_of_one_name_are_timed_apart():
    """A model file of an older commit beside the shipped one (both named ``bunny``): each gets
    its own rows, the second shown by the path it was given."""
    shipped = REPO / "models" / "bunny.safetensors"
    result = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "neural_query.py"), "--points", "2000", "--rounds", "1",
         "--threads", "1", "--model", "bunny", "--model", str(shipped)],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    for label in ("neural bunny ", f"neural {shipped} ", "mesh (exact, libigl) for bunny ",
                  f"mesh (exact, libigl) for {shipped} "):
        assert any(line.startswith(label) for line in result.stdout.splitlines()), (label, result.stdout)
