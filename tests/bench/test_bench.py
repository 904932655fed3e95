"""``collider bench`` and ``collider bake --max-error``: the pieces without a server (timing
policy, Pareto front, budget quantities, candidate plan), then the real thing: ``collider bench
--quick`` on the Stanford bunny (a real ``collider serve`` for the served half) and a budget
picked from its report. Structure and plausible accuracy are asserted, never timings."""

from __future__ import annotations

import itertools
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tests.conftest import REPO_ROOT, run_collider

from collider_cli.bench.budget import (
    Budget,
    NothingMeetsBudget,
    angle_deg,
    equally_fast,
    format_bytes,
    length_mm,
    rank,
    size_bytes,
)
from collider_cli.bench.plan import PlanConfig, plan_candidates
from collider_cli.bench.report import equal_times, front, front_text, pareto_front, ranking_basis
from collider_cli.bench.timing import (
    Cell,
    Timing,
    TimingPolicy,
    process_cpu_clock,
    served_beats_embedded,
    spread,
    time_rounds,
)


@pytest.fixture(scope="module")
def bunny(meshes_dir) -> Path:
    path = meshes_dir / "stanford-bunny.obj"
    if not path.is_file():
        pytest.skip(f"shared test mesh {path} is absent")
    return path


class FakeClock:
    """A clock that advances by ``durations[name]`` per reading pair: each timed call "takes"
    the duration of the cell being called (the cell name is set by the call itself)."""

    def __init__(self):
        self.now, self.reads, self.step = 0.0, 0, 0.0

    def __call__(self) -> float:
        self.reads += 1
        if self.reads % 2 == 0:
            self.now += self.step
        return self.now


def _cells(clock, durations: dict, order: list, reference=(), cpu=None):
    """Cells named by ``durations``, each call taking its duration(s) (a list is cycled) and
    logging its name in ``order``."""
    cells = []
    for name, duration in durations.items():
        values = duration if isinstance(duration, list) else [duration]

        def call(name=name, values=values, count=[0]):
            clock.step = values[count[0] % len(values)]
            count[0] += 1
            order.append(name)

        path = "served" if name.endswith("served") else "embedded"
        timing = Timing(path, "cpu", "distance+normal+contact", 1000, reference=name in reference)
        cells.append(Cell(name.split()[0], timing, call, cpu or (lambda: 0.0,)))
    return cells


def test_rounds_interleave_the_cells_and_stop_each_at_its_budget():
    clock, order = FakeClock(), []
    cells = _cells(clock, {"fast": 0.01, "slow": 3.0, "slow-reference": 3.0}, order, reference={"slow-reference"})
    rounds = time_rounds(cells, TimingPolicy(repeats=4, cell_budget_s=5.0, min_repeats=3, retime_rounds=0),
                         clock=clock)
    # One call of every cell still timing per round, in the list's order: never one cell's
    # repeats in a row while the others wait.
    assert order[:3] == ["fast", "slow", "slow-reference"] and order[3:6] == ["fast", "slow", "slow-reference"]
    counts = {c.name: len(c.timing.times_s) for c in cells}
    assert counts == {"fast": 4, "slow": 2, "slow-reference": 3}  # 6 s >= 5 s; a reference cell: 3 calls
    assert rounds == 4 and cells[0].timing.median_s == pytest.approx(0.01)


def test_unstable_figures_are_retimed_then_flagged_and_stable_ones_are_not():
    clock, order = FakeClock(), []
    cells = _cells(clock, {"steady": 1.0, "bursty": [1.0, 5.0, 1.0, 9.0]}, order)
    policy = TimingPolicy(repeats=4, cell_budget_s=100.0, max_spread=0.25, retime_rounds=3)
    # bursty: median 3 of [1, 1, 5, 9], IQR 5: spread 1.57 x 5 / (3 x 2) = 1.3
    time_rounds(cells, policy, clock=clock)
    steady, bursty = (c.timing for c in cells)
    assert len(steady.times_s) == 4 and steady.retimed == 0 and steady.stable(0.25)
    assert len(bursty.times_s) == 7 and bursty.retimed == 3 and not bursty.stable(0.25)
    assert steady.to_dict(0.25)["stable"] is True and bursty.to_dict(0.25)["stable"] is False
    assert spread([1.0, 1.0, 1.0]) == 0.0 and spread([1.0]) is None
    # The median's ~95 % half-width: 1.57 x IQR 2 / (median 3 x sqrt(5)); four times the calls halve it.
    assert spread([1.0, 2.0, 3.0, 4.0, 5.0]) == pytest.approx(1.57 * 2.0 / (3.0 * 5 ** 0.5))
    assert spread([1.0, 2.0, 3.0, 4.0, 5.0] * 4) == pytest.approx(spread([1.0, 2.0, 3.0, 4.0, 5.0] * 4 * 4) * 2, rel=0.05)


def test_served_faster_than_embedded_beyond_the_spread_is_retimed_with_its_twin():
    clock, order = FakeClock(), []
    cells = _cells(clock, {"grid embedded": [1.0, 1.02, 0.98], "grid served": [0.5, 0.51, 0.49],
                           "net embedded": [1.0, 1.02, 0.98], "net served": [1.1, 1.12, 1.08]}, order)
    time_rounds(cells, TimingPolicy(repeats=3, cell_budget_s=100.0, retime_rounds=2), clock=clock)
    retimed = {f"{c.name} {c.timing.path}": c.timing.retimed for c in cells}
    assert retimed == {"grid embedded": 2, "grid served": 2, "net embedded": 0, "net served": 0}
    assert served_beats_embedded(cells[0].timing, cells[1].timing)
    assert not served_beats_embedded(cells[2].timing, cells[3].timing)


def test_cpu_time_is_read_from_this_process_and_from_another_one():
    import os
    import time

    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])  # spins until killed
    try:
        theirs, ours = process_cpu_clock(busy.pid), process_cpu_clock()
        t0, o0 = theirs(), ours()
        # They spin, we sleep, until they have spun 0.2 s of CPU (however long a busy machine takes).
        deadline = time.monotonic() + 60
        while theirs() - t0 < 0.2 and time.monotonic() < deadline:
            time.sleep(0.02)
        spun, slept = theirs() - t0, ours() - o0
        assert spun >= 0.2 and slept < 0.05 and spun > 3 * slept
    finally:
        busy.kill()
        busy.wait()
    assert process_cpu_clock(os.getpid())() > 0


def test_pareto_front_keeps_only_undominated_items_ordered_by_time():
    items = [("slow-exact", 10.0, 0.0), ("fast-rough", 0.1, 0.3), ("mid", 1.0, 0.05),
             ("dominated", 2.0, 0.06), ("tie-worse", 1.0, 0.07)]
    assert pareto_front(items) == ["fast-rough", "mid", "slow-exact"]


def test_times_within_the_measurement_are_equal_for_the_front():
    # voxel 32^3 and 64^3 answer in about the same time: the coarser grid is on the front only
    # when it is faster beyond the tie (35 %) or the figures' spread, whichever is larger.
    assert pareto_front([("v32", 0.27, 0.28), ("v64", 0.35, 0.08)]) == ["v64"]  # 1.30x: equal
    assert pareto_front([("v32", 0.20, 0.28), ("v64", 0.31, 0.08)]) == ["v32", "v64"]  # 1.55x
    assert pareto_front([("v32", 0.20, 0.28, 0.6), ("v64", 0.31, 0.08, 0.1)]) == ["v64"]  # within its spread
    # An exact tie in both: neither dominates.
    assert pareto_front([("a", 1.0, 0.0), ("b", 1.1, 0.0)]) == ["a", "b"]
    assert equal_times(1.0, 1.35) and not equal_times(1.0, 1.36) and equal_times(1.0, 1.5, 0.0, 0.5)


def _row(name, seconds, error, normal=1.0, memory=1000, spread=0.05, stable=True, cpu=None, cpu_stable=True):
    return {"name": name, "label": name, "memory_bytes": memory,
            "accuracy": {"band_1mm": {"distance_mean_mm": error, "normal_mean_deg": normal}},
            "timings": [{"path": "embedded", "device": "cpu", "mode": "distance+normal+contact",
                         "points": 100, "median_s": seconds * 100, "spread": spread, "stable": stable,
                         "repeats": 5, "times_s": [seconds * 100] * 5,
                         "cpu_median_s": None if cpu is None else cpu * 100, "cpu_spread": 0.05,
                         "cpu_stable": cpu_stable}]}


def test_no_front_is_called_from_an_unstable_reference_time():
    report = {"config": {"sizes": [100], "timing": {"max_spread": 0.25}}, "colliders": [
        _row("exact", 10.0, 0.0), _row("grid", 0.2, 0.03, spread=0.6, stable=False)]}
    assert front(report, "cpu", "distance") is None
    text = front_text(report, "cpu")
    assert text.startswith("Pareto front (cpu): not called: the reference time of grid (spread 60 % over 5 calls)")
    report["colliders"][1] = _row("grid", 0.2, 0.03)
    assert front(report, "cpu", "distance") == ["grid", "exact"]
    assert "Pareto front (cpu, time vs distance error): grid, exact" in front_text(report, "cpu")


def test_unstable_wall_times_fall_back_to_stable_cpu_times_for_the_front_and_the_pick():
    report = {"config": {"sizes": [100], "timing": {"max_spread": 0.25}}, "skipped": [], "colliders": [
        _row("exact", 10.0, 0.0, cpu=9.0), _row("grid", 0.2, 0.03, spread=0.6, stable=False, cpu=12.0),
        _row("coarse", 0.1, 0.2, cpu=0.1)]}
    assert ranking_basis(report) == "cpu"
    # On CPU time the grid (12 s) is slower than the exact mesh (9 s) and less accurate: dominated.
    assert front(report, "cpu", "distance") == ["coarse", "exact"]
    text = front_text(report, "cpu")
    assert "the wall times of grid (spread 60 % over 5 calls) stayed unstable" in text
    assert "Pareto front (cpu, CPU time vs distance error): coarse, exact" in text
    assert [r["name"] for r in rank(report, Budget(0.05))] == ["exact", "grid"]
    report["colliders"][0] = _row("exact", 10.0, 0.0, cpu=9.0, cpu_stable=False)
    assert ranking_basis(report) is None and front(report, "cpu", "distance") is None


def test_when_stable_wall_and_cpu_times_call_different_fronts_the_cpu_one_is_called():
    """Measured on the shared machine: voxel 32^3 1.56x faster than 64^3 in wall time (cache
    traffic of other processes slows the 1 MB grid more), 1.2x in CPU time: the ranking by wall
    time was the load's, not the colliders'."""
    report = {"config": {"sizes": [100], "timing": {"max_spread": 0.25}}, "skipped": [], "colliders": [
        _row("voxel-32", 0.36, 0.28, cpu=0.25), _row("voxel-64", 0.56, 0.08, cpu=0.30),
        _row("mesh", 41.0, 0.0, cpu=23.0)]}
    assert ranking_basis(report) == "cpu" and front(report, "cpu", "distance") == ["voxel-64", "mesh"]
    assert "wall and CPU times call different fronts" in front_text(report, "cpu")
    report["colliders"][1] = _row("voxel-64", 0.40, 0.08, cpu=0.30)  # both agree now: wall time it is
    assert ranking_basis(report) == "wall" and front(report, "cpu", "distance") == ["voxel-64", "mesh"]


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


def test_a_budget_met_exactly_is_met_and_every_limit_checked_is_named():
    budget = Budget(0.05, max_normal_error_deg=3.0, max_memory_bytes=1000)
    exact = {"distance_mean_mm": 0.05, "normal_mean_deg": 3.0}
    assert budget.misses_figures(exact, 1000) == []
    assert [text for _, text in budget.checks(exact, 1000)] == [
        "mean distance error 0.0500 mm <= 0.05 mm", "mean normal error 3.00 deg <= 3 deg", "memory 1 kB <= 1 kB"]
    assert budget.misses_figures({"distance_mean_mm": 0.0500001, "normal_mean_deg": 3.0}, 1001) == [
        "mean distance error 0.0500 mm > 0.05 mm", "memory 1 kB > 1 kB"]
    report = {"config": {"sizes": [100]}, "skipped": [], "colliders": [_row("grid", 0.2, 0.05)]}
    assert [r["name"] for r in rank(report, Budget(0.05))] == ["grid"]


def test_memory_limits_are_shown_in_units_that_tell_them_apart():
    assert format_bytes(1000) == "1 kB" and format_bytes(512) == "512 bytes"
    assert format_bytes(8_388_608) == "8.39 MB" and format_bytes(1.5e9) == "1.5 GB"
    assert Budget(0.05, max_memory_bytes=size_bytes("1KB")).describe() == \
        "mean distance error <= 0.05 mm, memory <= 1 kB (+-1 mm band)"
    import trimesh

    from collider_server.engine.meshes import Mesh

    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    plan = plan_candidates(Mesh(np.asarray(box.vertices), np.asarray(box.faces), "box"), np.eye(4),
                           PlanConfig(kinds=("voxel",), resolutions=(8,), max_memory_bytes=size_bytes("1KB")), None)
    assert plan.skipped == [{"name": "voxel-8", "reason": "2.05 kB grid exceeds --max-memory 1 kB; larger grids not tried"}]


def test_rank_takes_the_fastest_that_meets_every_limit_and_explains_when_none_does():
    report = {"config": {"sizes": [10, 100]}, "skipped": [],
              "colliders": [_row("exact", 10.0, 0.0, 0.0, 2000), _row("grid", 0.2, 0.03, 4.0, 8000),
                            _row("coarse", 0.1, 0.2, 6.0, 100), _row("net", 5.0, 0.02, 2.0, 500)]}
    assert [r["name"] for r in rank(report, Budget(0.05))] == ["grid", "net", "exact"]
    assert [r["name"] for r in rank(report, Budget(0.05, max_normal_error_deg=3))] == ["net", "exact"]
    assert [r["name"] for r in rank(report, Budget(0.05, max_memory_bytes=1000))] == ["net"]
    with pytest.raises(NothingMeetsBudget, match=r"no measured collider meets.*\n.*exact: memory 2 kB > 10 bytes"):
        rank(report, Budget(0.001, max_memory_bytes=10))


def test_rank_takes_the_smaller_of_colliders_equally_fast_within_the_measurement():
    # The voxel 128^3 (0.30 s per 1M) and 256^3 (0.35 s): equally fast on a busy
    # machine; the pick is the one with an eighth of the memory.
    report = {"config": {"sizes": [100]}, "skipped": [],
              "colliders": [_row("voxel-256", 0.30, 0.008, memory=67_000_000),
                            _row("voxel-128", 0.35, 0.024, memory=8_400_000), _row("mesh", 30.0, 0.0)]}
    ranked = rank(report, Budget(0.05))
    assert [r["name"] for r in ranked] == ["voxel-128", "voxel-256", "mesh"]
    assert [r["name"] for r in equally_fast(report, ranked)] == ["voxel-256"]
    report["colliders"][1] = _row("voxel-128", 0.50, 0.024, memory=8_400_000)  # 1.67x: measurably slower
    assert next(r["name"] for r in rank(report, Budget(0.05))) == "voxel-256"


def test_plan_stops_voxels_at_the_memory_budget_and_lists_every_neural_preset(monkeypatch, load_shared_mesh):
    from collider_server.engine.kinds import neural

    mesh = load_shared_mesh("stanford-bunny.obj")
    monkeypatch.setitem(neural.PRESETS, "bench-test-preset", neural.Architecture(16, 2, 32, 3.0))
    plan = plan_candidates(mesh, np.eye(4), PlanConfig(resolutions=(32, 64, 128), max_memory_bytes=2_000_000),
                           REPO_ROOT / "models")
    names = [c.name for c in plan.candidates]
    assert names[:4] == ["kdtree", "mesh", "voxel-32", "voxel-64"]
    assert "neural-bunny" in names  # the shipped model of this very mesh file
    skipped = {s["name"]: s for s in plan.skipped}
    assert skipped["voxel-128"]["reason"] == "8.39 MB grid exceeds --max-memory 2 MB; larger grids not tried"
    assert skipped["neural-bench-test-preset"]["preset"] == "bench-test-preset"  # a new preset shows up by itself
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
    assert {s["name"]: s.get("model") for s in other.skipped}["neural-bunny"] == "bunny"


def collider_here(*args):
    """The same entry point in this process (no interpreter start-up): (exit code, stdout, stderr)."""
    result = run_collider(*args)
    return result.returncode, result.stdout, result.stderr


@pytest.fixture(scope="module")
def quick_bench(built_once, bunny):
    """``collider bench BUNNY --quick`` run once per test run (every worker's tests read the same
    one), in the process of the worker that builds it (its served half behind a real ``collider
    serve``): (output folder, report dict, stdout)."""

    def bench(out: Path) -> None:
        result = run_collider("bench", bunny, "--quick", "--quiet", "--models", REPO_ROOT / "models",
                          "--output", out / "result", "--cache", out / "cache")
        assert result.returncode == 0, result.stdout + result.stderr
        (out / "stdout.txt").write_text(result.stdout)

    out = built_once("quick-bench", bench)
    return out, json.loads((out / "result" / "bench.json").read_text()), (out / "stdout.txt").read_text()


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
        assert all(t["median_s"] > 0 and 1 <= t["repeats"] <= 15 for t in row["timings"])
        reference = [t for t in row["timings"] if t["reference"]]
        assert [(t["path"], t["mode"], t["points"]) for t in reference] == [
            ("embedded", "distance+normal+contact", 40_000)]
        assert reference[0]["repeats"] >= 3 and reference[0]["spread"] is not None
        assert all(t["cpu_median_s"] > 0 and len(t["cpu_s"]) == t["repeats"] for t in row["timings"])
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
    assert report["timing"]["rounds"] >= 5 and report["machine"]["torch_threads"] == max(1, (os.cpu_count() or 2) - 1)
    # Freed memory kept as `collider serve` keeps it (engine/memory.py): the two paths alike.
    if platform.libc_ver()[0] == "glibc" and not ({"MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"} & set(os.environ)
                                                  or "threshold" in os.environ.get("GLIBC_TUNABLES", "")):
        assert report["held_freed_memory_bytes"] >= 32 << 20
    assert "mesh: 69,451 faces, not watertight (5 holes, 223 boundary edges), 1 piece" in stdout
    assert "sign errors, +-1 mm band" in stdout and f"cache {out / 'cache'}: " in stdout
    assert not list((out / "cache").glob("served-*"))  # the served run's links are gone
    png = (out / "result" / "bench-cpu.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


@pytest.mark.slow
def test_budget_bake_picks_the_fastest_collider_that_meets_it_and_checks_it_afresh(quick_bench, tmp_path, bunny,
                                                                                  monkeypatch):
    """In this process (the pick is under test, not the interpreter), its fresh evaluation on
    20,000 points per set of the bunny instead of 100,000 (the exact distances are most of its
    cost; test_the_budget_bake_trains_neural_candidates... checks the default)."""
    from collider_cli.commands import budget

    monkeypatch.setattr(budget, "FRESH_POINTS", 20_000)
    out, report, _ = quick_bench
    mesh = bunny
    code, stdout, stderr = collider_here("bake", mesh, "--name", "picked", "--models", tmp_path,
                                         "--max-error", "0.1mm", "--bench", out / "result" / "bench.json",
                                         "--quiet", "--cache", out / "cache")
    assert code == 0, stdout + stderr
    from collider_server.engine.modelfile import read_info

    info = read_info(tmp_path / "picked.safetensors")
    expected = rank(report, Budget(0.1))[0]
    assert info.settings["picked_for_budget"]["candidate"] == expected["name"]
    assert info.kind == expected["kind"]
    assert info.accuracy["band_1mm"]["distance_mean_mm"] <= 0.1  # the fresh evaluation, seed 1234
    assert "meets the budget" in stdout
    verdict = next(line for line in stdout.splitlines() if "meets the budget" in line)
    assert verdict.endswith(f"meets the budget: mean distance error "
                            f"{info.accuracy['band_1mm']['distance_mean_mm']:.4f} mm <= 0.1 mm")

    # A memory limit at the shipped network's size: whatever is picked is what rank() says, and a
    # picked network is the trained model's own file (the shipped bunny is smaller than `mesh`).
    limit = next(r for r in report["colliders"] if r["name"] == "neural-bunny")["memory_bytes"]
    code, stdout, stderr = collider_here("bake", mesh, "--name", "small", "--models", tmp_path,
                                         "--max-error", "0.05mm", "--max-memory", str(limit), "--bench",
                                         out / "result" / "bench.json", "--quiet", "--cache", out / "cache")
    assert code == 0, stdout + stderr
    info = read_info(tmp_path / "small.safetensors")
    picked = rank(report, Budget(0.05, max_memory_bytes=limit))[0]
    assert info.settings["picked_for_budget"]["candidate"] == picked["name"] and info.kind == picked["kind"]

    code, _, stderr = collider_here("bake", mesh, "--name", "none", "--models", tmp_path, "--max-error",
                                    "0.05mm", "--max-memory", "0.5MB", "--bench", out / "result" / "bench.json",
                                    "--quiet", "--cache", out / "cache")
    assert code == 1
    assert "no measured collider meets mean distance error <= 0.05 mm" in stderr
    assert "Traceback" not in stderr and not (tmp_path / "none.safetensors").exists()


@pytest.mark.parametrize("args, message", [
    (["--max-error", "nan"], "--max-error must be a finite number"),
    (["--max-normal-error", "3deg"], "need --max-error"),
    (["--max-error", "0.05mm", "--max-memory", "lots"], "--max-memory must be"),
])
def test_budget_bake_refuses_bad_limits_in_one_line(args, message, tmp_path, bunny):
    code, _, err = collider_here("bake", bunny, "--name", "x", "--models", tmp_path, *args)
    assert code == 2 and message in err and "Traceback" not in err


def test_bench_refuses_unknown_kinds_and_a_bench_file_of_another_mesh(tmp_path, bunny):
    code, _, err = collider_here("bench", bunny, "--kinds", "voxel,magic")
    assert code == 2 and "--kinds must name some of" in err
    other = tmp_path / "bench.json"
    other.write_text(json.dumps({"mesh": {"sha256": "0" * 64, "transform": np.eye(4).tolist(), "path": "x.obj"}}))
    code, _, err = collider_here("bake", bunny, "--name", "x", "--models", tmp_path, "--max-error", "1mm",
                                 "--bench", other)
    assert code == 2 and "measured another mesh or placement" in err


def test_bench_places_the_mesh_like_every_command_and_reports_errors_in_mm(tmp_path, bunny):
    """The bunny in metres and the same bunny in millimetres (--scale 1000 --units mm) give the
    same physical errors: figures are in mm whatever the collider's units."""
    reports = {}
    for label, placement in (("m", []), ("mm", ["--scale", "1000", "--units", "mm"])):
        out = tmp_path / label
        code, stdout, err = collider_here("bench", bunny, *placement, "--kinds", "kdtree", "--no-served",
                                          "--sizes", "1k", "--accuracy-points", "3000", "--repeats", "1",
                                          "--quiet", "--output", out, "--cache", tmp_path / "cache")
        assert code == 0, stdout + err
        reports[label] = json.loads((out / "bench.json").read_text())
    assert reports["mm"]["mesh"]["units"] == "mm" and reports["mm"]["mesh"]["transform"][0][0] == 1000.0
    metres = reports["m"]["colliders"][0]["accuracy"]["band_1mm"]["distance_mean_mm"]
    millimetres = reports["mm"]["colliders"][0]["accuracy"]["band_1mm"]["distance_mean_mm"]
    assert 0.1 < metres < 0.5 and millimetres == pytest.approx(metres, rel=1e-3)


def assert_labels_readable(fig, report):
    """Every label of the error-vs-time figure lies inside its panel, covers no marker and no
    other label, and is either next to one of its own markers (embedded or served: nearer to it
    than to another collider's) or tied to its marker by a leader line."""
    from matplotlib.text import Annotation

    from collider_cli.bench.report import text_box

    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        # The time axis's numbers: each one readable, none running into the next.
        ticks = [t for t in ax.get_xticklabels(which="both") if t.get_visible() and t.get_text()]
        lo, hi = ax.get_xlim()
        ticks = [t for t in ticks if lo <= t.get_position()[0] <= hi]
        assert len(ticks) >= 2, [t.get_text() for t in ticks]
        boxes = sorted((t.get_window_extent(renderer) for t in ticks), key=lambda b: b.x0)
        assert all(a.x1 < b.x0 for a, b in itertools.pairwise(boxes)), [t.get_text() for t in ticks]
        markers = []
        for collection in ax.collections:
            sizes = collection.get_sizes()
            # a collider's colour: the embedded marker's fill, the served (hollow) marker's edge
            faces = collection.get_facecolors()
            colour = tuple(np.round((faces if len(faces) else collection.get_edgecolors())[0][:3], 3))
            for (x, y), size in zip(collection.get_offsets(), np.broadcast_to(sizes, (len(collection.get_offsets()),))):
                if size > 20:  # the colliders' markers (not the front's small dots)
                    cx, cy = ax.transData.transform((x, y))
                    r = np.sqrt(size) * fig.dpi / 72 / 2
                    markers.append((cx, cy, r, colour))
        labels = [a for a in ax.texts if isinstance(a, Annotation)]
        assert len(labels) == len(report["colliders"])
        frame = ax.get_window_extent(renderer)
        boxes = []
        for label in labels:
            b = text_box(label, renderer)
            assert frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1, label.get_text()
            for cx, cy, r, _ in markers:  # no marker under the text
                assert not (b.x0 < cx + r and cx - r < b.x1 and b.y0 < cy + r and cy - r < b.y1), label.get_text()
            for other in boxes:
                assert not (b.x0 < other.x1 and other.x0 < b.x1 and b.y0 < other.y1 and other.y0 < b.y1)
            boxes.append(b)
            own = ax.transData.transform(label.xy)
            own_colour = next(m[3] for m in markers if np.allclose(m[:2], own, atol=1.0))
            centre = np.array([(b.x0 + b.x1) / 2, (b.y0 + b.y1) / 2])
            nearest = min(markers, key=lambda m: np.hypot(*(centre - np.array(m[:2]))))
            assert label.arrow_patch is not None or nearest[3] == own_colour, label.get_text()


@pytest.mark.slow
def test_the_plot_labels_each_marker_without_covering_another(quick_bench):
    import matplotlib.pyplot as plt

    from collider_cli.bench.report import figure

    _, report, _ = quick_bench
    fig = figure(report, "cpu")
    try:
        assert_labels_readable(fig, report)
    finally:
        plt.close(fig)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(30))
def test_the_plot_labels_stay_readable_whatever_the_timings(quick_bench, seed):
    """The same, on the measured report with each collider's embedded and served times scaled
    at random (0.3x to 3x; served sometimes as fast as embedded): markers land beside each other as they may on a loaded machine (a
    served marker 3 px from its embedded one once put the label nearer it than its own)."""
    import copy

    import matplotlib.pyplot as plt

    from collider_cli.bench.report import figure

    report = copy.deepcopy(quick_bench[1])
    rng = np.random.default_rng(seed)
    for row in report["colliders"]:
        scale = {path: rng.uniform(0.3, 3.0) for path in ("embedded", "served")}
        if rng.random() < 0.3:  # served as fast as embedded: the two markers overlap
            scale["served"] = scale["embedded"] * rng.uniform(0.98, 1.02)
        for timing in row["timings"]:
            k = scale[timing["path"]]
            for key in ("median_s", "cpu_median_s"):
                timing[key] *= k
            timing["cpu_s"] = [t * k for t in timing["cpu_s"]]
            if timing.get("times_s"):
                timing["times_s"] = [t * k for t in timing["times_s"]]
    fig = figure(report, "cpu")
    try:
        assert_labels_readable(fig, report)
    finally:
        plt.close(fig)


@pytest.mark.slow
def test_the_budget_bake_trains_neural_candidates_and_names_every_limit_it_checked(tmp_path, monkeypatch):
    """In this process, its measurement made small (what is asserted is which candidates were
    trained and measured, and the verdict, not their figures): 5,000 points per call and per
    band, three rounds, 20,000 training samples per network; the pick's fresh evaluation is the
    bake's own (100,000 points per band)."""
    import trimesh

    from collider_cli.bench import plan
    from collider_cli.commands import budget

    monkeypatch.setattr(budget, "BUDGET_POINTS", 5_000)
    monkeypatch.setattr(budget, "BUDGET_ACCURACY_POINTS", 5_000)
    monkeypatch.setattr(budget, "BUDGET_TIMING", {"repeats": 3, "cell_budget_s": 0.2, "warmup_points": 1_000})
    monkeypatch.setattr(plan, "BENCH_TRAINING_SAMPLES", 20_000)
    mesh = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=0.05).export(mesh)
    result = run_collider("bake", mesh, "--name", "pick", "--models", tmp_path / "models", "--max-error", "0.5mm",
                      "--max-normal-error", "20deg", "--max-memory", "3MB", "--train-minutes", "0.02",
                      "--cache", tmp_path / "cache", "--quiet")
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads((tmp_path / "cache" / "budget-pick" / "bench.json").read_text())
    trained = {r["settings"]["preset"] for r in report["colliders"] if r["build"] == "train"}
    from collider_server.engine.kinds.neural import PRESETS

    assert trained == set(PRESETS)  # every preset, trained 0.02 min each, was a candidate
    assert not [s for s in report["skipped"] if s.get("preset")]
    verdict = next(line for line in result.stdout.splitlines() if "meets the budget" in line)
    assert re.fullmatch(r"fresh evaluation \(seed 1234, 100,000 points per band\) meets the budget: mean distance "
                        r"error \d\.\d{4} mm <= 0\.5 mm; mean normal error \d+\.\d\d deg <= 20 deg; memory "
                        r"[\d.]+ (kB|MB|bytes) <= 3 MB", verdict), verdict
    assert "mesh: 1,280 faces, watertight, 1 piece, no self-intersections" in result.stdout
    assert f"cache {tmp_path / 'cache'}: " in result.stdout


def test_a_served_call_faster_than_embedded_is_retimed_whatever_its_cell_budget():
    """Slow cells time one call each (their budget spent); a served one faster than its embedded
    twin has no spread to judge by: both are timed again until it is not faster beyond it."""
    clock, order = FakeClock(), []
    cells = _cells(clock, {"mesh embedded": [4.8, 4.8, 4.8], "mesh served": [3.8, 4.9, 5.0]}, order)
    time_rounds(cells, TimingPolicy(repeats=5, cell_budget_s=1.0, retime_rounds=10), clock=clock)
    assert [len(c.timing.times_s) for c in cells] == [2, 2]
    assert not served_beats_embedded(cells[0].timing, cells[1].timing)


def test_figures_unstable_in_cpu_time_only_are_retimed_too():
    """The front may rank by CPU time (when wall times stay unstable): a cell steady in wall time
    but not in CPU time is retimed as well."""
    clock, order = FakeClock(), []
    steps, reads = [0.01, 0.05, 0.01, 0.09], [0, 0.0]

    def cpu():  # advances by the next of ``steps`` at each reading pair, like FakeClock
        reads[0] += 1
        if reads[0] % 2 == 0:
            reads[1] += steps[(reads[0] // 2 - 1) % len(steps)]
        return reads[1]

    cells = _cells(clock, {"steady": 1.0}, order, cpu=(cpu,))
    time_rounds(cells, TimingPolicy(repeats=4, cell_budget_s=100.0, retime_rounds=3), clock=clock)
    t = cells[0].timing
    assert t.stable(0.25) and not t.cpu_stable(0.25) and t.retimed == 3 and len(t.cpu_s) == 7


def test_an_interrupted_budget_bake_says_where_its_measured_figures_are(tmp_path, monkeypatch):
    """Issue 35: Ctrl-C during the budget bake's measuring said "the report holds what was
    measured" without saying where: it names the files it wrote, in the cache's budget-NAME/."""
    from collider_cli.bench import run as bench_run

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(bench_run, "build_all", interrupt)
    cache = tmp_path / "cache"
    code, _out, err = collider_here("bake", REPO_ROOT / "examples/meshes/spot.obj", "--z-up", "--fit-size",
                                   "0.2", "--name", "cut", "--models", tmp_path / "models", "--max-error",
                                   "0.05mm", "--cache", cache, "--quiet")
    assert code == 130, err
    folder = cache / "budget-cut"
    assert f"interrupted: {folder / 'bench.md'} and {folder / 'bench.json'} hold what was measured until then" in err
    assert json.loads((folder / "bench.json").read_text())["interrupted"] is True
    assert not (tmp_path / "models" / "cut.safetensors").exists()


def test_the_readme_says_what_the_quick_bench_of_its_tour_measures(tmp_path):
    """Issue 35: the tour said "every kind" of a quick bench that measures no neural collider
    (four "not measured" lines). Its line names what the quick plan builds for spot and says the
    networks are not measured."""
    from collider_cli.bench import QUICK
    from collider_server.making.mesh_files import load_mesh

    (line,) = [line for line in (REPO_ROOT / "README.md").read_text().splitlines()
               if line.startswith("collider bench ") and "--quick" in line]
    plan = plan_candidates(load_mesh(REPO_ROOT / "examples/meshes/spot.obj"), np.eye(4), QUICK.plan, tmp_path)
    comment = line.split("#", 1)[1]
    built = [c.kind if c.kind != "voxel" else f"{c.settings['resolution']}^3" for c in plan.candidates]
    assert built == ["kdtree", "mesh", "32^3", "64^3"]
    assert all(name in comment for name in built), comment
    assert {s["name"].split("-")[0] for s in plan.skipped} == {"neural"}
    assert "every kind" not in comment and "neural presets are listed as not measured" in comment
