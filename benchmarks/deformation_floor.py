"""The error floor of preset ``deformed`` (a rest pose carried by deformation fields), which no
training removes: the *exact* SDF of the rest pose (the first frame) read through the fitted
fields, with the network's own rules (:func:`fit_deformation`, the trilinear warp, the stretch
correction), against the exact SDF of the mesh interpolated at t. What is left is the fields'
share of the error: how well a smooth field follows the motion. The same times and +-1 mm band
points as ``collider bench --animation`` (seed 0, 8 random times, 5,000 points per time); metres,
seconds, degrees.

    python benchmarks/deformation_floor.py out/animations/twisting-bunny.obj out/animations/twisting-bunny.pc2 30
    python benchmarks/deformation_floor.py examples/animations/arm.obj examples/animations/arm.pc2 24 \\
        --resolutions 16 32
    python benchmarks/deformation_floor.py out/animations/spot-bend.obj out/animations/spot-bend.pc2 12 --clamp \\
        --resolutions 16 24 32 --fraction 0
"""
import argparse
import os
import time

import numpy as np

from collider_server.engine.kinds.neural_deformed import trilinear
from collider_server.engine.meshes import ExactSDF
from collider_server.making.animation_files import load_animation
from collider_server.making.evaluation import SIGN_THRESHOLD_M
from collider_server.making.sampling import animated_band_sets, random_times
from collider_server.making.training import TrainConfig, fit_deformation
from collider_server.making.training.data import normalisation

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("mesh")
parser.add_argument("cache")
parser.add_argument("fps", type=float)
parser.add_argument("--resolutions", type=int, nargs="+", default=[16], help="cells per side of the fields")
parser.add_argument("--times", type=int, default=8)
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--fraction", type=float, default=None,
                    help="each random time moved to this fraction of its frame segment (0: at the frames, "
                         "where the fields were fitted; 0.5: midway, where their blend in time errs most)")
parser.add_argument("--clamp", action="store_true", help="the animation clamps (default: it loops)")
args = parser.parse_args()

print(f"load average {os.getloadavg()[0]:.2f}")
animation = load_animation(args.mesh, args.cache, args.fps, loop=not args.clamp)
centre, radius = normalisation(animation, TrainConfig().padding)
times = random_times(animation.timeline, args.times, args.seed)
if args.fraction is not None:
    times = (np.floor(times * args.fps) + args.fraction) / args.fps
sets = animated_band_sets(animation, times, 40_000 // args.times, args.seed, 1.0)
truth = []
for t, bands in sets:
    exact = ExactSDF(animation.mesh_at(t))
    points = bands["band_1mm"]
    d, closest, face = exact.query(points)
    truth.append((t, points, d, exact.gradient(points, d, closest, face)))
rest = ExactSDF(animation.frame(0))
for resolution in args.resolutions:
    started = time.perf_counter()
    fit = fit_deformation(animation, centre, radius, resolution, show_progress=False)
    seconds = time.perf_counter() - started
    errors, angles, signs = [], [], []
    for t, points, d, g in truth:
        k, s, _ = animation.timeline.locate(t)
        field = fit.fields[k] + s * (fit.fields[k + 1] - fit.fields[k])
        u = (points - centre) / radius
        nodes, weight, dweight = trilinear(u, resolution)
        values = field[nodes].astype(np.float64)
        rest_points = centre + radius * (u + (weight[..., None] * values).sum(axis=1))
        jacobian = np.eye(3) + np.einsum("ncd,nce->nde", values, dweight)
        d0, closest0, face0 = rest.query(rest_points)
        n0 = rest.gradient(rest_points, d0, closest0, face0)
        composed = np.einsum("nca,nc->na", jacobian, n0)
        stretch = np.linalg.norm(composed, axis=1)
        errors.append(np.abs(d0 / stretch - d))
        signs.append(((d0 < 0) != (d < 0))[np.abs(d) > SIGN_THRESHOLD_M])
        cosine = np.einsum("na,na->n", composed / stretch[:, None], g)
        angles.append(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
    e, a = np.concatenate(errors) * 1000, np.concatenate(angles)
    memory = animation.timeline.frames * (resolution + 1) ** 3 * 3 * 4
    print(f"{resolution}^3 fields x {animation.timeline.frames} frames ({memory / 1e6:.1f} MB, fitted in "
          f"{seconds:.0f} s; fit residual p99 {fit.residual_p99.max() * 1000:.4f} mm, max "
          f"{fit.residual_max.max() * 1000:.3f} mm): distance mean {e.mean():.4f} / p99 "
          f"{np.percentile(e, 99):.4f} / max {e.max():.3f} mm, sign errors beyond {SIGN_THRESHOLD_M * 1000:g} mm "
          f"{100 * np.concatenate(signs).mean():.3f} %, normals {a.mean():.2f} / {np.percentile(a, 99):.1f} deg")
print(f"load average {os.getloadavg()[0]:.2f}")
