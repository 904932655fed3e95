"""The articulated neural collider (kind ``neural-skinned``) of the generated walking figure against
the exact skinned kind, at poses it was not trained on, and its query time against the static grid
network's.

Accuracy: at ``--clip-times`` random times of the walker's clips and ``--poses`` random poses off
the clips (``collider_server.engine.skinning.random_poses``: a random clip time, then every joint's
local rotation turned by up to 15 degrees about a random axis; seeds apart from training's),
``--points`` points per pose in the +-1 mm band (``--band-mm``) of the exact skinned surface at
that pose (surface samples offset along the face normal): mean / p99 / max distance error and how
many points err over 5 mm (a wider band shows the errors off the skin, where cloth meets it),
sign errors (all, and where the exact |d| > 0.2 mm), normal error mean / p99 (degrees). Also the
model file's size and its training (steps, seconds).

Speed: 1M points in the +-10 mm band, per round each candidate once in turn (interleaved, the
load falls on both alike): the articulated network's distance + normal + contact + velocity at a
new pose each round (joint transforms and velocities: no pose cache; also a cloth's 3,321 points
at another new pose), and the static ``grid``
preset's network of the rest mesh (same preset and size, untrained weights: the fused kernel's
time does not depend on the values) for distance + normal + contact; the median and range.

    python benchmarks/articulated_neural.py --model models/walker-neural.safetensors
    python benchmarks/articulated_neural.py --train-minutes 10   # trains one first (not saved)
    python benchmarks/articulated_neural.py --model models/walker-neural.safetensors --no-accuracy  # time only

``--ways`` (default all three, interleaved): ``cells``, every query as the collider answers one of
``NEAR_POINTS`` (65,536) or more points, the 1M queries' way (the points in the clean cells of the
posed skin by the skin itself, the others through the network, ``engine/kinds/patches.py``);
``patches``, every query as the collider answers a smaller one (through the network, its rows
near the skin by the exact patches about its closest points; ``collider.near_points = None``);
``network``, the network alone (``collider.patches = None``).

``--candidate-rules own-label retry-labels`` measures the model through each candidate rule (the
architecture's ``candidate_rule``; the network is the same, only the parts a point is answered
by differ), interleaved, the mean candidates per point beside, each read from the model file;
without it, the model's own rule.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1] / "server"), str(Path(__file__).resolve().parents[1] / "client")]

from collider_contract.skeleton import SkeletonPose
from collider_server.engine.collider import ColliderInfo
from collider_server.engine.kinds.neural import PRESETS, NeuralCollider, architecture_dict, build_network
from collider_server.engine.kinds.neural_skinned import CANDIDATE_RULES
from collider_server.engine.meshes import Mesh
from collider_server.engine.modelfile import load_collider, save_collider
from collider_server.engine.skinning import PERTURB_DEG, pose_at, random_poses, skin_vertices
from collider_server.making.sampling import surface_band_points
from collider_server.making.skinned import skinned_collider
from collider_server.making.training import TrainConfig
from collider_server.making.training.articulated import train_articulated
from collider_server.making.training.data import normalisation
from collider_server.making.walker import make_walker

#: The ways ``--ways`` measures the model: as the collider answers a large query, a small one, or
#: by its network alone.
WAYS = {"cells": "pose's cells", "patches": "network and patches", "network": "network alone"}
#: A cloth's query beside the 1M one (the shipped cape's 3,321 vertices), in the +-2 cm band: what
#: a pose's cost is against a small query.
SMALL_POINTS = 3_321


def accuracy(collider, exact, skin, poses, points_per_pose: int, seed: int, band: float = 1e-3) -> dict:
    """Errors of ``collider`` against ``exact`` in the +-``band`` (m) band at each of ``poses``."""
    errors, truths, answers, angles, candidates = [], [], [], [], []
    for p, transforms in enumerate(poses):
        mesh = Mesh(skin_vertices(skin, transforms), skin.faces, "posed")
        points = surface_band_points(mesh, points_per_pose, band, seed + p)
        truth = exact.query(points, ("distance", "normal"), joint_transforms=transforms)
        answer = collider.query(points, ("distance", "normal"), joint_transforms=transforms)
        rows = collider.parts_at(points, None, SkeletonPose(joint_transforms=transforms))[0]
        candidates.append(len(rows) / len(points))
        errors.append(np.abs(answer.distance - truth.distance))
        truths.append(truth.distance)
        answers.append(answer.distance)
        cos = np.clip(np.einsum("ij,ij->i", answer.normal, truth.normal), -1.0, 1.0)
        angles.append(np.degrees(np.arccos(cos)))
    error, truth, answer, angle = (np.concatenate(a) for a in (errors, truths, answers, angles))
    wrong = np.sign(answer) != np.sign(truth)
    clear = np.abs(truth) > 2e-4
    return {"poses": len(poses), "points": len(error), "mean_mm": error.mean() * 1e3,
            "p99_mm": np.percentile(error, 99) * 1e3, "max_mm": error.max() * 1e3,
            "over_5mm": int((error > 5e-3).sum()),
            "sign_errors_pct": wrong.mean() * 100, "sign_errors_beyond_0.2mm_pct": wrong[clear].mean() * 100,
            "normal_mean_deg": angle.mean(), "normal_p99_deg": np.percentile(angle, 99),
            "candidates": float(np.mean(candidates))}


def timing(colliders: dict, skin, rounds: int, seed: int, threads: int) -> dict:
    """Median (min - max) seconds per 1M points: each of ``colliders`` (name -> articulated
    collider) d+n+c+v at a new pose each round, and on :data:`SMALL_POINTS` points at another new
    pose, the static grid network of the rest mesh d+n+c, interleaved."""
    import torch

    torch.set_num_threads(threads)
    rest = Mesh(skin.vertices, skin.faces, "rest")
    centre, radius = normalisation(rest, 0.1)
    arch = PRESETS["grid"]
    lo, hi = centre - radius, centre + radius
    info = ColliderInfo(name="static", kind="neural", domain_min=lo.tolist(), domain_max=hi.tolist(),
                        settings={"architecture": architecture_dict(arch)})
    static = NeuralCollider(info, build_network(arch, centre, radius), device="cpu")
    static_points = surface_band_points(rest, 1_000_000, 1e-2, seed)
    poses = random_poses(skin, rounds, seed + 1, perturbed_share=0.5).transforms
    small_poses = random_poses(skin, rounds, seed + 2, perturbed_share=0.5).transforms
    _, velocities = pose_at(skin, skin.clips[0].name, 0.3)
    fields = ("distance", "normal", "contact", "velocity")
    times: dict = {f"articulated {name} d+n+c+v (new pose)": [] for name in colliders}
    times.update({f"articulated {name} d+n+c+v, {SMALL_POINTS:,} points (new pose)": [] for name in colliders})
    times["static grid d+n+c"] = []
    for r in range(rounds):
        mesh = Mesh(skin_vertices(skin, poses[r]), skin.faces, "posed")
        points = surface_band_points(mesh, 1_000_000, 1e-2, seed + 10 + r)
        small = surface_band_points(Mesh(skin_vertices(skin, small_poses[r]), skin.faces, "posed"), SMALL_POINTS,
                                    2e-2, seed + 20 + r)
        for name, collider in colliders.items():
            started = time.perf_counter()
            collider.query(points, fields, joint_transforms=poses[r], joint_velocities=velocities)
            times[f"articulated {name} d+n+c+v (new pose)"].append(time.perf_counter() - started)
            started = time.perf_counter()
            collider.query(small, fields, joint_transforms=small_poses[r], joint_velocities=velocities)
            times[f"articulated {name} d+n+c+v, {SMALL_POINTS:,} points (new pose)"].append(
                time.perf_counter() - started)
        started = time.perf_counter()
        static.query(static_points, ("distance", "normal", "contact"))
        times["static grid d+n+c"].append(time.perf_counter() - started)
    return {k: (float(np.median(v)), float(min(v)), float(max(v))) for k, v in times.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, help="a trained neural-skinned model of the walker")
    parser.add_argument("--train-minutes", type=float, default=None, help="train one first (no --model)")
    parser.add_argument("--save", type=Path, default=None, help="where a model trained here is saved")
    parser.add_argument("--clip-times", type=int, default=16)
    parser.add_argument("--poses", type=int, default=100)
    parser.add_argument("--points", type=int, default=2000, help="points per pose")
    parser.add_argument("--band-mm", type=float, default=1.0,
                        help="the accuracy's band about the exact surface (mm; the issue's: 1)")
    parser.add_argument("--rounds", type=int, default=5, help="timing rounds (0: no timing)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--candidate-rules", nargs="+", choices=CANDIDATE_RULES, default=None,
                        help="measure the model through each of these candidate rules (default: its own)")
    parser.add_argument("--no-accuracy", action="store_true", help="time the query only (no accuracy part)")
    parser.add_argument("--ways", nargs="+", choices=WAYS, default=list(WAYS),
                        help="as the collider answers a large query (the pose's cells first), a small one (the "
                             "network and its patches), or by the network alone (default: all three, interleaved)")
    args = parser.parse_args()
    if (args.model is None) == (args.train_minutes is None):
        parser.error("give --model or --train-minutes")
    print(f"load average at start: {os.getloadavg()[0]:.1f}")
    if args.model is not None:
        path = args.model
        collider = load_collider(path)
        size = path.stat().st_size
        skin = collider.skin  # the walker as the model holds it (e.g. placed Z up by `collider train`)
    else:
        skin = make_walker().skin()
        config = TrainConfig(max_minutes=args.train_minutes, threads=args.threads, batch_size=4096)
        result = train_articulated(skin, "walker-neural", config, loop=True)
        collider = result.collider
        path = save_collider(collider, args.save or Path("/tmp/walker-neural.safetensors"))
        size = path.stat().st_size
        print(result.summary())
    exact = None if args.no_accuracy else skinned_collider(skin, "walker", loop=True)
    training = collider.info.settings.get("training", {})
    print(f"model: {size / 1e6:.2f} MB; trained {training.get('steps_done')} steps in "
          f"{training.get('seconds')} s; best validation {training.get('best_validation_1mm_mm')} mm")
    import torch

    torch.set_num_threads(args.threads)
    colliders = {}
    rules = args.candidate_rules or [collider.arch.candidate_rule]
    for rule in rules:
        for way in args.ways:
            # One collider each, from the file (a trained one's table rounds to 8 bits there).
            copy = load_collider(path) if len(rules) * len(args.ways) > 1 else collider
            copy.arch = dataclasses.replace(copy.arch, candidate_rule=rule)  # the same network, other candidates
            copy.near_points = 0 if way == "cells" else None
            if way == "network":
                copy.patches = None
            colliders[f"{rule}, {WAYS[way]}"] = copy
    clip_poses = random_poses(skin, args.clip_times, args.seed, perturbed_share=0.0).transforms
    off_poses = random_poses(skin, args.poses, args.seed + 5).transforms
    for rule, each in ({} if args.no_accuracy else colliders).items():
        # The one rule of random poses (engine.skinning.random_poses), as collider eval draws them.
        band = args.band_mm * 1e-3
        figures = {"clip times": accuracy(each, exact, skin, clip_poses, args.points, args.seed, band),
                   f"poses off the clips ({PERTURB_DEG:g} deg)": accuracy(each, exact, skin, off_poses, args.points,
                                                                          args.seed + 1000, band)}
        for name, f in figures.items():
            print(f"[{rule}] {name}: {f['poses']} poses, {f['points']:,} points in the +-{args.band_mm:g} mm band: "
                  f"mean {f['mean_mm']:.4f} / p99 {f['p99_mm']:.3f} / max {f['max_mm']:.2f} mm "
                  f"({f['over_5mm']} over 5 mm), sign errors "
                  f"{f['sign_errors_pct']:.3f} % ({f['sign_errors_beyond_0.2mm_pct']:.3f} % beyond 0.2 mm), normals "
                  f"{f['normal_mean_deg']:.2f} / {f['normal_p99_deg']:.1f} deg, {f['candidates']:.3f} candidates "
                  f"per point")
    speed = timing(colliders, skin, args.rounds, args.seed + 7, args.threads) if args.rounds else {}
    for name, (median, low, high) in speed.items():
        unit = ("ms", 1e3) if "points (new pose)" in name else ("s per 1M points", 1.0)
        print(f"{name}: {median * unit[1]:.3f} {unit[0]} ({low * unit[1]:.3f}-{high * unit[1]:.3f}, "
              f"{args.rounds} rounds)")
    for rule in colliders if speed else ():
        ratio = speed[f"articulated {rule} d+n+c+v (new pose)"][0] / speed["static grid d+n+c"][0]
        print(f"articulated {rule} / static: {ratio:.2f}x")
    print(f"load average at end: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
