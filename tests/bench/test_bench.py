"""``collider bench`` and ``collider bake --max-error``: the pieces without a server (timing
policy, Pareto front, budget quantities, candidate plan), then the real thing: ``collider bench
--quick`` on the Stanford bunny (a real ``collider serve`` for the served half) and a budget
picked from its report. Structure and plausible accuracy are asserted, never timings."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from collider_cli.bench.budget import Budget, NothingMeetsBudget, angle_deg, length_mm, rank, size_bytes
from collider_cli.bench.plan import PlanConfig, plan_candidates
from collider_cli.bench.report import pareto_front
from collider_cli.bench.timing import TimingPolicy, time_calls

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def bunny(meshes_dir) -> Path:
    path = meshes_dir / "stanford-bunny.obj"
    if not path.is_file():
        pytest.skip(f"shared test mesh {path} is absent")
    return path


class FakeClock:
    """A clock that advances by a fixed step per reading pair: each timed call "takes" ``step``."""

    def __init__(self, step: float):
        self.now, self.step, self.reads = 0.0, step, 0

    def __call__(self) -> float:
        self.reads += 1
        if self.reads % 2 == 0:
            self.now += self.step
        return self.now


def test_time_calls_repeats_until_the_cell_budget_then_stops():
    calls = []
    times = time_calls(lambda: calls.append(1), TimingPolicy(repeats=5, cell_budget_s=2.5), FakeClock(1.0))
    assert times == [1.0, 1.0, 1.0] and len(calls) == 3  # 3 s >= 2.5 s budget: no 4th call
    assert time_calls(lambda: None, TimingPolicy(repeats=5, cell_budget_s=0.1), FakeClock(7.0)) == [7.0]
    assert len(time_calls(lambda: None, TimingPolicy(repeats=4, cell_budget_s=100), FakeClock(1.0))) == 4


def test_pareto_front_keeps_only_undominated_items_ordered_by_time():
    items = [("slow-exact", 10.0, 0.0), ("fast-rough", 0.1, 0.3), ("mid", 1.0, 0.05),
             ("dominated", 2.0, 0.06), ("tie-worse", 1.0, 0.07)]
    assert pareto_front(items) == ["fast-rough", "mid", "slow-exact"]


def test_budget_quantities_take_units_and_refuse_nonsense():
    assert length_mm("0.05mm") == pytest.approx(0.05)
    assert length_mm("50um") == pytest.approx(0.05)
    assert length_mm("0.05") == pytest.approx(0.05)
    assert length_mm("5e-5 m") == pytest.approx(0.05)
    assert angle_deg("3deg") == 3.0 and angle_deg("3") == 3.0
    assert size_bytes("8MB") == 8_000_000 and size_bytes("8MiB") == 8 * 2**20
    for bad in ("nan", "inf mm", "-1mm", "0", "5 parsecs", "mm", ""):
        with pytest.raises(ValueError, match="--max-error"):
            length_mm(bad)


def _row(name, seconds, error, normal=1.0, memory=1000):
    return {"name": name, "label": name, "memory_bytes": memory,
            "accuracy": {"band_1mm": {"distance_mean_mm": error, "normal_mean_deg": normal}},
            "timings": [{"path": "embedded", "device": "cpu", "mode": "distance+normal+contact",
                         "points": 100, "median_s": seconds * 100}]}


def test_rank_takes_the_fastest_that_meets_every_limit_and_explains_when_none_does():
    report = {"config": {"sizes": [10, 100]}, "skipped": [],
              "colliders": [_row("exact", 10.0, 0.0, 0.0, 2000), _row("grid", 0.2, 0.03, 4.0, 8000),
                            _row("coarse", 0.1, 0.2, 6.0, 100), _row("net", 5.0, 0.02, 2.0, 500)]}
    assert [r["name"] for r in rank(report, Budget(0.05))] == ["grid", "net", "exact"]
    assert [r["name"] for r in rank(report, Budget(0.05, max_normal_error_deg=3))] == ["net", "exact"]
    assert [r["name"] for r in rank(report, Budget(0.05, max_memory_bytes=1000))] == ["net"]
    with pytest.raises(NothingMeetsBudget, match=r"no measured collider meets.*\n.*exact: memory 0.00 MB"):
        rank(report, Budget(0.001, max_memory_bytes=10))


def test_plan_stops_voxels_at_the_memory_budget_and_lists_every_neural_preset(monkeypatch, load_shared_mesh):
    from collider_server.engine.kinds import neural

    mesh = load_shared_mesh("stanford-bunny.obj")
    monkeypatch.setitem(neural.PRESETS, "bench-test-preset", neural.Architecture(16, 2, 32, 3.0))
    plan = plan_candidates(mesh, np.eye(4), PlanConfig(resolutions=(32, 64, 128), max_memory_bytes=2_000_000),
                           REPO_ROOT / "models")
    names = [c.name for c in plan.candidates]
    assert names[:4] == ["kdtree", "mesh", "voxel-32", "voxel-64"]
    assert "neural-bunny" in names  # the shipped model of this very mesh file
    skipped = {s["name"]: s["reason"] for s in plan.skipped}
    assert "--max-memory" in skipped["voxel-128"]
    assert "--train-minutes" in skipped["neural-bench-test-preset"]  # a new preset shows up by itself
    with_training = plan_candidates(mesh, np.eye(4), PlanConfig(kinds=("neural",), train_minutes=0.5),
                                    REPO_ROOT / "models")
    assert "neural-bench-test-preset" in [c.name for c in with_training.candidates]
    only = plan_candidates(mesh, np.eye(4), PlanConfig(kinds=("neural",), presets=("bench-test-preset",),
                                                       train_minutes=0.5), REPO_ROOT / "models")
    assert [c.name for c in only.candidates] == ["neural-bench-test-preset"] and not only.skipped
    with pytest.raises(ValueError, match="--presets must name some of"):
        PlanConfig(presets=("no-such-preset",)).check()
    other = plan_candidates(mesh, np.diag([2.0, 2.0, 2.0, 1.0]), PlanConfig(kinds=("neural",), train_minutes=0),
                            REPO_ROOT / "models")
    assert "another placement" in {s["name"]: s["reason"] for s in other.skipped}["neural-bunny"]


def collider(*args):
    """The ``collider`` command in a subprocess (what a user runs)."""
    return subprocess.run([sys.executable, "-m", "collider_cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def collider_here(capsys, *args):
    """The same entry point in this process (no interpreter start-up): (exit code, stdout, stderr)."""
    from collider_cli import main

    code = main([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture(scope="module")
def quick_bench(tmp_path_factory, bunny):
    """``collider bench BUNNY --quick`` run once: (output folder, report dict, stdout)."""
    mesh = bunny
    out = tmp_path_factory.mktemp("bench")
    result = collider("bench", mesh, "--quick", "--quiet", "--models", REPO_ROOT / "models",
                      "--output", out / "result", "--cache", out / "cache")
    assert result.returncode == 0, result.stdout + result.stderr
    return out, json.loads((out / "result" / "bench.json").read_text()), result.stdout


@pytest.mark.slow
def test_quick_bench_measures_every_kind_embedded_and_served_with_plausible_accuracy(quick_bench):
    out, report, stdout = quick_bench
    rows = {r["name"]: r for r in report["colliders"]}
    assert list(rows)[:4] == ["kdtree", "mesh", "voxel-32", "voxel-64"]
    assert "neural-bunny" in rows  # the shipped model of this mesh (others may join it)
    for row in rows.values():
        cells = {(t["path"], t["device"], t["mode"], t["points"]) for t in row["timings"]}
        assert cells == {(path, "cpu", mode, n) for path in ("embedded", "served")
                         for mode in ("distance", "distance+normal+contact") for n in (10_000, 40_000)}
        assert all(t["median_s"] > 0 and 1 <= t["repeats"] <= 2 for t in row["timings"])
        assert row["file_bytes"] > 0 and row["memory_bytes"] > 0
        assert set(row["accuracy"]) == {"band_1mm", "band_10mm"}
    band = {name: r["accuracy"]["band_1mm"] for name, r in rows.items()}
    assert band["mesh"]["distance_mean_mm"] < 1e-3 and band["mesh"]["normal_mean_deg"] < 0.1
    assert 0.1 < band["kdtree"]["distance_mean_mm"] < 0.5          # nearest vertex: ~half an edge
    assert band["voxel-64"]["distance_mean_mm"] < band["voxel-32"]["distance_mean_mm"] < 1.0
    assert band["neural-bunny"]["distance_mean_mm"] < 0.06          # shipped: 0.031 mm
    assert rows["voxel-64"]["memory_bytes"] == 64**3 * 4
    assert rows["neural-bunny"]["build"] == "trained" and rows["neural-bunny"]["build_seconds"] > 0
    machine = report["machine"]
    assert machine["cores"] >= 1 and machine["versions"]["torch"] and "cpu" in machine
    assert "| 10k |" in stdout and "| 40k |" in stdout and "Pareto front (cpu" in stdout
    png = (out / "result" / "bench-cpu.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


@pytest.mark.slow
def test_budget_bake_picks_the_fastest_collider_that_meets_it_and_checks_it_afresh(quick_bench, tmp_path, bunny):
    out, report, _ = quick_bench
    mesh = bunny
    result = collider("bake", mesh, "--name", "picked", "--models", tmp_path, "--max-error", "0.1mm",
                      "--bench", out / "result" / "bench.json", "--quiet")
    assert result.returncode == 0, result.stdout + result.stderr
    from collider_server.engine.modelfile import read_info

    info = read_info(tmp_path / "picked.safetensors")
    expected = rank(report, Budget(0.1))[0]
    assert info.settings["picked_for_budget"]["candidate"] == expected["name"]
    assert info.kind == expected["kind"]
    assert info.accuracy["band_1mm"]["distance_mean_mm"] <= 0.1  # the fresh evaluation, seed 1234
    assert "meets the budget" in result.stdout

    # A memory limit at the shipped network's size: whatever is picked is what rank() says, and a
    # picked network is the trained model's own file (the shipped bunny is smaller than `mesh`).
    limit = next(r for r in report["colliders"] if r["name"] == "neural-bunny")["memory_bytes"]
    small = collider("bake", mesh, "--name", "small", "--models", tmp_path, "--max-error", "0.05mm",
                     "--max-memory", str(limit), "--bench", out / "result" / "bench.json", "--quiet")
    assert small.returncode == 0, small.stdout + small.stderr
    info = read_info(tmp_path / "small.safetensors")
    picked = rank(report, Budget(0.05, max_memory_bytes=limit))[0]
    assert info.settings["picked_for_budget"]["candidate"] == picked["name"] and info.kind == picked["kind"]

    nothing = collider("bake", mesh, "--name", "none", "--models", tmp_path, "--max-error", "0.05mm",
                       "--max-memory", "0.5MB", "--bench", out / "result" / "bench.json", "--quiet")
    assert nothing.returncode == 1
    assert "no measured collider meets mean distance error <= 0.05 mm" in nothing.stderr
    assert "Traceback" not in nothing.stderr and not (tmp_path / "none.safetensors").exists()


@pytest.mark.parametrize("args, message", [
    (["--max-error", "nan"], "--max-error must be a finite number"),
    (["--max-normal-error", "3deg"], "need --max-error"),
    (["--max-error", "0.05mm", "--max-memory", "lots"], "--max-memory must be"),
])
def test_budget_bake_refuses_bad_limits_in_one_line(args, message, tmp_path, bunny, capsys):
    code, _, err = collider_here(capsys, "bake", bunny, "--name", "x", "--models", tmp_path, *args)
    assert code == 2 and message in err and "Traceback" not in err


def test_bench_refuses_unknown_kinds_and_a_bench_file_of_another_mesh(tmp_path, bunny, capsys):
    code, _, err = collider_here(capsys, "bench", bunny, "--kinds", "voxel,magic")
    assert code == 2 and "--kinds must name some of" in err
    other = tmp_path / "bench.json"
    other.write_text(json.dumps({"mesh": {"sha256": "0" * 64, "transform": np.eye(4).tolist(), "path": "x.obj"}}))
    code, _, err = collider_here(capsys, "bake", bunny, "--name", "x", "--models", tmp_path, "--max-error", "1mm",
                                 "--bench", other)
    assert code == 2 and "measured another mesh or placement" in err


def test_bench_places_the_mesh_like_every_command_and_reports_errors_in_mm(tmp_path, bunny, capsys):
    """The bunny in metres and the same bunny in millimetres (--scale 1000 --units mm) give the
    same physical errors: figures are in mm whatever the collider's units."""
    reports = {}
    for label, placement in (("m", []), ("mm", ["--scale", "1000", "--units", "mm"])):
        out = tmp_path / label
        code, stdout, err = collider_here(capsys, "bench", bunny, *placement, "--kinds", "kdtree", "--no-served",
                                          "--sizes", "1k", "--accuracy-points", "3000", "--repeats", "1",
                                          "--quiet", "--output", out, "--cache", tmp_path / "cache")
        assert code == 0, stdout + err
        reports[label] = json.loads((out / "bench.json").read_text())
    assert reports["mm"]["mesh"]["units"] == "mm" and reports["mm"]["mesh"]["transform"][0][0] == 1000.0
    metres = reports["m"]["colliders"][0]["accuracy"]["band_1mm"]["distance_mean_mm"]
    millimetres = reports["mm"]["colliders"][0]["accuracy"]["band_1mm"]["distance_mean_mm"]
    assert 0.1 < metres < 0.5 and millimetres == pytest.approx(metres, rel=1e-3)
