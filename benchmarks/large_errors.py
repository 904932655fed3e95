"""Where an articulated network (kind ``neural-skinned``) errs by more than ``--over-mm`` in a band
about the exact skinned surface: the map to the rest pose or the network?

At ``--poses`` random poses off the clips (``engine.skinning.random_poses``, the benchmark's seed
for such poses), ``--points`` points per pose in the +-``--band-mm`` band of the exact union of
the posed skin; each point answered as the query answers it by the network alone, without the
exact patches (the candidate rows carried through the skinning, the network per row, the minimum
over the usable rows). For each point that errs by
more than ``--over-mm``, the chosen row's rest point is looked up in the exact SDF of the rest
mesh (the "floor": what a perfect rest-pose field would answer there, no network):

- ``map``: the floor itself errs by more than ``--over-mm`` (no network could answer right
  through this row); of those, ``truth inside``: the exact union's distance is negative (a point
  inside the body, where the minimum of the parts is not the union's depth), ``side``: the floor's
  sign is not the truth's (the root lies on the other side of the rest surface: the blend folds
  there), ``metric``: the floor divided by the stretch of the map along the gradient (``d /
  |B^T grad d|``, the metric correction) lands within 2 mm of the truth;
- ``network``: the floor is right, the network at that rest point is not; ``another row``: one of
  the point's other usable rows answers within 2 mm of the truth (the minimum picked a wrong one);
- ``low`` / ``high``: the answer below the truth or above; ``the truth outside``: low where the
  point is outside the body (a contact deeper than it is, or where there is none: what throws cloth);
- the chosen rows' parts.

    python benchmarks/large_errors.py out/quiet2/models/walker-neural.safetensors --band-mm 10
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path
from typing import NamedTuple

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1] / "server"), str(Path(__file__).resolve().parents[1] / "client")]

from collider_contract.skeleton import SkeletonPose
from collider_server.engine.kinds.neural_skinned import union_of_parts
from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.engine.modelfile import load_collider
from collider_server.engine.skinning import random_poses, skin_vertices
from collider_server.making.sampling import surface_band_points
from collider_server.making.skinned import skinned_collider


class Answer(NamedTuple):
    """Points answered row by row as the query answers them: the rows (``point``, ``joint``,
    ``rest``, ``inverse``: the collider's ``parts_at``), each row's distance ``row_distance``, and
    per point the union ``distance`` and its row ``chosen``."""

    point: np.ndarray
    joint: np.ndarray
    rest: np.ndarray
    inverse: np.ndarray
    row_distance: np.ndarray
    distance: np.ndarray
    chosen: np.ndarray


def answer_by_rows(collider, x: np.ndarray, transforms: np.ndarray) -> Answer:
    """:class:`Answer` of ``collider`` at points ``x`` (n, 3) at joint transforms (J, 4, 4): the
    query's own rows (its candidate rule, map and surface offsets), so ``distance`` is the query's."""
    pose = SkeletonPose(joint_transforms=transforms)
    point, joint, rest, inverse = collider.parts_at(x, None, pose)
    d, _ = collider._part_values(rest, joint, collider.pose(None, pose).bias, False)
    best, chosen = union_of_parts(d, point, np.ones(len(point), bool), len(x))
    return Answer(point, joint, rest, inverse, d, best, chosen)


def causes(collider, poses: int, points: int, band: float, over: float, seed: int) -> tuple[Counter, Counter, int]:
    """(causes, the chosen rows' parts, points measured) of the points erring over ``over`` (m)."""
    skin = collider.skin
    exact = skinned_collider(skin, "exact", loop=collider.loop)
    rest_sdf = ExactSDF(Mesh(skin.vertices, skin.faces, "rest"))
    tally: Counter = Counter()
    parts: Counter = Counter()
    for p, transforms in enumerate(random_poses(skin, poses, seed).transforms):
        mesh = Mesh(skin_vertices(skin, transforms), skin.faces, "posed")
        x = surface_band_points(mesh, points, band, seed + 1000 + p)
        truth = exact.query(x, ("distance",), joint_transforms=transforms).distance
        point, joint, rest, inverse, d, best, best_row = answer_by_rows(collider, x, transforms)
        bad = np.flatnonzero(np.abs(best - truth) > over)
        floor, closest, face = rest_sdf.query(rest[best_row[bad]])
        stretch = np.einsum("mba,mb->ma", inverse[best_row[bad]], rest_sdf.gradient(
            rest[best_row[bad]], floor, closest, face))
        corrected = floor / np.maximum(np.linalg.norm(stretch, axis=1), 1e-9)
        for k, i in enumerate(bad):
            tally["points"] += 1
            tally["low" if best[i] < truth[i] else "high"] += 1
            tally["low: the truth outside"] += int(best[i] < truth[i] and truth[i] > 0)
            parts[skin.skeleton.names[joint[best_row[i]]]] += 1
            if abs(floor[k] - truth[i]) > over:
                tally["map"] += 1
                tally["map: truth inside"] += int(truth[i] < 0)
                tally["map: side"] += int(np.sign(floor[k]) != np.sign(truth[i]))
                tally["map: metric"] += int(abs(corrected[k] - truth[i]) < 2e-3)
            else:
                tally["network"] += 1
                others = np.flatnonzero(point == i)
                tally["network: another row"] += int(any(abs(d[r] - truth[i]) < 2e-3 for r in others
                                                         if r != best_row[i]))
    return tally, parts, poses * points


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", type=Path, nargs="+", help="neural-skinned model files")
    parser.add_argument("--poses", type=int, default=12)
    parser.add_argument("--points", type=int, default=10_000, help="points per pose")
    parser.add_argument("--band-mm", type=float, default=10.0)
    parser.add_argument("--over-mm", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=2031)
    args = parser.parse_args()
    for path in args.models:
        collider = load_collider(path)
        collider.patches = None  # the network alone: the exact patches answer most points near the skin exactly
        tally, parts, total = causes(collider, args.poses, args.points, args.band_mm * 1e-3, args.over_mm * 1e-3,
                                     args.seed)
        print(f"{path}: {tally['points']} of {total:,} points in the +-{args.band_mm:g} mm band err over "
              f"{args.over_mm:g} mm ({args.poses} poses off the clips)")
        for key in ("map", "map: truth inside", "map: side", "map: metric", "network", "network: another row",
                    "low", "low: the truth outside", "high"):
            print(f"  {key}: {tally[key]}")
        print("  chosen parts: " + ", ".join(f"{name} {count}" for name, count in parts.most_common()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
