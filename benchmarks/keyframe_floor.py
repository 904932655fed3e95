"""The error floor of keyframe grids, which no resolution removes: the exact SDFs of the two
keyframes around a time t blended linearly (what a voxel keyframe set does, without its grid)
against the exact SDF of the mesh interpolated at t. The same times and +-1 mm band points as
``collider bench --animation`` (seed 0, 8 random times, 5,000 points per time); metres, seconds.

    python benchmarks/keyframe_floor.py examples/animations/arm.obj examples/animations/arm.pc2 24
    python benchmarks/keyframe_floor.py out/animations/twisting-bunny.obj out/animations/twisting-bunny.pc2 12
"""
import argparse
import os

import numpy as np

from collider_server.engine.meshes import ExactSDF
from collider_server.making.animation_files import load_animation
from collider_server.making.bake import keyframe_positions
from collider_server.making.sampling import animated_band_sets, random_times

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("mesh")
parser.add_argument("cache")
parser.add_argument("fps", type=float)
parser.add_argument("--keyframes", default="5,13,all", help="keyframe counts ('all': one per frame)")
parser.add_argument("--times", type=int, default=8)
parser.add_argument("--seed", type=int, default=0)
args = parser.parse_args()

print(f"load average {os.getloadavg()[0]:.2f}")
animation = load_animation(args.mesh, args.cache, args.fps, loop=True)
frames = animation.timeline.frames
times = random_times(animation.timeline, args.times, args.seed)
sets = animated_band_sets(animation, times, 40_000 // args.times, args.seed, 1.0)
for count in (frames if k == "all" else int(k) for k in args.keyframes.split(",")):
    positions = keyframe_positions(frames, count)
    errors = []
    for t, bands in sets:
        points = bands["band_1mm"]
        at = t * args.fps  # in frames
        i = min(int(np.searchsorted(positions, at, side="right")) - 1, count - 2)
        u = (at - positions[i]) / (positions[i + 1] - positions[i])
        d0, d1 = (ExactSDF(animation.at_frame(float(p))).signed_distance(points) for p in positions[i:i + 2])
        truth = ExactSDF(animation.mesh_at(t)).signed_distance(points)
        errors.append(np.abs((1 - u) * d0 + u * d1 - truth) * 1000.0)
    e = np.concatenate(errors)
    print(f"{count:>3} keyframes: blended exact keyframe SDFs vs the exact SDF at t, +-1 mm band: "
          f"mean {e.mean():.3f} mm, p99 {np.percentile(e, 99):.2f} mm, max {e.max():.2f} mm "
          f"({len(e):,} points at {len(times)} times)")
