"""benchmarks/chunk_points.py times one collider's query at several block sizes, interleaved, and
prints the medians, their range and the ratio to the kind's own block size."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_the_benchmark_prints_every_block_size_against_the_kinds_own():
    result = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "chunk_points.py"), "--kind", "voxel", "--resolution", "16",
         "--points", "3000", "--rounds", "2", "--threads", "1", "--chunks", "700,5000"],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    out = result.stdout
    assert re.search(r"^voxel \(16\^3\), 3,000 points, 1 threads, 2 rounds; freed memory not held; load average [0-9.]+, "
                     r"[0-9.]+, [0-9.]+; the kind's own block: 65,536$", out, re.MULTILINE), out
    number = r"[0-9]+\.[0-9]{4}"
    for label in ("distance", r"d\+n\+c"):
        for chunk in ("700", "5,000", "65,536"):
            assert re.search(rf"^  {label}\s+blocks of\s+{chunk}: median {number} s \({number}-{number}\), "
                             rf"[0-9.]+x the kind's own$", out, re.MULTILINE), (label, chunk, out)
        assert re.search(rf"^  {label}\s+blocks of\s+65,536: .* 1\.00x the kind's own$", out, re.MULTILINE), out
