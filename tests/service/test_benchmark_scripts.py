"""The load-test script runs headless against a real server and reports what it measured."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from .conftest import ServerThread

REPO = Path(__file__).resolve().parents[2]


def test_loadtest_runs_headless_for_a_bounded_time(repo, tmp_path):
    with ServerThread(models=repo, device="cpu") as server:
        result = subprocess.run(
            [sys.executable, str(REPO / "benchmarks" / "loadtest.py"), "--url", server.url,
             "--model", "sphere", "--simulators", "3", "--cloth", "8", "--duration", "1.5",
             "--output", str(tmp_path / "report.json")],
            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    summary = result.stdout.strip().splitlines()[-1]
    assert re.search(r"3 simulators x 64 vertices, .* points/s; latency p50 [0-9.]+ ms", summary)
    assert "status {200:" in summary and "transport errors 0" in summary
    assert (tmp_path / "report.json").is_file()
