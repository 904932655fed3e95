"""Where a ``neural-skinned`` model of the walker errs: at its rest pose (the skeleton's bind
transforms, where the map to the rest pose is the identity) against the exact rest mesh, and at
posed points by the largest skinning weight at each point's rest point (blends against nearly
rigid skin), beside the map's floor there (the exact rest SDF read through the same map, no
network: :func:`~collider_server.engine.kinds.neural_skinned.parts_through_skinning`'s rows, the
minimum over a point's candidates).

``--poses`` random clip times and as many random poses off the clips (every joint turned by up to
15 degrees), ``--points`` points each in the +-1 mm band of the exact union at that pose.

    python benchmarks/articulated_error_parts.py --model models/walker-neural.safetensors
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1] / "server"), str(Path(__file__).resolve().parents[1] / "client")]

from collider_contract.skeleton import SkeletonPose
from collider_server.engine.kinds import neural_skinned as ns
from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.engine.modelfile import load_collider
from collider_server.engine.skinning import random_poses, skin_vertices
from collider_server.making.sampling import surface_band_points
from collider_server.making.skinned import skinned_collider

#: Bins of the largest skinning weight at a point's rest point.
WEIGHT_BINS = (0.0, 0.6, 0.9, 0.98, 0.999, 1.01)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, required=True, help="a neural-skinned model file")
    parser.add_argument("--poses", type=int, default=4, help="clip times, and as many poses off the clips")
    parser.add_argument("--points", type=int, default=5000, help="points per pose in the +-1 mm band")
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    try:
        collider = load_collider(args.model)
    except (OSError, ValueError) as exc:
        parser.error(str(exc))
    if collider.kind != "neural-skinned":
        parser.error(f"{args.model} is a {collider.kind} model, not an articulated network (neural-skinned)")
    collider.patches = None  # the network's errors (the exact patches answer most points near the skin exactly)
    skin = collider.skin
    rest_mesh = Mesh(skin.vertices, skin.faces, "rest")
    rest_sdf = ExactSDF(rest_mesh)
    points = surface_band_points(rest_mesh, 4 * args.points, 1e-3, args.seed)
    truth = rest_sdf.signed_distance(points)
    bind = np.linalg.inv(skin.skeleton.inverse_bind)
    answer = collider.query(points, "distance", joint_transforms=bind).distance
    error = np.abs(answer - truth)
    print(f"rest pose: {len(points):,} points, mean {error.mean() * 1e3:.4f} / p99 {np.quantile(error, 0.99) * 1e3:.3f} / "
          f"max {error.max() * 1e3:.3f} mm, sign errors {np.mean(np.sign(answer) != np.sign(truth)) * 100:.2f} %")
    exact = skinned_collider(skin, "exact", loop=True)
    joints = skin.skeleton.joint_count
    for name, share, seed in (("clip times", 0.0, args.seed), ("off the clips", 1.0, args.seed + 5)):
        network, floor, largest = [], [], []
        for p, transforms in enumerate(random_poses(skin, args.poses, seed, perturbed_share=share).transforms):
            posed_points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"),
                                               args.points, 1e-3, seed + 10 + p)
            truth = exact.query(posed_points, "distance", joint_transforms=transforms).distance
            network.append(collider.query(posed_points, "distance", joint_transforms=transforms).distance - truth)
            point, _, rest, _ = collider.parts_at(posed_points, None, SkeletonPose(joint_transforms=transforms))
            d = rest_sdf.signed_distance(rest)
            least = np.full(len(posed_points), np.inf)
            np.minimum.at(least, point, d)
            floor.append(least - truth)
            # The largest weight at the rest point of each point's chosen (least) row.
            chosen = np.full(len(posed_points), -1)
            order = np.argsort(d)[::-1]
            chosen[point[order]] = order  # the last write, the least distance, wins
            largest.append(ns.weights_at(rest[chosen], collider.weights, collider.centre, collider.radius,
                                         joints).max(axis=1))
        e, f, w = (np.abs(np.concatenate(a)) for a in (network, floor, largest))
        print(f"{name}: {len(e):,} points, network mean {e.mean() * 1e3:.4f} mm, the map's floor {f.mean() * 1e3:.4f} mm")
        for lo, hi in itertools.pairwise(WEIGHT_BINS):
            inside = (w >= lo) & (w < hi)
            if inside.any():
                print(f"  largest weight [{lo:g}, {hi:g}): {inside.mean() * 100:5.1f} % of points; network mean "
                      f"{e[inside].mean() * 1e3:.4f} / p99 {np.quantile(e[inside], 0.99) * 1e3:.3f} mm; floor mean "
                      f"{f[inside].mean() * 1e3:.4f} / p99 {np.quantile(f[inside], 0.99) * 1e3:.3f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
