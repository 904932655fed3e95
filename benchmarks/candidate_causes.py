"""What the worst points of kind ``neural-skinned`` are: which part a bad point's truth belongs to,
which candidates it had, whether their Newton steps reached a root, and what other candidate rules
would have answered, through the exact rest SDF ("floor", no network) and through a trained
model's network (docs/neural.md, "The worst points").

At ``--clip-times`` random clip times and ``--poses`` random poses off the clips
(``engine.skinning.random_poses``), ``--points`` points each in the +-1 mm band of the posed mesh:
every point is carried to the rest pose from **every** joint's rigid image (the model's map: its
weight field, solver and steps), so that a candidate rule is scored afterwards by choosing rows.
Rows are kept as :func:`carry_to_rest` keeps them (converged ones; all where none converged).
The truth's part: the dominant joint of the posed vertex nearest the exact union's closest point.

Printed per source (floor, network) and pose set (clip times, off the clips): mean / p99 / max and
sign errors (all, beyond 0.2 mm) of the rules ``own-label`` (the model's label rule), ``+truth's
part`` (an oracle), ``all parts``, and ``retry-labels`` (:func:`parts_through_skinning`'s second
pass, from the same rows); then the own-label rule's bad points (the max, the worst 1 %, the sign
errors beyond 0.2 mm) by cause: (a) no candidate reached a root, another joint's start did; (b)
no joint's start did; (c) a candidate did; with the share of their error, and how many lack the
truth's part.

    python benchmarks/candidate_causes.py --model out/quiet/models/walker-neural.safetensors
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1] / "server"), str(Path(__file__).resolve().parents[1] / "client")]

from collider_contract import SkeletonPose
from collider_server.engine.kinds import neural_skinned as ns
from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.engine.modelfile import load_collider
from collider_server.engine.skinning import random_poses
from collider_server.making.sampling import surface_band_points
from collider_server.making.skinned import skinned_collider


def every_part(collider, rest_sdf, transforms, points):
    """Per joint j and point p (J, n): the floor's and the network's value at j's root, whether
    j's steps converged, and the own-label and retry candidate masks."""
    skin = collider.skin
    joints = skin.skeleton.joint_count
    n = len(points)
    to_rest, posed = ns.rest_maps(skin.skeleton, transforms)
    joint = np.repeat(np.arange(joints), n)
    point = np.tile(np.arange(n), joints)
    rigid = np.einsum("mab,mb->ma", to_rest[joint, :, :3], points[point]) + to_rest[joint, :, 3]
    arch = collider.arch
    # Every row carried (the dropped ones too) and whether it reached a root.
    prepared = collider.pose(None, SkeletonPose(joint_transforms=transforms))
    carried = ns.carried_rows(points, point, joint, rigid, to_rest, posed, collider.weights, collider.centre,
                              collider.radius, arch.skinning_iterations, arch.skinning_solver,
                              offsets=prepared.offsets)
    rest, converged = carried.rest, carried.converged
    floor = rest_sdf.query(rest)[0].reshape(joints, n)
    bias = prepared.bias
    network = collider._part_values(rest, joint, bias, False)[0].reshape(joints, n)
    own = ns._candidate_mask_numpy(points, to_rest, collider.labels, collider.centre, collider.radius,
                                   collider.allowed, collider.part_boxes)
    seen = ns.labels_seen(points, to_rest, collider.labels, collider.centre, collider.radius)
    return floor, network, converged.reshape(joints, n), own, seen


def answer(mask, converged, values):
    """The minimum over a point's kept rows of ``mask``; whether the point had a converged row."""
    has = (mask & converged).any(axis=0)
    kept = mask & (converged | ~has[None])
    return np.where(kept, values, np.inf).min(axis=0), has


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, required=True, help="a trained neural-skinned model")
    parser.add_argument("--clip-times", type=int, default=4)
    parser.add_argument("--poses", type=int, default=8)
    parser.add_argument("--points", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    collider = load_collider(args.model)
    skin = collider.skin
    exact = skinned_collider(skin, "truth", loop=True)
    rest_sdf = ExactSDF(Mesh(skin.vertices, skin.faces, "rest"))
    owner = skin.joints[np.arange(len(skin.joints)), np.argmax(skin.weights, axis=1)]
    poses = [("clip", t) for t in random_poses(skin, args.clip_times, args.seed, perturbed_share=0.0).transforms]
    poses += [("off", t) for t in random_poses(skin, args.poses, args.seed + 5, perturbed_share=1.0).transforms]
    rows: dict = {}
    for p, (kind, transforms) in enumerate(poses):
        posed = exact.posed(None, SkeletonPose(joint_transforms=transforms)).exact
        points = surface_band_points(posed.mesh, args.points, 1e-3, args.seed + 974 + p)
        truth, closest, face = posed.query(points)
        corners = skin.faces[face]
        nearest = np.linalg.norm(posed.mesh.vertices[corners] - closest[:, None], axis=2).argmin(axis=1)
        part = owner[corners[np.arange(len(points)), nearest]]
        floor, network, converged, own, seen = every_part(collider, rest_sdf, transforms, points)
        columns = np.arange(len(points))
        oracle = own.copy()
        oracle[part, columns] = True
        for source, values in (("floor", floor), ("network", network)):
            first, has = answer(own, converged, values)
            retry = own.copy()
            retry[:, ~has] |= seen[:, ~has]
            second, _ = answer(retry, converged, values)
            retried = np.where(has, first, np.where((retry & converged).any(axis=0), second, first))
            kept = own & (converged | ~has[None])
            cause = np.where(has, 2, np.where(converged.any(axis=0), 0, 1))
            for rule, d in (("own-label", first), ("+truth's part", answer(oracle, converged, values)[0]),
                            ("all parts", answer(np.ones_like(own), converged, values)[0]),
                            ("retry-labels", retried)):
                rows.setdefault((source, kind, rule), []).append(
                    (np.abs(d - truth), np.sign(d) != np.sign(truth), np.abs(truth) > 2e-4, cause,
                     ~kept[part, columns]))
        print(f"pose {p + 1}/{len(poses)} ({kind}) done, load {os.getloadavg()[0]:.2f}", flush=True)
    names = ("a: no candidate reached a root, another start did", "b: no start did", "c: a candidate did")
    for (source, kind, rule), parts in rows.items():
        error, wrong, clear, cause, missing = (np.concatenate([x[i] for x in parts]) for i in range(5))
        error = error * 1e3
        print(f"{source:7s} {kind:4s} {rule:14s} mean {error.mean():.4f} / p99 {np.percentile(error, 99):.3f} / max "
              f"{error.max():.2f} mm, sign errors {wrong.mean() * 100:.2f} % ({wrong[clear].mean() * 100:.2f} % "
              f"beyond 0.2 mm)")
        if rule != "own-label":
            continue
        for what, bad in (("the max", error == error.max()), ("worst 1 %", error >= np.percentile(error, 99)),
                          ("sign errors beyond 0.2 mm", wrong & clear)):
            shares = "; ".join(f"{name} {(bad & (cause == k)).sum()} ({error[bad & (cause == k)].sum() / error[bad].sum() * 100:.0f} % of the error)"
                               for k, name in enumerate(names))
            print(f"    {what} ({bad.sum()}): {shares}; the truth's part not kept at {(bad & missing).sum()}")
    print(f"load average at end: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
