"""``collider bench``'s measurement run: build every candidate collider of a mesh, measure its
accuracy against the exact SDF and its query time embedded and served, on CPU and on CUDA when
present, and return every raw figure as one JSON-ready dict (see :func:`run_bench`).

Units: lengths in the placed mesh's units inside the engine; every reported error in mm and
degrees, times in seconds, memory in bytes. Frames: all points are in the collider frame (the
placed mesh's frame), which is also the world frame here (identity pose).
"""

from __future__ import annotations

import contextlib
import functools
import os
import platform
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from collider_server.engine.devices import DEVICE_KINDS
from collider_server.engine.memory import hold_freed_memory
from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.making.progress import format_duration, progress

from .plan import Candidate, PlanConfig, build_candidate, build_seconds_estimate, plan_candidates
from .report import REFERENCE_MODE, size_label
from .timing import MODES, Cell, Timing, TimingPolicy, process_cpu_clock, time_rounds, warm_up

PATHS = ("embedded", "served")


@dataclass(frozen=True)
class BenchConfig:
    """sizes : points per query call (the paper's table rows); accuracy_points : points per
    band for the error figures; paths : "embedded" and/or "served"; devices : None for "cpu"
    plus "cuda" when present; seed : of every point set; threads : CPU threads of the engine
    (None: what ``collider serve`` computes with by default, all cores but one), used embedded
    and by the served process alike."""

    sizes: tuple[int, ...] = (10_000, 40_000, 1_000_000)
    accuracy_points: int = 40_000
    paths: tuple[str, ...] = PATHS
    devices: tuple[str, ...] | None = None
    seed: int = 0
    threads: int | None = None
    timing: TimingPolicy = field(default_factory=TimingPolicy)
    plan: PlanConfig = field(default_factory=PlanConfig)

    def check(self) -> None:
        if not self.sizes or any(not isinstance(n, int) or n < 1 for n in self.sizes):
            raise ValueError(f"--sizes must be positive integers, got {list(self.sizes)}")
        if not isinstance(self.accuracy_points, int) or self.accuracy_points < 1:
            raise ValueError(f"--accuracy-points must be a positive integer, got {self.accuracy_points!r}")
        if not set(self.paths) <= set(PATHS) or not self.paths:
            raise ValueError(f"paths must be some of {list(PATHS)}, got {list(self.paths)}")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {self.threads}")
        self.timing.check()
        self.plan.check()


#: ``collider bench --quick``: the same run at a size that takes well under a minute.
QUICK = BenchConfig(sizes=(10_000, 40_000), accuracy_points=5_000,
                    timing=TimingPolicy(repeats=5, cell_budget_s=1.0, warmup_points=2_000),
                    plan=PlanConfig(resolutions=(32, 64)))


def default_devices() -> tuple[str, ...]:
    import torch

    return ("cpu", "cuda") if torch.cuda.is_available() else ("cpu",)


def default_threads() -> int:
    """``collider serve``'s compute threads when not told (and ``collider simulate``'s embedded
    engine's): all cores but one, at least one."""
    return max(1, (os.cpu_count() or 2) - 1)


def say(text: str) -> None:
    """One line for the person watching (stderr: stdout is the report)."""
    print(text, file=sys.stderr, flush=True)


def run_bench(mesh: Mesh, transform: np.ndarray, config: BenchConfig, *, units: str = "m",
              meters_per_unit: float = 1.0, models_root: Path | None = None, cache: Path,
              mesh_path: str = "", show_progress: bool = True) -> dict:
    """Measure every candidate of ``mesh`` (already placed: ``transform`` is what was applied
    to the file's coordinates). Returns the report dict (``colliders``, ``skipped``, ``mesh``,
    ``machine``, ``config``, ``timing``, ``seconds``, and ``interrupted`` when Ctrl-C or SIGTERM
    ended the run early: the report then holds what was measured until then).

    cache : grids, bench-trained networks and the served run's repository (links) go there."""
    import torch

    config.check()
    started = time.perf_counter()
    load_at_start = load_average()
    torch.set_num_threads(config.threads or default_threads())
    # As `collider serve` does (its setting hold_freed_memory), so that the embedded and served
    # paths differ only by the service.
    held = hold_freed_memory()
    devices = config.devices or default_devices()
    plan = plan_candidates(mesh, transform, config.plan, models_root)
    if not plan.candidates:
        raise ValueError("nothing to measure: " + "; ".join(f"{s['name']}: {s['reason']}" for s in plan.skipped))
    rows: dict[str, dict] = {}
    report = {
        "mesh": {"path": mesh_path, "name": mesh.name, "sha256": mesh.sha256,
                 "vertices": len(mesh.vertices), "faces": len(mesh.faces),
                 "transform": np.asarray(transform).tolist(), "units": units,
                 "meters_per_unit": meters_per_unit},
        "config": {**asdict(config), "devices": list(devices)},
        "colliders": [], "skipped": plan.skipped, "timing": {}, "held_freed_memory_bytes": held,
    }
    try:
        sets = point_sets(mesh, config, meters_per_unit)
        sdf = ExactSDF(mesh)
        colliders = build_all(plan.candidates, mesh, transform, sdf, sets, config, units=units,
                              meters_per_unit=meters_per_unit, cache=cache, rows=rows,
                              show_progress=show_progress)
        report["timing"] = time_all(plan.candidates, colliders, devices, sets["timing"], config, cache,
                                    rows, show_progress)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the report of what was measured until now
        interrupted(report)
    return finish_report(report, rows, load_at_start, started)


def interrupted(report: dict) -> None:
    """Mark ``report`` as cut short (Ctrl-C or SIGTERM) and say so; whoever writes the report
    says where it is (:func:`~.report.interrupted_line`)."""
    report["interrupted"] = True
    say("interrupted: measuring stopped; writing what was measured until now")


def finish_report(report: dict, rows: dict, load_at_start, started: float) -> dict:
    """``report`` with its collider rows, the machine (and its load from ``load_at_start``) and
    the seconds since ``started`` (``time.perf_counter``)."""
    report["colliders"] = list(rows.values())
    report["machine"] = machine_info(load_at_start)
    report["seconds"] = time.perf_counter() - started
    return report


def build_all(candidates: list[Candidate], mesh: Mesh, transform, sdf: ExactSDF, sets: dict,
              config: BenchConfig, *, units: str, meters_per_unit: float, cache: Path, rows: dict,
              show_progress: bool) -> dict:
    """Build (or take from the cache) every candidate and measure its accuracy, first saying how
    long that will take (from the exact SDF's cost measured on this machine). Fills ``rows``;
    returns name -> collider (CPU)."""
    probe = sets["band_1mm"][: min(len(sets["band_1mm"]), 5_000)]
    sdf.query(probe[:16])  # its trees are built by the first query: not a cost per point
    t0 = time.perf_counter()
    sdf.query(probe)
    per_point = (time.perf_counter() - t0) / len(probe)
    builds = {c.name: build_seconds_estimate(c, mesh, transform, units, meters_per_unit, cache, per_point)
              for c in candidates}
    # Accuracy: the exact SDF at both bands' points once, then per candidate at its contacts.
    accuracy = 2 * config.accuracy_points * per_point
    total = sum(builds.values()) + (len(candidates) + 1) * accuracy
    slow = [f"{c.label} {format_duration(builds[c.name])}" for c in candidates if builds[c.name] >= 10]
    say(f"bench: building and measuring {len(candidates)} colliders, about {format_duration(total)}"
        + (f" ({', '.join(slow)})" if slow else "")
        + f" (the exact SDF measured at {per_point * 1e6:.1f} us per point here)")
    from collider_server.making.evaluation import exact_reference

    references = {band: exact_reference(sdf, sets[band]) for band in ACCURACY_BANDS}
    colliders = {}
    with progress(len(candidates) * 2, "bench: build + accuracy", "step", show_progress) as bar:
        for candidate in candidates:
            bar.set_postfix_str(f"build {candidate.label}")
            collider = build_candidate(candidate, mesh, transform, units=units, meters_per_unit=meters_per_unit,
                                       cache=cache, show_progress=False)
            bar.update(1)
            bar.set_postfix_str(f"accuracy {candidate.label}")
            rows[candidate.name] = candidate_row(candidate, collider, sdf, sets, references)
            colliders[candidate.name] = collider
            bar.update(1)
    return colliders


def point_sets(mesh: Mesh, config: BenchConfig, meters_per_unit: float) -> dict[str, np.ndarray]:
    """``band_1mm`` and ``band_10mm`` (accuracy, float64) and ``timing`` (float32): points
    around the surface moved along the face normal by U(-band, band), collider frame. The
    timing set is the +-10 mm band set itself (where a cloth simulator queries): the accuracy in
    that band is measured on its first ``accuracy_points`` points."""
    from collider_server.making.sampling import band_sets

    n = config.accuracy_points
    sets = band_sets(mesh, n, config.seed, meters_per_unit,
                     sizes={"band_10mm": max(max(config.sizes), n)})
    ten = sets["band_10mm"]
    return {"band_1mm": sets["band_1mm"], "band_10mm": ten[:n], "timing": ten.astype(np.float32)}


#: The point sets a candidate's accuracy is measured on.
ACCURACY_BANDS = ("band_1mm", "band_10mm")


def candidate_row(candidate: Candidate, collider, sdf: ExactSDF, sets: dict, references: dict) -> dict:
    """Everything but the timings of one candidate: accuracy per band, build cost, memory.
    ``references``: band -> the exact SDF at its points (:func:`exact_reference`), the same for
    every candidate."""
    from collider_server.making.evaluation import error_figures

    accuracy = {band: error_figures(collider, sdf, sets[band], reference=references[band])
                for band in ACCURACY_BANDS}
    return {**candidate.to_dict(), "file_bytes": int(candidate.path.stat().st_size),
            "memory_bytes": int(collider.nbytes()), "accuracy": accuracy, "timings": []}


def _devices_of(candidate: Candidate, devices) -> list[str]:
    return [d for d in devices if d == "cpu" or candidate.kind in DEVICE_KINDS]


def time_all(candidates: list[Candidate], colliders: dict, devices, points: np.ndarray, config: BenchConfig,
             cache: Path, rows: dict, show_progress: bool, modes: dict = MODES,
             reference_mode: str = REFERENCE_MODE, at: float | None = None,
             asked: dict[str, dict] | None = None) -> dict:
    """Time every cell of every candidate in interleaved rounds (:mod:`.timing`): embedded, and
    behind one real ``collider serve`` per device when served is asked for. Appends each cell's
    figures to its row (also when interrupted); returns the run's timing summary.

    modes : the query modes timed (name -> fields); reference_mode : the one ranked by
    at : seconds, when animated colliders are asked (every call at this one time)
    asked : per mode, the pose keywords of its queries (a skinned collider's ``clip`` and
        ``time``, or ``joint_transforms``), instead of ``at``"""
    from contextlib import ExitStack

    policy = config.timing
    biggest = max(config.sizes)
    cells: list[Cell] = []
    with ExitStack() as stack:
        clients = {}
        if "served" in config.paths:
            for device in devices:
                served = [c for c in candidates if device in _devices_of(c, devices)]
                if served:
                    say(f"bench: starting collider serve on {device} with {len(served)} colliders ...")
                    clients[device] = stack.enter_context(served_client(served, device, cache, config))
        embedded = {}
        for candidate in candidates:
            for device in _devices_of(candidate, devices):
                embedded[candidate.name, device] = (colliders[candidate.name] if device == "cpu" else
                                                    _load_on(candidate, device))
        # Cells in round order: per device, mode and size, every collider, embedded then served
        # (twins side by side, so a load burst hits both).
        warm: dict[tuple, float] = {}
        for device in devices:
            for mode, fields in modes.items():
                for size in config.sizes:
                    chunk = points[:size]
                    for candidate in candidates:
                        if device not in _devices_of(candidate, devices):
                            continue
                        for path in config.paths:
                            if path == "served" and device not in clients:
                                continue
                            keywords = asked[mode] if asked is not None else {"time": at}
                            call, clocks = _query_call(path, embedded.get((candidate.name, device)),
                                                       clients.get(device), candidate.name, device, fields,
                                                       keywords)
                            timing = Timing(path, device, mode, size,
                                            reference=(mode == reference_mode and size == biggest
                                                       and path == "embedded"))
                            cells.append(Cell(candidate.name, timing, functools.partial(call, chunk), clocks))
                            key = (candidate.name, path, device, mode)
                            if key not in warm:  # one untimed call per (collider, path, device, mode)
                                warm[key] = warm_up(functools.partial(call, points[: min(policy.warmup_points,
                                                                                         len(points))]))
        per_point = {k: v / min(policy.warmup_points, len(points)) for k, v in warm.items()}
        expected = [per_point[c.name, c.timing.path, c.timing.device, c.timing.mode] * c.timing.points
                    for c in cells]
        calls = sum(_expected_calls(c, e, policy) for c, e in zip(cells, expected, strict=True))
        estimate = sum(_expected_calls(c, e, policy) * e for c, e in zip(cells, expected, strict=True))
        say(f"bench: timing {len(cells)} cells in {policy.repeats} interleaved rounds, about "
            f"{format_duration(estimate)} (from the warm-up calls)")
        rounds = 0
        try:
            with progress(calls, "bench: timing", "call", show_progress) as bar:
                def on_call(cell):
                    if bar.n >= bar.total:  # retiming adds calls beyond the plan
                        bar.total += 1
                    bar.set_postfix_str(f"{cell.name} {cell.timing.path} {size_label(cell.timing.points)}",
                                        refresh=False)
                    bar.update(1)

                rounds = time_rounds(cells, policy, on_call)
        finally:
            for cell in cells:
                if cell.timing.times_s:
                    rows[cell.name]["timings"].append(cell.timing.to_dict(policy.max_spread))
    retimed = sorted({f"{c.name} {c.timing.path} {c.timing.mode} {size_label(c.timing.points)}"
                      for c in cells if c.timing.retimed})
    return {"rounds": rounds, "estimate_s": estimate, "retimed": retimed,
            "max_spread": policy.max_spread}


def _expected_calls(cell: Cell, seconds: float, policy: TimingPolicy) -> int:
    floor = min(policy.min_repeats, policy.repeats) if cell.timing.reference else 1
    within = int(policy.cell_budget_s // seconds) + 1 if seconds > 0 else policy.repeats
    return max(floor, min(policy.repeats, within))


def _load_on(candidate: Candidate, device: str):
    from collider_server.engine.modelfile import load_collider

    return load_collider(candidate.path, device)


def _query_call(path: str, collider, client, name: str, device: str, fields, keywords: dict):
    """``(call(points), cpu clocks)`` of one (collider, path, device, fields), asked with the
    query's pose ``keywords`` (``time``; a skinned collider's ``clip``, ``joint_transforms``)."""
    if path == "embedded":
        def call(chunk):
            result = collider.query(chunk, fields, **keywords)
            if device != "cpu":
                _synchronize(device)
            return result

        return call, (process_cpu_clock(),)
    return (lambda chunk: client.query(name, chunk, fields=fields, **keywords)), (process_cpu_clock(),
                                                                              client.server_cpu_clock)


@contextlib.contextmanager
def served_client(candidates: list[Candidate], device: str, cache: Path, config: BenchConfig):
    """A client of one real ``collider serve --device DEVICE`` (HTTP + msgpack, float32 points)
    serving ``candidates`` (links to their files in a folder of the cache, removed after); the
    server gets as many compute threads as this process uses, so the two paths differ only by
    the service. The client carries ``server_cpu_clock``, the server process's CPU seconds."""
    import torch

    from collider_client import Client

    from ..launch import serve_process

    biggest = max(config.sizes)
    flags = ["--device", device, "--compute-threads", str(torch.get_num_threads()), "--log-level", "warning",
             "--max-request-points", str(max(biggest, 1_000_000)),
             "--max-queue-points", str(max(4 * biggest, 4_000_000)),
             "--max-body-bytes", str(max(64 * 2**20, 64 * biggest))]
    served = cache / f"served-{os.getpid()}-{device.replace(':', '-')}"
    shutil.rmtree(served, ignore_errors=True)
    served.mkdir(parents=True)
    try:
        for candidate in candidates:
            (served / f"{candidate.name}.safetensors").symlink_to(Path(candidate.path).resolve())
        with serve_process(served, *flags, ready_timeout_s=300.0, capture=True) as server, \
                Client(server.url, timeout_s=None) as client:
            client.server_cpu_clock = process_cpu_clock(server.process.pid)
            yield client
    finally:
        shutil.rmtree(served, ignore_errors=True)


def _synchronize(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def load_average() -> float | None:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def machine_info(load_at_start: float | None) -> dict:
    """CPU model, cores, GPU, load average (start and end of the run) and library versions."""
    from importlib import metadata

    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    versions = {}
    for package in ("torch", "numpy", "scipy", "libigl", "trimesh", "fastapi", "uvicorn", "msgpack"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"cpu": cpu, "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(), "gpu": gpu,
            "platform": platform.platform(), "python": platform.python_version(), "versions": versions,
            "load_average_start": load_at_start, "load_average_end": load_average(),
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
