"""``collider bench``'s measurement run: build every candidate collider of a mesh, measure its
accuracy against the exact SDF and its query time embedded and served, on CPU and on CUDA when
present, and return every raw figure as one JSON-ready dict (see :func:`run_bench`).

Units: lengths in the placed mesh's units inside the engine; every reported error in mm and
degrees, times in seconds, memory in bytes. Frames: all points are in the collider frame (the
placed mesh's frame), which is also the world frame here (identity pose).
"""

from __future__ import annotations

import os
import platform
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.making.progress import progress

from .plan import Candidate, PlanConfig, build_candidate, plan_candidates
from .timing import MODES, TimingPolicy, time_cells

PATHS = ("embedded", "served")
GPU_KINDS = ("voxel", "neural")  # mesh and kdtree run on the CPU only (libigl, SciPy)


@dataclass(frozen=True)
class BenchConfig:
    """sizes : points per query call (the paper's table rows); accuracy_points : points per
    band for the error figures; paths : "embedded" and/or "served"; devices : None for "cpu"
    plus "cuda" when present; seed : of every point set; threads : torch CPU threads (None:
    torch's default), used embedded and by the served process alike."""

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
                    timing=TimingPolicy(repeats=2, cell_budget_s=1.0, warmup_points=2_000),
                    plan=PlanConfig(resolutions=(32, 64)))


def default_devices() -> tuple[str, ...]:
    import torch

    return ("cpu", "cuda") if torch.cuda.is_available() else ("cpu",)


def run_bench(mesh: Mesh, transform: np.ndarray, config: BenchConfig, *, units: str = "m",
              meters_per_unit: float = 1.0, models_root: Path | None = None,
              cache: Path = Path("out/bench-cache"), work_dir: Path = Path("out/bench"),
              mesh_path: str = "", show_progress: bool = True) -> dict:
    """Measure every candidate of ``mesh`` (already placed: ``transform`` is what was applied
    to the file's coordinates). Returns the report dict (``colliders``, ``skipped``, ``mesh``,
    ``machine``, ``config``, ``seconds``); model files of the run go to ``work_dir/models``."""
    import torch

    config.check()
    started = time.perf_counter()
    load_at_start = _load_average()
    if config.threads is not None:
        torch.set_num_threads(config.threads)
    devices = config.devices or default_devices()
    plan = plan_candidates(mesh, transform, config.plan, models_root)
    if not plan.candidates:
        raise ValueError("nothing to measure: " + "; ".join(f"{s['name']}: {s['reason']}" for s in plan.skipped))
    sets = point_sets(mesh, config, meters_per_unit)
    served_dir = work_dir / "models"
    sdf = ExactSDF(mesh)
    # Progress steps: build + accuracy, then one per timing cell on each path and device.
    cells = len(MODES) * len(config.sizes)
    total = sum(2 + cells * len(_devices_of(c, devices)) * len(config.paths) for c in plan.candidates)
    rows: dict[str, dict] = {}
    with progress(total, "bench", "step", show_progress) as bar:
        for candidate in plan.candidates:
            bar.set_postfix_str(f"build {candidate.label}")
            collider = build_candidate(candidate, mesh, transform, units=units, meters_per_unit=meters_per_unit,
                                       cache=cache, out_dir=served_dir, show_progress=False)
            bar.update(1)
            bar.set_postfix_str(f"accuracy {candidate.label}")
            rows[candidate.name] = candidate_row(candidate, collider, sdf, sets)
            bar.update(1)
            if "embedded" in config.paths:
                for device in _devices_of(candidate, devices):
                    bar.set_postfix_str(f"time {candidate.label}, embedded, {device}")
                    timings = time_embedded(candidate, collider, device, sets["timing"], config,
                                            lambda: bar.update(1))
                    rows[candidate.name]["timings"] += [t.to_dict() for t in timings]
            del collider
        if "served" in config.paths:
            for device in devices:
                names = [c for c in plan.candidates if device in _devices_of(c, devices)]
                if not names:
                    continue
                bar.set_postfix_str(f"start collider serve on {device}")
                for name, timings in time_served(names, served_dir, device, sets["timing"], config,
                                                 bar).items():
                    rows[name]["timings"] += [t.to_dict() for t in timings]
    return {
        "mesh": {"path": mesh_path, "name": mesh.name, "sha256": mesh.sha256,
                 "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
                 "transform": np.asarray(transform).tolist(), "units": units,
                 "meters_per_unit": meters_per_unit},
        "config": {**asdict(config), "devices": list(devices)},
        "machine": machine_info(load_at_start),
        "colliders": list(rows.values()),
        "skipped": plan.skipped,
        "seconds": time.perf_counter() - started,
    }


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


def candidate_row(candidate: Candidate, collider, sdf: ExactSDF, sets: dict) -> dict:
    """Everything but the timings of one candidate: accuracy per band, build cost, memory."""
    from collider_server.making.evaluation import error_figures

    accuracy = {band: error_figures(collider, sdf, sets[band]) for band in ("band_1mm", "band_10mm")}
    return {**candidate.to_dict(), "file_bytes": int(candidate.path.stat().st_size),
            "memory_bytes": int(collider.nbytes()), "accuracy": accuracy, "timings": []}


def _devices_of(candidate: Candidate, devices) -> list[str]:
    return [d for d in devices if d == "cpu" or candidate.kind in GPU_KINDS]


def time_embedded(candidate: Candidate, collider, device: str, points: np.ndarray, config: BenchConfig,
                  on_cell) -> list:
    """The engine in this process: ``Collider.query`` on ``device``."""
    if device != "cpu":
        from collider_server.engine.modelfile import load_collider

        collider = load_collider(candidate.path, device)

    def query(chunk, fields):
        result = collider.query(chunk, fields)
        if device != "cpu":
            _synchronize(device)
        return result

    return time_cells(query, points, config.sizes, "embedded", device, config.timing, on_cell)


def time_served(candidates: list[Candidate], models: Path, device: str, points: np.ndarray,
                config: BenchConfig, bar) -> dict[str, list]:
    """The same colliders behind one real ``collider serve --device DEVICE`` (HTTP + msgpack,
    float32 points) through the client SDK; the server gets as many compute threads as this
    process uses, so the two paths differ only by the service."""
    import torch

    from collider_client import Client

    from ..launch import serve_process

    biggest = max(config.sizes)
    flags = ["--device", device, "--compute-threads", str(torch.get_num_threads()), "--log-level", "warning",
             "--max-request-points", str(max(biggest, 1_000_000)),
             "--max-queue-points", str(max(4 * biggest, 4_000_000)),
             "--max-body-bytes", str(max(64 * 2**20, 64 * biggest))]
    # Only the candidates of this device in the served repository.
    served = models.parent / f"served-{device}"
    served.mkdir(parents=True, exist_ok=True)
    for old in served.glob("*.safetensors"):
        old.unlink()
    for candidate in candidates:
        shutil.copyfile(candidate.path, served / candidate.path.name)
    results = {}
    with serve_process(served, *flags, ready_timeout_s=300.0, capture=True) as server, \
            Client(server.url, timeout_s=None) as client:
        for candidate in candidates:
            bar.set_postfix_str(f"time {candidate.label}, served, {device}")
            results[candidate.name] = time_cells(
                lambda chunk, fields: client.query(candidate.name, chunk, fields=fields),
                points, config.sizes, "served", device, config.timing, lambda: bar.update(1))
    return results


def _synchronize(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def _load_average() -> float | None:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def machine_info(load_at_start: float | None) -> dict:
    """CPU model, cores, GPU, load average (start and end of the run) and library versions."""
    import importlib.metadata as metadata

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
            "load_average_start": load_at_start, "load_average_end": _load_average(),
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
