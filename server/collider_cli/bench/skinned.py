"""``collider bench CHARACTER``: what accuracy costs in time for the skinned colliders of a
character (glTF or USD), at random clip times and at random poses.

Candidates (:func:`plan_skinned`): ``skinned``, the exact kind (built here from the character),
and ``neural-skinned``, each articulated network of the model repository made from this
character file (same sha256) under the same placement; without one, listed as not measured with
the command that trains one.

Accuracy: each candidate in the two pose sets of ``collider eval``
(:func:`~collider_server.making.evaluation.skinned_pose_sets`: ``times`` random clip times, asked
by clip and time, and ``poses`` random poses, every joint turned, asked by joint transforms),
against the exact skin (its union) at each pose
(:func:`~collider_server.making.evaluation.pose_set_figures`), the same poses for every candidate.
Each row's ``accuracy`` holds both sets; its ``band_1mm`` and ``band_10mm`` (what the tables,
the front and the plot rank by) are the random poses'. Timing: the static bench's interleaved
rounds (:func:`.run.time_all`), ``distance`` and ``distance+normal+contact+velocity``, at one more
random clip time and at one more random pose (:data:`.timing.SKINNED_MODES`), embedded and
served, on the +-10 mm band of the skin at that random pose.

Units: the placed character's; errors in mm and degrees, times in seconds, memory in bytes.
Frames: every point is in the collider frame (the world frame here).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from collider_server.engine.collider import Collider

from .plan import Candidate, Plan
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
from .timing import SKINNED_MODES

KINDS = ("skinned", "neural-skinned")
REFERENCE_MODE = "distance+normal+contact+velocity, random pose"


@dataclass(frozen=True)
class SkinnedPlanConfig:
    """kinds : some of :data:`KINDS`; times, poses : random clip times and random poses the
    errors are measured at; padding : the exact kind's domain padding (fraction of the largest
    side)."""

    kinds: tuple[str, ...] = KINDS
    times: int = 8
    poses: int = 8
    padding: float = 0.1

    def check(self) -> None:
        if not self.kinds or set(self.kinds) - set(KINDS):
            raise ValueError(f"--kinds with a character must name some of {list(KINDS)}, got {list(self.kinds)}")
        for option, value in (("--times", self.times), ("--poses", self.poses)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{option} must be a positive number of random {option[2:]}, got {value!r}")


#: ``collider bench --quick CHARACTER``: fewer poses.
QUICK_PLAN = SkinnedPlanConfig(times=4, poses=4)


def plan_skinned(sha256: str, transform: np.ndarray, config: SkinnedPlanConfig, models_root: Path | None,
                 mesh_path: str) -> Plan:
    """The candidates of the character file with ``sha256``, placed by ``transform`` (4, 4)."""
    from collider_server.engine.modelfile import read_info
    from collider_server.engine.repository import ModelRepository

    config.check()
    candidates = []
    if "skinned" in config.kinds:
        candidates.append(Candidate("skinned", "skinned (exact)", "skinned", {"padding": config.padding}))
    if "neural-skinned" not in config.kinds:
        return Plan(candidates, [])
    repo = ModelRepository(models_root)
    found = []
    for name in repo.names() if repo.root.is_dir() else []:
        try:
            info = read_info(repo.path(name))
        except ValueError:
            continue  # a damaged file is `collider info`'s business, not the bench's
        stored = np.asarray(info.source.get("transform", np.eye(4)), dtype=np.float64)
        if (info.kind == "neural-skinned" and sha256 and info.source.get("sha256") == sha256
                and stored.shape == (4, 4) and np.allclose(stored, transform, rtol=1e-9, atol=1e-12)):
            found.append(Candidate(f"neural-{name}", f"neural-skinned {name}", "neural-skinned",
                                   {"model": name, "model_file": str(repo.path(name).resolve())},
                                   path=repo.path(name), build="trained",
                                   build_seconds=info.settings.get("training", {}).get("seconds")))
    skipped = [] if found else [{"name": "neural-skinned", "reason": (
        "no articulated network of this character (same file and placement) in the model repository; "
        f"train one first with `collider train {mesh_path} --name NAME` (and the same placement options)")}]
    return Plan(candidates + found, skipped)


def run_skinned_bench(exact: Collider, read, transform: np.ndarray, config: BenchConfig,
                      plan_config: SkinnedPlanConfig, *, cache: Path, models_root: Path | None,
                      mesh_path: str = "", exact_seconds: float | None = None, show_progress: bool = True) -> dict:
    """Measure the skinned candidates of the character ``read`` (a ``SkinFile``); ``exact``: its
    ``skinned`` collider placed by ``transform`` (its skin is the truth), built in ``exact_seconds``. Returns the report dict
    of :func:`.run.run_bench` plus ``skinned`` (joints, clips, ``perturb_deg``, both pose sets'
    poses, and the clip time and random pose every query was timed at) and ``reference_mode``."""
    import torch

    from collider_server.engine.meshes import Mesh
    from collider_server.engine.modelfile import load_collider, save_collider
    from collider_server.engine.skinning import skin_vertices
    from collider_server.making.evaluation import pose_query, pose_set_figures, skinned_pose_sets
    from collider_server.making.progress import progress
    from collider_server.making.sampling import band_sets

    config.check()
    plan_config.check()
    started = time.perf_counter()
    load_at_start = load_average()
    torch.set_num_threads(config.threads or default_threads())
    devices = config.devices or default_devices()
    plan = plan_skinned(read.sha256, transform, plan_config, models_root, mesh_path)
    if not plan.candidates:
        raise ValueError("nothing to measure: " + "; ".join(f"{s['name']}: {s['reason']}" for s in plan.skipped))
    skin, info = exact.skin, exact.info
    drawn = skinned_pose_sets(skin, plan_config.times, plan_config.poses, config.seed)
    timed = skinned_pose_sets(skin, 1, 1, config.seed + 99)  # one more clip time, one more pose
    asked = {}
    for mode in SKINNED_MODES:
        where = "clip_times" if mode.endswith("clip time") else "random_poses"
        time_s, skeleton = pose_query(timed[where], 0)
        asked[mode] = {**skeleton, **({} if time_s is None else {"time": time_s})}
    report = {
        "mesh": {"path": mesh_path, "name": read.name, "sha256": read.sha256, "vertices": len(skin.vertices),
                 "faces": len(skin.faces), "transform": np.asarray(transform).tolist(), "units": info.units,
                 "meters_per_unit": info.meters_per_unit},
        "skinned": {"joints": skin.skeleton.joint_count, "clips": [c.name for c in skin.clips],
                    "perturb_deg": drawn["random_poses"].perturb_deg,
                    "timed_at": {name: {"clip": p.clips[0], "time_s": float(p.times[0]),
                                        "perturbed": bool(p.perturbed[0])} for name, p in timed.items()}},
        "reference_mode": REFERENCE_MODE,
        "config": {**asdict(config), "plan": asdict(plan_config), "devices": list(devices)},
        "colliders": [], "skipped": plan.skipped, "timing": {},
    }
    rows: dict[str, dict] = {}
    try:
        say(f"bench: measuring {len(plan.candidates)} skinned colliders at {plan_config.times} random clip times "
            f"and {plan_config.poses} random poses")
        colliders = {}
        with progress(len(plan.candidates) * (plan_config.times + plan_config.poses), "bench: accuracy", "pose",
                      show_progress) as bar:
            for candidate in plan.candidates:
                if candidate.kind == "skinned":
                    collider, candidate.build_seconds = exact, exact_seconds
                    candidate.path = cache / "colliders" / f"{read.sha256[:16] or 'character'}-skinned.safetensors"
                    candidate.path.parent.mkdir(parents=True, exist_ok=True)
                    save_collider(exact, candidate.path)  # the file a served run loads
                else:
                    collider = load_collider(candidate.path, "cpu")
                figures = pose_set_figures(collider, skin, drawn, config.accuracy_points, config.seed,
                                           sets=("band_1mm", "band_10mm"), on_pose=lambda: bar.update(1))
                rows[candidate.name] = {**candidate.to_dict(), "file_bytes": int(candidate.path.stat().st_size),
                                        "memory_bytes": int(collider.nbytes()),
                                        "accuracy": {**{k: figures["random_poses"][k] for k in ("band_1mm",
                                                                                                "band_10mm")},
                                                     **figures}, "timings": []}
                colliders[candidate.name] = collider
        posed = Mesh(skin_vertices(skin, timed["random_poses"].transforms[0]), skin.faces, "posed")
        points = band_sets(posed, max(config.sizes), config.seed, info.meters_per_unit)["band_10mm"]
        report["timing"] = time_all(plan.candidates, colliders, devices, points.astype(np.float32), config, cache,
                                    rows, show_progress, modes=SKINNED_MODES, reference_mode=REFERENCE_MODE,
                                    asked=asked)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the report of what was measured until now
        interrupted(report)
    return finish_report(report, rows, load_at_start, started)
