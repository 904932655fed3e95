"""The keyframes preset's warm start (issue 34), measured: keyframe tables trained from scratch
against tables started from a static grid of the first frame, for several shares of the run,
interleaved step by step in one process on one animation (its units: metres), with the training
loop's own parts (``train_step``: its loss and Adam; ``keyframe_weights``: the copy; the cosine
learning rate over the steps; the static phase's samples: the first frame's, over every frame's
box) and 2 kernel threads.

Per variant, every ``--every`` steps: the mean and median error (mm) in the +-1 mm band at 16
random times (the exact interpolated mesh; a static grid answers every time alike) and the
variant's own seconds of training (validation not counted), so that the errors compare by steps
and by seconds; at the end the median milliseconds of a step in each phase and the load average.
Figures in docs/neural.md ("Why the keyframe tables learn slower").

    python benchmarks/warm_start.py examples/animations/arm.obj examples/animations/arm.pc2 24 \\
        --steps 400 --every 50 --shares 0,0.1,0.25,0.5
"""
import argparse
import os
import time

import numpy as np
import torch

from collider_server.engine.kinds.neural import ANIMATED_PRESETS, build_network
from collider_server.engine.kinds.neural_keyframes import keyframe_segments, keyframe_weights
from collider_server.engine.meshes import ExactSDF
from collider_server.making.animation_files import load_animation
from collider_server.making.bake import padded_box
from collider_server.making.training import TrainConfig
from collider_server.making.training.data import (
    animated_validation_sets,
    make_animated_training_data,
    make_training_data,
    normalisation,
)
from collider_server.making.training.loop import Batches, train_step
from collider_server.making.training.schedule import (
    cosine_learning_rate,
    make_optimizer,
    set_training_threads,
)

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("mesh")
parser.add_argument("cache")
parser.add_argument("fps", type=float)
parser.add_argument("--loop", action="store_true", help="the animation loops (default: it clamps)")
parser.add_argument("--steps", type=int, default=400)
parser.add_argument("--every", type=int, default=50)
parser.add_argument("--samples", type=int, default=200_000)
parser.add_argument("--batch-size", type=int, default=8192)
parser.add_argument("--threads", type=int, default=2)
parser.add_argument("--shares", default="0,0.25", help="warm-start shares of the steps (0: none)")
args = parser.parse_args()

animation = load_animation(args.mesh, args.cache, args.fps, loop=args.loop)
arch = ANIMATED_PRESETS["keyframes"]
set_training_threads(arch, args.threads)
config = TrainConfig(preset="keyframes", samples=args.samples, batch_size=args.batch_size)
first_lr, last_lr = config.resolved_learning_rates()
normal_weight = config.resolved_normal_weight()
centre, radius = normalisation(animation, config.padding)
duration = animation.timeline.duration_s


def segments(times):
    key, frac = keyframe_segments(times, duration, arch.keyframes)
    return torch.from_numpy(key), torch.from_numpy(frac)


moving = make_animated_training_data(animation, config, 1.0, False)
rest = animation.frame(0)
first = make_training_data(rest, ExactSDF(rest), config, 1.0, False, box=padded_box(animation, config.padding))
moving_batches, first_batches = Batches.of(moving, segments(moving.times), "cpu"), Batches.of(first, (), "cpu")
val_points, val_distance, val_times = animated_validation_sets(animation, 4000, 100, 1.0)["1mm"]
val_points, val_distance, val_inputs = torch.from_numpy(val_points), torch.from_numpy(val_distance), segments(val_times)
print(f"{animation.name}: {len(animation.frames)} frames, {duration:g} s; {args.samples:,} samples, batch "
      f"{args.batch_size}, {args.threads} threads; load average {os.getloadavg()[0]:.2f} (data made)", flush=True)

runs = {}
for share in (float(s) for s in args.shares.split(",")):
    torch.manual_seed(0)
    network = build_network(arch, centre, radius)
    run = {"share": share, "network": network, "optimizer": make_optimizer(network, first_lr, fused=True),
           "batches": moving_batches, "trained": network, "warming": share > 0, "seconds": 0.0,
           "times": {"first frame": [], "keyframes": []}, "generator": torch.Generator().manual_seed(0)}
    if share > 0:
        torch.manual_seed(0)
        static = build_network(arch.spatial(), centre, radius)
        run.update(trained=static, static_optimizer=make_optimizer(static, first_lr), batches=first_batches)
    runs["keyframes" if share == 0 else f"warm {share:g}"] = run

for step in range(args.steps):
    fraction = step / args.steps  # the loop's RunClock.fraction with a step count
    lr = cosine_learning_rate(fraction, first_lr, last_lr)
    for run in runs.values():
        began = time.perf_counter()
        if run["warming"] and fraction >= run["share"]:
            run["network"].load_state_dict(keyframe_weights(run["trained"].state_dict(), arch.keyframes))
            run.update(trained=run["network"], batches=moving_batches, warming=False)
        optimizer = run["static_optimizer"] if run["warming"] else run["optimizer"]
        for group in optimizer.param_groups:
            group["lr"] = lr
        index = torch.randint(0, len(run["batches"].points), (args.batch_size,), generator=run["generator"])
        train_step(run["trained"], optimizer, run["batches"], index, radius, normal_weight)
        spent = time.perf_counter() - began
        run["seconds"] += spent
        run["times"]["first frame" if run["warming"] else "keyframes"].append(spent)
    if (step + 1) % args.every == 0 or step + 1 == args.steps:
        shown = []
        for variant, run in runs.items():
            with torch.no_grad():
                got = run["trained"](val_points) if run["warming"] else run["trained"](val_points, *val_inputs)
            error = (got - val_distance).abs().numpy() * 1000
            shown.append(f"{variant} {error.mean():.4f} / {np.median(error):.4f} mm at {run['seconds']:.0f} s")
        print(f"step {step + 1}: " + "  ".join(shown) + f"  (mean / median; load {os.getloadavg()[0]:.1f})",
              flush=True)

for variant, run in runs.items():
    phases = ", ".join(f"{name} {np.median(t) * 1000:.0f} ms ({len(t)} steps)" for name, t in run["times"].items() if t)
    print(f"{variant}: median step {phases}; {args.steps / run['seconds']:.2f} steps/s over the run", flush=True)
print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")
