"""Which colliders a bench compares, and how each one is built (or found) for a mesh.

Candidates, in the order they are measured:

- ``kdtree``: the paper's baseline (nearest vertex, approximate);
- ``mesh``: exact closest point on the triangles;
- ``voxel`` at each resolution of ``resolutions`` (ascending), stopping before the first grid
  whose memory (``resolution**3 * 4`` bytes) exceeds ``max_memory_bytes``;
- ``neural``: for every preset of :data:`collider_server.engine.kinds.neural.PRESETS`, the trained
  models of this mesh in the model repository (same source file sha256 and placement), else a
  training run of ``train_minutes`` when that is > 0; trained models of the mesh with an
  architecture outside the presets are included too.

Voxel grids and bench-trained networks are cached in the cache folder's ``colliders/`` (keyed by
the mesh file's sha256, the placement and the settings), with the seconds their bake or training
took, so a second run measures the same colliders without rebuilding them and still reports what
building cost; the mesh and kdtree colliders, rebuilt every run, are written there too (a served
run loads every candidate from its file).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from collider_server.engine.collider import Collider
from collider_server.engine.meshes import Mesh

KINDS = ("kdtree", "mesh", "voxel", "neural")
VOXEL_BYTES_PER_SAMPLE = 4  # float32 grid
#: Exact samples a bench's training run caches (static or 4D): a run of a few minutes sees each
#: several times, and making more would take longer than the training.
BENCH_TRAINING_SAMPLES = 500_000


@dataclass(frozen=True)
class PlanConfig:
    """What to compare.

    kinds : the collider kinds to include (subset of :data:`KINDS`)
    resolutions : voxel samples per axis to try, ascending
    max_memory_bytes : largest memory of one collider (voxel resolutions stop before it)
    train_minutes : training time per neural preset that has no trained model of the mesh
        (0: such presets are listed as skipped)
    padding : domain padding, fraction of the largest side (voxel, mesh, kdtree)
    presets : the neural presets to include (None: every preset of the registry)
    """

    kinds: tuple[str, ...] = KINDS
    resolutions: tuple[int, ...] = (64, 128, 256, 512)
    max_memory_bytes: int = 128 * 2**20
    train_minutes: float = 0.0
    padding: float = 0.1
    presets: tuple[str, ...] | None = None

    def check(self) -> None:
        unknown = set(self.kinds) - set(KINDS)
        if unknown or not self.kinds:
            raise ValueError(f"--kinds must name some of {list(KINDS)}, got {list(self.kinds)}")
        if any(not isinstance(r, int) or r < 8 for r in self.resolutions):
            raise ValueError(f"--resolutions must be integers >= 8, got {list(self.resolutions)}")
        if not self.max_memory_bytes > 0:
            raise ValueError(f"--max-memory must be > 0, got {self.max_memory_bytes}")
        if not (np.isfinite(self.train_minutes) and self.train_minutes >= 0):
            raise ValueError(f"--train-minutes must be a finite number >= 0, got {self.train_minutes}")
        if self.presets is not None:
            from collider_server.engine.kinds.neural import PRESETS

            unknown = sorted(set(self.presets) - set(PRESETS))
            if unknown or not self.presets:
                raise ValueError(f"--presets must name some of {sorted(PRESETS)}, got {list(self.presets)}")


@dataclass
class Candidate:
    """One collider of the comparison.

    name : model name in the bench's served repository (also the JSON key), e.g. "voxel-128"
    label : what tables and plots call it, e.g. "voxel 128^3"
    kind : collider kind
    settings : what distinguishes it (resolution, preset, model file, ...)
    path : its model file once built (None before)
    build : "bake", "train" (timed in this run or cached from an earlier bench run) or "trained"
        (an existing model of the repository; its own training time is reported)
    build_seconds : wall time of the bake or training (None when unknown)
    """

    name: str
    label: str
    kind: str
    settings: dict = field(default_factory=dict)
    path: Path | None = None
    build: str = "bake"
    build_seconds: float | None = None

    def to_dict(self) -> dict:
        data = asdict(self)
        data["path"] = None if self.path is None else str(self.path)
        return data


@dataclass
class Plan:
    candidates: list[Candidate]
    skipped: list[dict]  # {"name", "reason"}: what was left out and why


def placement_key(mesh: Mesh, transform: np.ndarray, padding: float, units: str,
                  meters_per_unit: float) -> str:
    """Short hash of the source file, the placement, the units and the padding: the cache
    key's stem."""
    digest = hashlib.sha256()
    digest.update(mesh.sha256.encode() or np.ascontiguousarray(mesh.vertices).tobytes())
    digest.update(np.round(np.asarray(transform, np.float64), 12).tobytes())
    digest.update(repr((float(padding), units, float(meters_per_unit))).encode())
    return digest.hexdigest()[:16]


def plan_candidates(mesh: Mesh, transform: np.ndarray, config: PlanConfig,
                    models_root: Path | None) -> Plan:
    """The candidates for ``mesh`` (already placed by ``transform``), not yet built."""
    from .budget import format_bytes

    config.check()
    candidates: list[Candidate] = []
    skipped: list[dict] = []
    for kind in ("kdtree", "mesh"):
        if kind in config.kinds:
            label = "kdtree (approximate)" if kind == "kdtree" else "mesh (exact)"
            candidates.append(Candidate(kind, label, kind, {"padding": config.padding}))
    if "voxel" in config.kinds:
        for resolution in sorted(config.resolutions):
            size = resolution**3 * VOXEL_BYTES_PER_SAMPLE
            if size > config.max_memory_bytes:
                skipped.append({"name": f"voxel-{resolution}", "reason": (
                    f"{format_bytes(size)} grid exceeds --max-memory "
                    f"{format_bytes(config.max_memory_bytes)}; larger grids not tried")})
                break
            candidates.append(Candidate(f"voxel-{resolution}", f"voxel {resolution}^3", "voxel",
                                        {"resolution": resolution, "padding": config.padding}))
    if "neural" in config.kinds:
        found, notes = neural_candidates(mesh, transform, config, models_root)
        candidates += found
        skipped += notes
    return Plan(candidates, skipped)


def neural_candidates(mesh: Mesh, transform: np.ndarray, config: PlanConfig,
                      models_root: Path | None) -> tuple[list[Candidate], list[dict]]:
    """Trained neural models of this mesh per preset (and outside the presets), and, for
    presets without one, a training candidate (``train_minutes`` > 0) or a skip note."""
    from collider_server.engine.kinds.neural import PRESETS
    from collider_server.engine.modelfile import read_info
    from collider_server.engine.repository import ModelRepository

    repo = ModelRepository(models_root)
    trained: dict[str, list] = {}
    other_placement: list[str] = []
    names = repo.names() if repo.root.is_dir() else []
    for name in names:
        path = repo.path(name)
        try:
            info = read_info(path)
        except ValueError:
            continue  # a damaged file is `collider info`'s business, not the bench's
        if info.kind != "neural" or not mesh.sha256 or info.source.get("sha256") != mesh.sha256:
            continue
        stored = np.asarray(info.source.get("transform", np.eye(4)), dtype=np.float64)
        if stored.shape != (4, 4) or not np.allclose(stored, transform, rtol=1e-9, atol=1e-12):
            other_placement.append(name)
            continue
        preset = preset_of(info.settings.get("architecture", {}))
        trained.setdefault(preset, []).append((name, path, info))
    candidates, skipped = [], []
    wanted = list(PRESETS) + sorted(set(trained) - set(PRESETS))
    if config.presets is not None:
        wanted = [p for p in wanted if p in config.presets]
    for preset in wanted:
        for name, path, info in trained.get(preset, []):
            seconds = info.settings.get("training", {}).get("seconds")
            candidates.append(Candidate(
                f"neural-{name}", f"neural {name} ({preset})", "neural",
                {"preset": preset, "model": name, "model_file": str(path.resolve()),
                 "architecture": info.settings.get("architecture")},
                path=path, build="trained", build_seconds=seconds))
        if preset in trained or preset not in PRESETS:
            continue
        if config.train_minutes > 0:
            candidates.append(Candidate(
                f"neural-{preset}", f"neural {preset} ({config.train_minutes:g} min)", "neural",
                {"preset": preset, "train_minutes": config.train_minutes,
                 "architecture": asdict(PRESETS[preset])}, build="train"))
        else:
            skipped.append({"name": f"neural-{preset}", "preset": preset,
                            "reason": "no trained model of this mesh in the model repository"})
    for name in other_placement:
        skipped.append({"name": f"neural-{name}", "model": name, "reason": (
            "trained from this mesh file with another placement (its source.transform); pass the "
            "same --scale/--fit-size/--z-up to compare it")})
    return candidates, skipped


def preset_of(architecture: dict) -> str:
    """The preset name whose architecture equals ``architecture``, else "custom"."""
    from collider_server.engine.kinds.neural import PRESETS

    for name, arch in PRESETS.items():
        if asdict(arch) == architecture:
            return name
    return "custom"


# -- building -------------------------------------------------------------------------------------


def build_candidate(candidate: Candidate, mesh: Mesh, transform: np.ndarray, *, units: str,
                    meters_per_unit: float, cache: Path, show_progress: bool = True) -> Collider:
    """Build (or load from ``cache``) ``candidate``'s collider on the CPU; set ``candidate.path``
    (the file a served run loads: the cached file, or a trained model's own file) and
    ``candidate.build_seconds``; returns the collider.

    cache : the cache folder (:func:`collider_cli.commands.options.default_cache_dir`); files go
        to its ``colliders/`` folder, named by :func:`placement_key` and the settings."""
    from collider_server.engine.modelfile import load_collider, save_collider

    if candidate.build == "trained":
        return load_collider(candidate.path, "cpu")
    if candidate.kind == "voxel" or candidate.build == "train":
        return _cached(candidate, mesh, transform, units, meters_per_unit, cache, show_progress)
    # mesh and kdtree: cheap to build, rebuilt and timed every run (written for the served run)
    from collider_server.making.bake import bake_collider

    started = time.perf_counter()
    collider = bake_collider(mesh, candidate.kind, candidate.name, padding=candidate.settings["padding"],
                             units=units, meters_per_unit=meters_per_unit, device="cpu", show_progress=False)
    candidate.build_seconds = time.perf_counter() - started
    collider.info.source["transform"] = np.asarray(transform).tolist()
    candidate.path = cache_path(candidate, mesh, transform, units, meters_per_unit, cache)
    candidate.path.parent.mkdir(parents=True, exist_ok=True)
    save_collider(collider, candidate.path)
    return collider


def cache_path(candidate: Candidate, mesh: Mesh, transform, units: str, meters_per_unit: float,
               cache: Path) -> Path:
    """Where ``candidate``'s file lives in ``cache``: keyed by the mesh file, the placement, the
    units, the padding and every setting."""
    key = placement_key(mesh, transform, candidate.settings.get("padding", 0.1), units, meters_per_unit)
    detail = json.dumps(candidate.settings, sort_keys=True)
    return cache / "colliders" / f"{key}-{candidate.name}-{hashlib.sha256(detail.encode()).hexdigest()[:8]}.safetensors"


def _cached(candidate: Candidate, mesh: Mesh, transform, units, meters_per_unit, cache: Path,
            show_progress: bool) -> Collider:
    """A voxel grid or a bench-trained network from ``cache``, made (and timed) when absent."""
    from collider_server.engine.modelfile import load_collider, save_collider

    path = cache_path(candidate, mesh, transform, units, meters_per_unit, cache)
    candidate.path = path
    if path.is_file():
        collider = load_collider(path, "cpu")
        candidate.build_seconds = collider.info.settings.get("bench_build_seconds")
        return collider
    started = time.perf_counter()
    if candidate.kind == "voxel":
        from collider_server.making.bake import bake_collider

        collider = bake_collider(mesh, "voxel", candidate.name, resolution=candidate.settings["resolution"],
                                 padding=candidate.settings["padding"], units=units,
                                 meters_per_unit=meters_per_unit, device="cpu",
                                 show_progress=show_progress)
    else:
        from collider_server.making.training import TrainConfig, train_neural

        minutes = candidate.settings["train_minutes"]
        config = TrainConfig(preset=candidate.settings["preset"], max_minutes=minutes, samples=BENCH_TRAINING_SAMPLES)
        collider = train_neural(mesh, candidate.name, config, units=units, meters_per_unit=meters_per_unit,
                                transform=transform, device="cpu", show_progress=show_progress).collider
    collider.info.source["transform"] = np.asarray(transform).tolist()
    candidate.build_seconds = time.perf_counter() - started
    collider.info.settings["bench_build_seconds"] = candidate.build_seconds
    path.parent.mkdir(parents=True, exist_ok=True)
    save_collider(collider, path)
    return collider


def build_seconds_estimate(candidate: Candidate, mesh: Mesh, transform, units: str, meters_per_unit: float,
                           cache: Path, sdf_seconds_per_point: float) -> float:
    """Expected seconds to build ``candidate`` given the exact SDF's measured cost per point: a
    voxel grid's resolution^3 points, a training run's minutes, nothing for what the cache or the
    repository already holds (mesh and kdtree: about a second)."""
    if candidate.build == "trained":
        return 0.0
    if candidate.kind == "voxel" or candidate.build == "train":
        if cache_path(candidate, mesh, transform, units, meters_per_unit, cache).is_file():
            return 0.0
        if candidate.kind == "voxel":
            return candidate.settings["resolution"] ** 3 * sdf_seconds_per_point
        return 60.0 * candidate.settings["train_minutes"] + 500_000 * sdf_seconds_per_point
    return 1.0
