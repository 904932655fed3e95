"""The 4D neural collider (``collider train --animation``) measured at random times.

Accuracy: at ``--times`` random times (seconds, uniform over the animation, not its frames), points
in the +-1 mm band around the exact interpolated mesh at that time (``--points`` in all); truth: the
exact SDF and its gradient (:class:`ExactAtTimes`). Figures: distance error mean / p99 / max (mm),
sign errors among points with |d| > 0.2 mm (percent), normal angle mean / p99 (degrees), and the
normal speed error (mm/s) against the exact surface's: the vertex velocities interpolated at the
closest point, projected on the normal.

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

SIGN_THRESHOLD_MM = 0.2


def accuracy(collider, animation, times: int, points: int, seed: int) -> dict:
    """Figures of the module docstring, pooled over every time."""
    rng = np.random.default_rng(seed)
    exact = ExactAtTimes(animation, keep=1)
    to_mm = 1000.0 * collider.info.meters_per_unit
    errors, signs, angles, speeds = [], [], [], []
    for i, t in enumerate(rng.uniform(0.0, animation.timeline.duration_s, times)):
        sdf, k, rate = exact.at(float(t))
        p = band_sets(sdf.mesh, max(1, points // times), seed + 10 * i, collider.info.meters_per_unit)["band_1mm"]
        truth, closest, face = sdf.query(p)
        normal = sdf.gradient(p, truth, closest, face)
        got = collider.query(p, ["distance", "normal", "velocity"], time=float(t))
        d = got.distance.astype(np.float64)
        errors.append(np.abs(d - truth) * to_mm)
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
    error, sign, angle, speed = (np.concatenate(a) for a in (errors, signs, angles, speeds))
    return {"points": int(len(error)), "times": times,
            "distance_mean_mm": float(error.mean()), "distance_p99_mm": float(np.percentile(error, 99)),
            "distance_max_mm": float(error.max()), "sign_errors_percent": float(100.0 * sign.mean()),
            "normal_mean_deg": float(angle.mean()), "normal_p99_deg": float(np.percentile(angle, 99)),
            "normal_speed_error_mean_mm_s": float(speed.mean()),
            "normal_speed_error_p99_mm_s": float(np.percentile(speed, 99))}


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
    """The static model's source mesh, placed as it was (the shipped bunny's file)."""
    from collider_server.making.mesh_files import load_mesh

    mesh = load_mesh(static.info.source["path"]) if os.path.exists(static.info.source.get("path", "")) \
        else load_mesh(str(Path(__file__).resolve().parents[1] / "examples/meshes/stanford-bunny.obj"))
    transform = np.asarray(static.info.source.get("transform", np.eye(4)))
    return mesh if np.allclose(transform, np.eye(4)) else mesh.transformed(transform)


def train_variants(animation, variants: list[str], minutes: float, threads: int, folder: Path) -> list[Path]:
    from collider_server.making.training import TrainConfig, train_animated_neural

    paths = []
    for variant in variants:
        architecture = json.loads(variant)
        config = TrainConfig(preset="keyframes", max_minutes=minutes, threads=threads, architecture=architecture)
        result = train_animated_neural(animation, "variant", config, show_progress=False)
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
    parser.add_argument("--seed", type=int, default=4321)
    parser.add_argument("--variants", nargs="*", default=[], metavar="JSON",
                        help='architecture overrides of the keyframes preset to train, e.g. \'{"keyframes": 5}\'')
    parser.add_argument("--minutes", type=float, default=5.0, help="training budget per variant")
    parser.add_argument("--out", type=Path, default=Path("runs/animated-neural"), help="variants and report")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    animation = load_animation(args.mesh, args.animation, args.fps, args.loop)
    args.out.mkdir(parents=True, exist_ok=True)
    paths = [Path(p) for p in args.models] + train_variants(animation, args.variants, args.minutes, args.threads,
                                                           args.out)
    static = load_collider(args.static) if args.static else None
    report = {"load_before": os.getloadavg(), "models": []}
    for path in paths:
        collider = load_collider(path)
        entry = {"model": str(path), "architecture": collider.info.settings.get("architecture"),
                 "training_s": collider.info.settings.get("training", {}).get("seconds"),
                 "steps": collider.info.settings.get("training", {}).get("steps_done"),
                 "file_bytes": path.stat().st_size, "memory_bytes": collider.nbytes(),
                 "accuracy": accuracy(collider, animation, args.times, args.points, args.seed)}
        if args.rounds:
            entry["query_1M"] = query_times(collider, static, animation, args.rounds, args.seed)
        report["models"].append(entry)
        print(json.dumps(entry, indent=1), flush=True)
    report["load_after"] = os.getloadavg()
    (args.out / "report.json").write_text(json.dumps(report, indent=1))
    print(f"load average before {report['load_before']}, after {report['load_after']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
