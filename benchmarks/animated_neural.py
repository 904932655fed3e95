"""The 4D neural collider (``collider train --animation``) measured at random times.

Accuracy: at ``--times`` random times (seconds, uniform over the animation, not its frames), points
in the +-1 mm band around the exact interpolated mesh at that time (``--points`` in all); truth: the
exact SDF and its gradient (:class:`ExactAtTimes`). Figures: distance error mean / p99 / max (mm),
sign errors among points with |d| > 0.2 mm (percent), normal angle mean / p99 (degrees), and the
normal speed error (mm/s) against the exact surface's: the vertex velocities interpolated at the
closest point, projected on the normal. And the mean distance error by where the time lies between
two of the collider's keyframes, in fifths of the segment: even, the blend in time is not what
limits it (docs/neural.md).

Memory: the model file's bytes. Query: 1M points in the +-10 mm band at one random time, fields
distance + normal + contact + velocity, against ``--static`` (a static grid network, the same
query without time or velocity), interleaved round by round; median (min - max) seconds.

    python benchmarks/animated_neural.py MODEL --mesh examples/animations/arm.obj \\
        --animation examples/animations/arm.pc2 --fps 24 --static models/bunny.safetensors

``--variants`` instead trains each named architecture for ``--minutes`` (the architecture choice of
docs/neural.md) and measures them alike.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from collider_server.engine.animated_meshes import ExactAtTimes
from collider_server.engine.meshes import barycentric
from collider_server.engine.modelfile import load_collider, save_collider
from collider_server.making.animation_files import load_animation
from collider_server.making.sampling import band_sets

sys.path.insert(0, str(Path(__file__).resolve().parent))
from neural_query import source_mesh

SIGN_THRESHOLD_MM = 0.2


def accuracy(collider, animation, times: int, points: int, seed: int) -> dict:
    """Figures of the module docstring, pooled over every time."""
    rng = np.random.default_rng(seed)
    exact = ExactAtTimes(animation, keep=1)
    to_mm = 1000.0 * collider.info.meters_per_unit
    errors, signs, angles, speeds, fifths = [], [], [], [], []
    keyframes = collider.info.animation["frames"]  # the collider's own keyframes (a network's tables)
    for i, t in enumerate(rng.uniform(0.0, animation.timeline.duration_s, times)):
        sdf, k, rate = exact.at(float(t))
        p = band_sets(sdf.mesh, max(1, points // times), seed + 10 * i, collider.info.meters_per_unit)["band_1mm"]
        truth, closest, face = sdf.query(p)
        normal = sdf.gradient(p, truth, closest, face)
        got = collider.query(p, ["distance", "normal", "velocity"], time=float(t))
        d = got.distance.astype(np.float64)
        errors.append(np.abs(d - truth) * to_mm)
        # Where t lies between two of the collider's keyframes, in fifths: a blend errs most mid-way.
        position = t / animation.timeline.duration_s * (keyframes - 1)
        fifths.append(np.full(len(p), min(int(5 * (position - np.floor(position))), 4)))
        decided = np.abs(truth) * to_mm > SIGN_THRESHOLD_MM
        signs.append(((d < 0) != (truth < 0))[decided])
        cosine = np.clip(np.einsum("ij,ij->i", got.normal.astype(np.float64), normal), -1.0, 1.0)
        angles.append(np.degrees(np.arccos(cosine)))
        corners = animation.faces[face]
        step = (animation.frames[k + 1] - animation.frames[k]) * rate
        true_velocity = np.einsum("mj,mjc->mc", barycentric(closest, sdf.mesh.vertices[corners]), step[corners])
        true_speed = np.einsum("ij,ij->i", true_velocity, normal)
        speed = np.einsum("ij,ij->i", got.velocity.astype(np.float64), normal)
        speeds.append(np.abs(speed - true_speed) * to_mm)
    error, sign, angle, speed, fifth = (np.concatenate(a) for a in (errors, signs, angles, speeds, fifths))
    return {"points": len(error), "times": times,
            "distance_mean_mm": float(error.mean()), "distance_p99_mm": float(np.percentile(error, 99)),
            "distance_max_mm": float(error.max()), "sign_errors_percent": float(100.0 * sign.mean()),
            "normal_mean_deg": float(angle.mean()), "normal_p99_deg": float(np.percentile(angle, 99)),
            "normal_speed_error_mean_mm_s": float(speed.mean()),
            "normal_speed_error_p99_mm_s": float(np.percentile(speed, 99)),
            "distance_mean_mm_by_fifth_of_keyframe_segment": [
                float(error[fifth == j].mean()) if (fifth == j).any() else None for j in range(5)]}


def voxel_keyframe_errors(animation, resolutions, keyframe_counts, times: int, points: int, seed: int,
                          padding: float = 0.1) -> list[dict]:
    """Mean / p99 distance error (mm) of the voxel keyframe collider (``collider bake --animation
    --resolution R --keyframes K``) at the same random times and +-1 mm points as
    :func:`accuracy`, for every R and K, and its memory (K R^3 float32), without baking it: its
    answer at a point is the trilinear interpolation of exact distances at the 8 corners of the
    point's cell, on the two keyframe meshes around the time, blended linearly in time, so only
    those corners are computed (:func:`check_voxel_emulation` pins this to a baked collider)."""
    from collider_contract import Timeline
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.bake import padded_box

    lo, hi = padded_box(animation, padding)
    rng = np.random.default_rng(seed)
    exact = ExactAtTimes(animation, keep=1)
    to_mm = 1000.0  # the shipped animations are in metres
    duration, frames = animation.timeline.duration_s, animation.timeline.frames
    keyed_sdfs: dict = {}
    errors: dict = {(r, k): [] for r in resolutions for k in keyframe_counts}
    for i, t in enumerate(rng.uniform(0.0, duration, times)):
        sdf, _, _ = exact.at(float(t))
        p = band_sets(sdf.mesh, max(1, points // times), seed + 10 * i, 1.0)["band_1mm"]
        truth = sdf.signed_distance(p)
        for count in keyframe_counts:
            k, u, _ = Timeline(count, (count - 1) / duration, animation.timeline.loop).locate(float(t))
            positions = np.linspace(0.0, frames - 1, count)
            ends = []
            for j in (k, k + 1):
                if (count, j) not in keyed_sdfs:
                    keyed_sdfs[(count, j)] = ExactSDF(animation.at_frame(float(positions[j])))
                ends.append(keyed_sdfs[(count, j)])
            for resolution in resolutions:
                d = [trilinear_of_exact(e, p, lo, hi, resolution) for e in ends]
                errors[(resolution, count)].append(np.abs(d[0] + u * (d[1] - d[0]) - truth) * to_mm)
    return [{"resolution": r, "keyframes": k, "memory_bytes": 4 * k * r ** 3,
             "distance_mean_mm": float(np.concatenate(e).mean()),
             "distance_p99_mm": float(np.percentile(np.concatenate(e), 99))}
            for (r, k), e in errors.items()]


def trilinear_of_exact(sdf, p, lo, hi, resolution: int) -> np.ndarray:
    """The voxel collider's distance at ``p`` (inside the box): trilinear interpolation of the
    exact distances (stored as float32) at the corners of an R^3 grid over [lo, hi]."""
    spacing = (hi - lo) / (resolution - 1)
    coords = (p - lo) / spacing
    base = np.clip(np.floor(coords), 0, resolution - 2)
    f = np.clip(coords - base, 0.0, 1.0)
    corners = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])  # x, y, z bits
    where = lo + (base[None] + corners[:, None, :]) * spacing  # (8, n, 3)
    values = sdf.signed_distance(where.reshape(-1, 3)).astype(np.float32).astype(np.float64).reshape(8, -1)
    weights = np.prod(np.where(corners[:, None, :] == 1, f[None], 1.0 - f[None]), axis=2)  # (8, n)
    return (weights * values).sum(axis=0)


def check_voxel_emulation(animation, seed: int) -> float:
    """Largest difference (m) between :func:`trilinear_of_exact` blended in time and a baked
    voxel keyframe collider (R = 24, K = 5) at 2,000 points at random times."""
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.bake import bake_animated_collider, padded_box

    baked = bake_animated_collider(animation, "voxel", "check", resolution=24, keyframes=5, show_progress=False)
    lo, hi = padded_box(animation, 0.1)
    rng = np.random.default_rng(seed)
    worst = 0.0
    positions = np.linspace(0.0, animation.timeline.frames - 1, 5)
    for t in rng.uniform(0.0, animation.timeline.duration_s, 4):
        p = lo + rng.random((500, 3)) * (hi - lo)
        k, u, _ = baked.timeline.locate(float(t))
        d = [trilinear_of_exact(ExactSDF(animation.at_frame(float(positions[j]))), p, lo, hi, 24) for j in (k, k + 1)]
        got = baked.query(p, ["distance"], time=float(t)).distance
        worst = max(worst, float(np.abs(d[0] + u * (d[1] - d[0]) - got).max()))
    return worst


def query_times(collider, static, animation, rounds: int, seed: int) -> dict:
    """Seconds per 1M points (median, min, max over ``rounds``), the animated collider with
    distance + normal + contact + velocity at one time, the static one with distance + normal +
    contact, interleaved."""
    rng = np.random.default_rng(seed)
    t = float(rng.uniform(0.0, animation.timeline.duration_s))
    mesh = animation.mesh_at(t)
    points = band_sets(mesh, 1_000_000, seed, collider.info.meters_per_unit)["band_10mm"]
    static_points = band_sets(static_mesh(static), 1_000_000, seed, static.info.meters_per_unit)["band_10mm"] \
        if static is not None else None
    runs: dict[str, list] = {"animated": [], "static": []}
    for _ in range(rounds):
        started = time.perf_counter()
        collider.query(points, ["distance", "normal", "contact", "velocity"], time=t)
        runs["animated"].append(time.perf_counter() - started)
        if static is not None:
            started = time.perf_counter()
            static.query(static_points, ["distance", "normal", "contact"])
            runs["static"].append(time.perf_counter() - started)
    return {k: {"median_s": float(np.median(v)), "min_s": float(min(v)), "max_s": float(max(v))}
            for k, v in runs.items() if v}


def static_mesh(static):
    """The static model's source mesh (:func:`neural_query.source_mesh`), placed as it was."""
    mesh = source_mesh(static.info, None)
    transform = np.asarray(static.info.source.get("transform", np.eye(4)))
    return mesh if np.allclose(transform, np.eye(4)) else mesh.transformed(transform)


def train_variants(animation, variants: list[str], minutes: float, threads: int, samples: int,
                   folder: Path) -> list[Path]:
    from collider_server.making.training import TrainConfig, train_animated_neural

    paths = []
    for variant in variants:
        architecture = json.loads(variant)
        config = TrainConfig(preset="keyframes", max_minutes=minutes, threads=threads, samples=samples,
                             architecture=architecture)
        result = train_animated_neural(animation, "variant", config, device="cpu", show_progress=False)
        path = save_collider(result.collider, folder / f"variant-{len(paths)}.safetensors")
        print(f"{variant}: {result.summary()}", flush=True)
        paths.append(path)
    return paths


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", nargs="*", help="animated model files to measure")
    parser.add_argument("--mesh", required=True)
    parser.add_argument("--animation", required=True)
    parser.add_argument("--fps", type=float, required=True)
    parser.add_argument("--loop", action="store_true")
    parser.add_argument("--static", default=None, help="a static grid network to time the query against")
    parser.add_argument("--times", type=int, default=50)
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu", help="where the models run (cpu or cuda); training stays on the CPU")
    parser.add_argument("--seed", type=int, default=4321)
    parser.add_argument("--variants", nargs="*", default=[], metavar="JSON",
                        help='architecture overrides of the keyframes preset to train, e.g. \'{"keyframes": 5}\'')
    parser.add_argument("--minutes", type=float, default=5.0, help="training budget per variant")
    parser.add_argument("--samples", type=int, default=1_000_000, help="cached exact samples per variant")
    parser.add_argument("--voxel-resolutions", type=int, nargs="*", default=[],
                        help="also the voxel keyframe collider's error at these resolutions")
    parser.add_argument("--voxel-keyframes", type=int, nargs="*", default=[],
                        help="... and keyframe counts (default: one per frame)")
    parser.add_argument("--out", type=Path, default=Path("runs/animated-neural"), help="variants and report")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    animation = load_animation(args.mesh, args.animation, args.fps, args.loop)
    args.out.mkdir(parents=True, exist_ok=True)
    paths = [Path(p) for p in args.models] + train_variants(animation, args.variants, args.minutes, args.threads,
                                                           args.samples, args.out)
    static = load_collider(args.static, args.device) if args.static else None
    report = {"load_before": os.getloadavg(), "device": args.device, "models": []}
    for path in paths:
        collider = load_collider(path, args.device)
        entry = {"model": str(path), "architecture": collider.info.settings.get("architecture"),
                 "training_s": collider.info.settings.get("training", {}).get("seconds"),
                 "steps": collider.info.settings.get("training", {}).get("steps_done"),
                 "file_bytes": path.stat().st_size, "memory_bytes": collider.nbytes(),
                 "accuracy": accuracy(collider, animation, args.times, args.points, args.seed)}
        if args.rounds:
            entry["query_1M"] = query_times(collider, static, animation, args.rounds, args.seed)
        report["models"].append(entry)
        print(json.dumps(entry, indent=1), flush=True)
    if args.voxel_resolutions:
        report["voxel_emulation_max_difference_m"] = check_voxel_emulation(animation, args.seed)
        print(f"voxel emulation against a baked collider: {report['voxel_emulation_max_difference_m']:.2e} m",
              flush=True)
        report["voxel"] = voxel_keyframe_errors(animation, args.voxel_resolutions,
                                                args.voxel_keyframes or [animation.timeline.frames],
                                                args.times, args.points, args.seed)
        for row in report["voxel"]:
            print(json.dumps(row), flush=True)
    report["load_after"] = os.getloadavg()
    (args.out / "report.json").write_text(json.dumps(report, indent=1))
    print(f"load average before {report['load_before']}, after {report['load_after']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
