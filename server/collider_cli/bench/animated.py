"""``collider bench MESH --animation CACHE --fps F``: what accuracy costs in time for the animated
colliders of an animation, measured here.

Candidates (:func:`plan_animated`), in the order they are measured:

- ``mesh``: exact at any time (the linearly interpolated vertices);
- ``voxel`` at each resolution of ``resolutions`` and each keyframe count of ``keyframes`` (grids
  evenly spaced from the first frame to the last, :func:`~collider_server.making.bake.
  keyframe_positions`), leaving out any whose memory (``K R^3 4`` bytes) exceeds
  ``max_memory_bytes``. The grids of one resolution are baked once for every keyframe count
  (5, 13 and 25 keyframes of 25 frames share their grids) and cached like the static bench's;
- ``neural``: the 4D networks (each animated preset: ``keyframes`` and ``deformed``,
  docs/neural.md) trained here for ``train_minutes`` each on the CPU and cached like a voxel set
  (0, the default: listed as not measured, with the option that measures them).

Another animated kind joins by an entry in :data:`KINDS`: a function listing its candidates and
one building (or loading) a candidate.

Accuracy: errors pooled over ``times`` random times drawn uniformly over the animation
(:func:`~collider_server.making.sampling.random_times`: between frames), against the exact
interpolated mesh at each (:func:`~collider_server.making.evaluation.animated_error_figures`),
the same times for every candidate. Timing: the static bench's interleaved rounds
(:func:`.run.time_all`), every query at one more random time, ``distance`` and
``distance+normal+contact+velocity``, embedded and served. The report, its tables and the plot
are the static bench's (:mod:`.report`), with the animation and its times.

Units: the placed animation's inside the engine; errors in mm and degrees, times in seconds,
memory in bytes. Frames: every point is in the collider frame (the world frame here).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from collider_server.engine.animated_meshes import AnimatedMesh, ExactAtTimes
from collider_server.engine.collider import Collider
from collider_server.making.progress import format_duration, progress

from .plan import BENCH_TRAINING_SAMPLES, Candidate, Plan
from .run import (
    BenchConfig,
    default_devices,
    default_threads,
    finish_report,
    interrupted,
    load_average,
    say,
    time_all,
)
from .timing import ANIMATED_MODES

REFERENCE_MODE = "distance+normal+contact+velocity"


@dataclass(frozen=True)
class AnimatedPlanConfig:
    """What to compare for an animation.

    kinds : animated kinds to include (some of :data:`KINDS`)
    resolutions : voxel samples per axis; keyframes : voxel keyframe counts (None: one per frame)
    max_memory_bytes : largest memory of one collider (larger voxel sets are left out)
    padding : domain padding, fraction of the largest side over every frame
    times : random times the errors are measured at
    train_minutes : training time of the 4D network (0: not measured)
    """

    kinds: tuple[str, ...] = ("mesh", "voxel", "neural")
    resolutions: tuple[int, ...] = (32, 64, 128)
    keyframes: tuple[int | None, ...] = (5, 13, None)
    max_memory_bytes: int = 256 * 2**20
    padding: float = 0.1
    times: int = 8
    train_minutes: float = 0.0

    def check(self) -> None:
        unknown = set(self.kinds) - set(KINDS)
        if unknown or not self.kinds:
            raise ValueError(f"--kinds with --animation must name some of {list(KINDS)}, got {list(self.kinds)}")
        if not self.resolutions or any(not isinstance(r, int) or r < 8 for r in self.resolutions):
            raise ValueError(f"--resolutions must be integers >= 8, got {list(self.resolutions)}")
        if not self.keyframes or any(k is not None and (not isinstance(k, int) or k < 2) for k in self.keyframes):
            raise ValueError(f"--keyframes must be integers >= 2 or 'all', got {list(self.keyframes)}")
        if not self.max_memory_bytes > 0:
            raise ValueError(f"--max-memory must be > 0, got {self.max_memory_bytes}")
        if not isinstance(self.times, int) or self.times < 1:
            raise ValueError(f"--times must be a positive number of random times, got {self.times!r}")
        if not (np.isfinite(self.train_minutes) and self.train_minutes >= 0):
            raise ValueError(f"--train-minutes must be a finite number >= 0, got {self.train_minutes}")


#: ``collider bench --quick --animation ...``: small grids, few keyframes, few times.
QUICK_PLAN = AnimatedPlanConfig(resolutions=(16, 32), keyframes=(5, None), times=4)


# -- the kinds: their candidates and how each is built ---------------------------------------------


def mesh_candidates(animation: AnimatedMesh, config: AnimatedPlanConfig):
    return [Candidate("mesh", "mesh (exact)", "mesh", {"padding": config.padding})], []


def voxel_candidates(animation: AnimatedMesh, config: AnimatedPlanConfig):
    from .budget import format_bytes

    frames = animation.timeline.frames
    counts = sorted({frames if k is None else k for k in config.keyframes}, reverse=True)
    candidates, skipped = [], []
    for resolution in sorted(config.resolutions):
        # Most keyframes first: the smaller sets of the same resolution reuse their grids.
        for keyframes in counts:
            name = f"voxel-{resolution}-k{keyframes}"
            size = keyframes * resolution**3 * 4
            if keyframes > frames:
                skipped.append({"name": name, "reason": f"{keyframes} keyframes, but the animation has "
                                                        f"{frames} frames"})
            elif size > config.max_memory_bytes:
                skipped.append({"name": name, "reason": f"{format_bytes(size)} of grids exceeds --max-memory "
                                                        f"{format_bytes(config.max_memory_bytes)}"})
            else:
                every = " (every frame)" if keyframes == frames else ""
                candidates.append(Candidate(name, f"voxel {resolution}^3 x {keyframes}{every}", "voxel",
                                            {"resolution": resolution, "keyframes": keyframes,
                                             "padding": config.padding}))
    return candidates, skipped


def neural_candidates(animation: AnimatedMesh, config: AnimatedPlanConfig):
    from collider_server.engine.kinds.neural import ANIMATED_PRESETS

    minutes = config.train_minutes
    if minutes <= 0:
        return [], [{"name": f"neural-{preset}", "preset": preset,
                     "reason": "the 4D network is trained by the bench only when asked: give --train-minutes M"}
                    for preset in ANIMATED_PRESETS]
    return [Candidate(f"neural-{preset}", f"neural {preset} ({minutes:g} min)", "neural",
                      {"preset": preset, "train_minutes": minutes}, build="train")
            for preset in ANIMATED_PRESETS], []


def build_mesh(candidate: Candidate, animation: AnimatedMesh, shared: dict, **settings) -> Collider:
    from collider_server.making.bake import bake_animated_collider

    return bake_animated_collider(animation, "mesh", candidate.name, padding=candidate.settings["padding"],
                                  **settings)


def build_voxel(candidate: Candidate, animation: AnimatedMesh, shared: dict, **settings) -> Collider:
    """Bake the keyframe grids not in ``shared`` (grids by resolution, then frame position);
    ``candidate.settings["grid_seconds"]``: the measured seconds of one grid at its resolution."""
    from collider_server.making.bake import bake_animated_collider

    resolution = candidate.settings["resolution"]
    grids = shared.setdefault(("voxel", resolution), {})
    before = len(grids)
    started = time.perf_counter()
    collider = bake_animated_collider(animation, "voxel", candidate.name, resolution=resolution,
                                      keyframes=candidate.settings["keyframes"],
                                      padding=candidate.settings["padding"], grids=grids, **settings)
    baked = len(grids) - before
    if baked:
        shared[("voxel-seconds", resolution)] = (time.perf_counter() - started) / baked
    return collider


def build_neural(candidate: Candidate, animation: AnimatedMesh, shared: dict, *, units: str,
                 meters_per_unit: float, device: str, show_progress: bool) -> Collider:
    """Train the 4D network for ``train_minutes`` (the clock starts after its exact samples)."""
    from collider_server.making.training import TrainConfig, train_animated_neural

    config = TrainConfig(preset=candidate.settings["preset"], max_minutes=candidate.settings["train_minutes"],
                         samples=BENCH_TRAINING_SAMPLES)
    return train_animated_neural(animation, candidate.name, config, units=units, meters_per_unit=meters_per_unit,
                                 device=device, show_progress=show_progress).collider


#: The animated kinds: (candidates(animation, config) -> (candidates, skipped), build(candidate,
#: animation, shared, **bake settings) -> collider). A new animated kind adds its entry here.
KINDS = {"mesh": (mesh_candidates, build_mesh), "voxel": (voxel_candidates, build_voxel),
         "neural": (neural_candidates, build_neural)}


def plan_animated(animation: AnimatedMesh, config: AnimatedPlanConfig) -> Plan:
    """The candidates for ``animation`` (placed), not yet built, in :data:`KINDS` order."""
    config.check()
    candidates, skipped = [], []
    for kind, (listed, _) in KINDS.items():
        if kind in config.kinds:
            found, notes = listed(animation, config)
            candidates += found
            skipped += notes
    return Plan(candidates, skipped)


def animation_key(animation: AnimatedMesh, transform, units: str, meters_per_unit: float) -> str:
    """Short hash of the animation's files (or frames), rate, loop, placement and units."""
    digest = hashlib.sha256()
    digest.update((animation.sha256 + animation.cache_sha256).encode()
                  or np.ascontiguousarray(animation.frames).tobytes())
    digest.update(np.round(np.asarray(transform, np.float64), 12).tobytes())
    timeline = animation.timeline
    digest.update(repr((timeline.frames, float(timeline.frame_rate_hz), timeline.loop, units,
                        float(meters_per_unit))).encode())
    return digest.hexdigest()[:16]


def candidate_path(candidate: Candidate, key: str, cache: Path) -> Path:
    """Where ``candidate``'s file lives in ``cache``: the animation's key, then every setting."""
    detail = hashlib.sha256(json.dumps(candidate.settings, sort_keys=True).encode()).hexdigest()[:8]
    return cache / "colliders" / f"{key}-{candidate.name}-{detail}.safetensors"


def build_animated(candidate: Candidate, animation: AnimatedMesh, transform, *, units: str,
                   meters_per_unit: float, cache: Path, shared: dict) -> Collider:
    """Build ``candidate`` on the CPU, or load it from ``cache`` (``colliders/``, keyed by
    :func:`animation_key` and its settings); set its ``path`` and ``build_seconds`` (a voxel
    set: its keyframes times the measured seconds of one grid, whether baked now or for a set
    before it)."""
    from collider_server.engine.modelfile import load_collider, save_collider

    path = candidate_path(candidate, animation_key(animation, transform, units, meters_per_unit), cache)
    candidate.path = path
    if path.is_file() and candidate.kind != "mesh":
        collider = load_collider(path, "cpu")
        candidate.build_seconds = collider.info.settings.get("bench_build_seconds")
        return collider
    started = time.perf_counter()
    collider = KINDS[candidate.kind][1](candidate, animation, shared, units=units,
                                        meters_per_unit=meters_per_unit, device="cpu", show_progress=False)
    candidate.build_seconds = time.perf_counter() - started
    if candidate.kind == "voxel":
        per_grid = shared.get(("voxel-seconds", candidate.settings["resolution"]))
        candidate.build_seconds = None if per_grid is None else per_grid * candidate.settings["keyframes"]
    collider.info.source["transform"] = np.asarray(transform).tolist()
    collider.info.settings["bench_build_seconds"] = candidate.build_seconds
    path.parent.mkdir(parents=True, exist_ok=True)
    save_collider(collider, path)
    return collider


def run_animated_bench(animation: AnimatedMesh, transform: np.ndarray, config: BenchConfig,
                       plan_config: AnimatedPlanConfig, *, units: str = "m", meters_per_unit: float = 1.0,
                       cache: Path, mesh_path: str = "", cache_path: str = "",
                       show_progress: bool = True) -> dict:
    """Measure every candidate of ``animation`` (placed: ``transform`` was applied to the files'
    coordinates). Returns the report dict of :func:`.run.run_bench` plus ``animation`` (frames,
    rate, duration, loop, cache, ``times_s`` the random times of the errors, ``timing_time_s``
    the time every query was timed at) and ``reference_mode``."""
    import torch

    from collider_server.making.evaluation import animated_error_figures
    from collider_server.making.sampling import band_sets, random_times

    config.check()
    plan_config.check()
    started = time.perf_counter()
    load_at_start = load_average()
    torch.set_num_threads(config.threads or default_threads())
    devices = config.devices or default_devices()
    plan = plan_animated(animation, plan_config)
    if not plan.candidates:
        raise ValueError("nothing to measure: " + "; ".join(f"{s['name']}: {s['reason']}" for s in plan.skipped))
    timeline = animation.timeline
    times = random_times(timeline, plan_config.times, config.seed)
    timing_time = float(random_times(timeline, 1, config.seed + 99)[0])
    first = animation.frame(0)
    rows: dict[str, dict] = {}
    report = {
        "mesh": {"path": mesh_path, "name": animation.name, "sha256": animation.sha256,
                 "vertices": animation.vertex_count, "faces": len(animation.faces),
                 "transform": np.asarray(transform).tolist(), "units": units, "meters_per_unit": meters_per_unit},
        "animation": {**timeline.to_dict(), "cache": cache_path or animation.cache,
                      "cache_sha256": animation.cache_sha256, "times_s": times.tolist(),
                      "timing_time_s": timing_time},
        "reference_mode": REFERENCE_MODE,
        "config": {**asdict(config), "plan": asdict(plan_config), "devices": list(devices)},
        "colliders": [], "skipped": plan.skipped, "timing": {},
    }
    per_time = -(-config.accuracy_points // len(times))
    try:
        say(f"bench: building and measuring {len(plan.candidates)} animated colliders ("
            + build_estimate(plan.candidates, animation, first, cache, transform, units, meters_per_unit)
            + f"), errors at {len(times)} random times")
        exact = ExactAtTimes(animation, keep=len(times))
        colliders, shared = {}, {}
        with progress(len(plan.candidates) * 2, "bench: build + accuracy", "step", show_progress) as bar:
            for candidate in plan.candidates:
                bar.set_postfix_str(f"build {candidate.label}")
                collider = build_animated(candidate, animation, transform, units=units,
                                          meters_per_unit=meters_per_unit, cache=cache, shared=shared)
                bar.update(1)
                bar.set_postfix_str(f"accuracy {candidate.label}")
                accuracy = animated_error_figures(collider, animation, times, per_time, config.seed,
                                                  sets=("band_1mm", "band_10mm"), exact=exact)
                rows[candidate.name] = {**candidate.to_dict(), "file_bytes": int(candidate.path.stat().st_size),
                                        "memory_bytes": int(collider.nbytes()), "accuracy": accuracy,
                                        "timings": []}
                colliders[candidate.name] = collider
                bar.update(1)
        shared.clear()  # the grids live on in the colliders that use them
        sets = band_sets(animation.mesh_at(timing_time), 1, config.seed, meters_per_unit,
                         sizes={"band_10mm": max(config.sizes)})
        report["timing"] = time_all(plan.candidates, colliders, devices, sets["band_10mm"].astype(np.float32),
                                    config, cache, rows, show_progress, modes=ANIMATED_MODES,
                                    reference_mode=REFERENCE_MODE, at=timing_time)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the report of what was measured until now
        interrupted(report)
    return finish_report(report, rows, load_at_start, started)


def build_estimate(candidates, animation: AnimatedMesh, first, cache: Path, transform, units: str,
                   meters_per_unit: float) -> str:
    """How long the builds will take: the voxel grids not cached, at the exact SDF's cost per point
    measured now on the first frame, and the minutes of the networks to train."""
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.bake import exact_seconds_per_point, keyframe_positions, padded_box

    key = animation_key(animation, transform, units, meters_per_unit)
    grids: dict[int, set] = {}
    for c in candidates:
        if c.kind != "voxel" or candidate_path(c, key, cache).is_file():
            continue
        positions = keyframe_positions(animation.timeline.frames, c.settings["keyframes"])
        grids.setdefault(c.settings["resolution"], set()).update(float(p) for p in positions)
    # Measured at the resolution that costs the most, as its bake will ask.
    heaviest = max(grids, key=lambda r: r**3 * len(grids[r]), default=64)
    per_point = exact_seconds_per_point(ExactSDF(first), *padded_box(animation, 0.1), heaviest)
    seconds = sum(r**3 * len(p) for r, p in grids.items()) * per_point
    training = sum(c.settings["train_minutes"] for c in candidates
                   if c.kind == "neural" and not candidate_path(c, key, cache).is_file())
    return (f"{sum(len(p) for p in grids.values())} keyframe grids to bake, about {format_duration(seconds)} at "
            f"{per_point * 1e6:.1f} us per exact distance"
            + (f"; {training:g} min of training, after its exact samples" if training else ""))
