"""The exact skinned kind's cost per query against the static exact `mesh` kind of its rest mesh,
on the generated skinned arm (collider_server.making.skinned.skinned_arm: a capsule of 2,530
vertices and 5,056 faces, 3 joints; metres, collider frame, seconds).

Per round, interleaved: a 1M-point distance + normal + contact query

- at a **new pose** (clip "wave" at a time not asked before: the skin is posed and its tree built
  inside the timed call),
- at a **repeated pose** (the same time again: the cached tree answers),
- of the static `mesh` collider of the rest mesh (the same points; the target's baseline),
- of a static `mesh` collider of the mesh posed as in this round (built untimed): the same
  triangles as the skinned query's, so its ratio is the skinned kind's own overhead, while the
  ratio to the rest mesh also holds how much dearer libigl finds the posed shape for these points.

Prints each round's times and the ratios' median and range. The points are uniform in the
skinned model's domain box (the rest pose and every clip's poses, padded by 10 %).

    python benchmarks/skinned_query.py [--points 1000000] [--rounds 5]
"""
import argparse
import os
import time

import numpy as np

from collider_server.engine.meshes import Mesh
from collider_server.engine.skinning import pose_at, skin_vertices
from collider_server.making.bake import bake_collider
from collider_server.making.skinned import skinned_arm, skinned_collider

FIELDS = ["distance", "normal", "contact"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}")
    skin = skinned_arm()
    skinned = skinned_collider(skin, "arm")
    static = bake_collider(Mesh(skin.vertices, skin.faces, "rest"), "mesh", "rest")
    rng = np.random.default_rng(0)
    points = rng.uniform(skinned.domain_min, skinned.domain_max, (args.points, 3))
    static.query(points[:1000], FIELDS)  # first-use work (winding hierarchy) out of the timing
    skinned.query(points[:1000], FIELDS, time=0.0)
    new, repeated, still, same = [], [], [], []
    for r in range(args.rounds):
        t = 0.113 + 0.071 * r  # never asked before
        posed = bake_collider(Mesh(skin_vertices(skin, pose_at(skin, "wave", t)[0]), skin.faces,
                                   "posed"), "mesh", "posed")
        posed.query(points[:1000], FIELDS)
        started = time.perf_counter()
        skinned.query(points, FIELDS, time=t)
        new.append(time.perf_counter() - started)
        started = time.perf_counter()
        skinned.query(points, FIELDS, time=t)
        repeated.append(time.perf_counter() - started)
        started = time.perf_counter()
        static.query(points, FIELDS)
        still.append(time.perf_counter() - started)
        started = time.perf_counter()
        posed.query(points, FIELDS)
        same.append(time.perf_counter() - started)
        print(f"round {r}: new pose {new[-1]:.3f} s, repeated pose {repeated[-1]:.3f} s, "
              f"static rest mesh {still[-1]:.3f} s, static posed mesh {same[-1]:.3f} s", flush=True)
    for label, times in (("new pose", new), ("repeated pose", repeated)):
        for baseline, base in (("static rest mesh", still), ("static posed mesh", same)):
            ratio = np.array(times) / np.array(base)
            print(f"{args.points:,} points d+n+c, {label}: {np.median(times):.3f} s vs {baseline} "
                  f"{np.median(base):.3f} s, ratio median {np.median(ratio):.2f}x (range "
                  f"{ratio.min():.2f}-{ratio.max():.2f}), {args.rounds} interleaved rounds")
    print(f"trees built: {skinned.builds}, {skinned.build_s / max(skinned.builds, 1) * 1e3:.1f} ms "
          f"each (skinning included)")
    print(f"load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
