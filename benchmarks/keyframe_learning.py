"""Why the keyframe tables learn slower than the static network (issue 34): on the shipped bending
arm (examples/animations/arm.{obj,pc2}, 24 fps, metres), interleaved step by step in one process
(2 kernel threads, batch 8192, the loop's loss, Adam and cosine learning rate over the steps):

- ``static``: the keyframe preset's spatial grid (one table) trained on the arm's first frame;
- ``keyframes``: the keyframe preset (9 tables) as ``collider train`` trains it, every batch point
  at its own random time;
- ``shared``: the same tables trained as a shared base plus per-keyframe deltas (``T_k = B +
  D_k``, torch's parametrisation; the sum is the model), the base read by every sample;
- ``few-times``: batches drawn from 4 distinct times of the cached set (2,048 points each);
- ``warm-start``: the first quarter of the steps trains the static grid on the first frame, then
  its table is copied into every keyframe table (and its MLP kept) and the tables train on.

Per variant: the mean error in the +-1 mm band every ``--every`` steps (static: at the first
frame; the others: at 16 random times) and the steps per second; then one step's time split into
forward (encoding + MLP + analytic gradient), backward and Adam, for the static grid and the
keyframe tables. Figures in docs/neural.md ("Why the keyframe tables learn slower").

    python benchmarks/keyframe_learning.py --steps 400 --every 100
"""
import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

from collider_server.engine.kinds.neural import ANIMATED_PRESETS, build_network
from collider_server.engine.kinds.neural_keyframes import keyframe_segments
from collider_server.engine.meshes import ExactSDF
from collider_server.making.animation_files import load_animation
from collider_server.making.training import TrainConfig
from collider_server.making.training.data import (
    animated_validation_sets,
    make_animated_training_data,
    make_training_data,
    normalisation,
    validation_sets,
)
from collider_server.making.training.schedule import cosine_learning_rate, set_training_threads

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("--steps", type=int, default=400)
parser.add_argument("--every", type=int, default=100)
parser.add_argument("--samples", type=int, default=200_000)
parser.add_argument("--variants", default="static,keyframes,shared,few-times,warm-start")
args = parser.parse_args()

ROOT = Path(__file__).resolve().parents[1]
animation = load_animation(ROOT / "examples/animations/arm.obj", ROOT / "examples/animations/arm.pc2", 24.0)
arch = ANIMATED_PRESETS["keyframes"]
set_training_threads(arch, 2)
config = TrainConfig(preset="keyframes", samples=args.samples)
centre, radius = normalisation(animation, config.padding)
duration = animation.timeline.duration_s
rest = animation.frame(0)
static_data = make_training_data(rest, ExactSDF(rest), config, 1.0, False)
static_val = validation_sets(rest, ExactSDF(rest), 4000, 100, 1.0)["1mm"]
moving_data = make_animated_training_data(animation, config, 1.0, False)
moving_val = animated_validation_sets(animation, 4000, 100, 1.0)["1mm"]
print(f"load average {os.getloadavg()[0]:.2f} (data made)", flush=True)


def segments(times):
    key, frac = keyframe_segments(times, duration, arch.keyframes)
    return torch.from_numpy(key), torch.from_numpy(frac)


class SharedBase(torch.nn.Module):
    def forward(self, base, deltas):
        return base.unsqueeze(0) + deltas

    def right_inverse(self, table):
        base = table.mean(dim=0)
        return base, table - base.unsqueeze(0)


def sampler(variant, data):
    count = len(data.points)
    if variant != "few-times":
        return lambda generator: torch.randint(0, count, (8192,), generator=generator)
    starts = np.flatnonzero(np.r_[True, data.times[1:] != data.times[:-1]])
    start, size = torch.from_numpy(starts), torch.from_numpy(np.diff(np.r_[starts, count]))
    owner = torch.arange(8192) * 4 // 8192

    def draw(generator):
        chosen = torch.randperm(len(starts), generator=generator)[:4][owner]
        return start[chosen] + (torch.rand(8192, generator=generator, dtype=torch.float64) * size[chosen]).long()

    return draw


def adam(network, fused):
    # The loop's optimiser (schedule.make_optimizer): the tables (here also base and deltas) in
    # their own group with instant-NGP's settings, fused Adam for keyframe tables.
    table_names = [n for n, _ in network.named_parameters() if "table" in n]
    parameters = [
        {"params": [p for n, p in network.named_parameters() if n in table_names]},
        {"params": [p for n, p in network.named_parameters() if n not in table_names]},
    ]
    return torch.optim.Adam(parameters, lr=1e-2, betas=(0.9, 0.99), eps=1e-15, fused=fused or None)


WARM_STEPS = args.steps // 4
assert WARM_STEPS < args.every, "warm-start validates its keyframe network only"
runs = {}
for variant in args.variants.split(","):
    torch.manual_seed(0)
    static = variant in ("static", "warm-start")
    network = build_network(arch.spatial() if static else arch, centre, radius)
    if variant == "shared":
        torch.nn.utils.parametrize.register_parametrization(network, "table", SharedBase(), unsafe=True)
    optimizer = adam(network, not static)
    data, val = (static_data, static_val) if static else (moving_data, moving_val)
    extra = () if static else segments(data.times)
    runs[variant] = {
        "network": network, "optimizer": optimizer, "draw": sampler(variant, data),
        "data": [torch.from_numpy(a) for a in (data.points, data.distance, data.gradient, data.near)], "extra": extra,
        "val": (torch.from_numpy(val[0]), torch.from_numpy(val[1]), () if static else segments(val[2])),
        "generator": torch.Generator().manual_seed(0), "seconds": 0.0,
    }

for step in range(1, args.steps + 1):
    lr = cosine_learning_rate(step / args.steps, 1e-2, 1e-4)
    if step == WARM_STEPS + 1 and "warm-start" in runs:
        run = runs["warm-start"]
        warm = build_network(arch, centre, radius)
        with torch.no_grad():
            warm.table.copy_(run["network"].table.unsqueeze(0).expand_as(warm.table))
        warm.body.load_state_dict(run["network"].body.state_dict())
        run.update(network=warm, optimizer=adam(warm, True), draw=sampler("keyframes", moving_data),
                   data=[torch.from_numpy(a) for a in (moving_data.points, moving_data.distance,
                                                       moving_data.gradient, moving_data.near)],
                   extra=segments(moving_data.times), val=(torch.from_numpy(moving_val[0]),
                                                          torch.from_numpy(moving_val[1]), segments(moving_val[2])))
    for run in runs.values():
        points, target, target_gradient, near = run["data"]
        began = time.perf_counter()
        for group in run["optimizer"].param_groups:
            group["lr"] = lr
        index = run["draw"](run["generator"])
        prediction, gradient = run["network"].value_and_gradient(points[index], *(a[index] for a in run["extra"]))
        mask = near[index]
        cosine = torch.nn.functional.cosine_similarity(gradient[mask], target_gradient[index][mask], dim=1)
        loss = (prediction - target[index]).abs().mean() / radius + 0.1 * (1 - cosine).mean()
        run["optimizer"].zero_grad(set_to_none=True)
        loss.backward()
        run["optimizer"].step()
        run["seconds"] += time.perf_counter() - began
    if step % args.every == 0:
        shown = []
        for variant, run in runs.items():
            p, d, e = run["val"]
            with torch.no_grad():
                error = float((run["network"](p, *e) - d).abs().mean()) * 1000
            shown.append(f"{variant} {error:.4f} mm ({step / run['seconds']:.2f} steps/s)")
        print(f"step {step}: " + "  ".join(shown) + f"  load {os.getloadavg()[0]:.1f}", flush=True)

# One step's split (the same batch of 8192 random points of the moving set, 10 rounds after 2).
index = torch.randint(0, len(moving_data.points), (8192,), generator=torch.Generator().manual_seed(1))
for variant in ("static", "keyframes"):
    if variant not in runs:
        continue
    run = runs[variant]
    points, target, _, _ = run["data"]
    split = np.zeros(3)
    for round_ in range(12):
        began = time.perf_counter()
        prediction, gradient = run["network"].value_and_gradient(points[index], *(a[index] for a in run["extra"]))
        loss = (prediction - target[index]).abs().mean() + gradient.square().mean()
        forward = time.perf_counter()
        run["optimizer"].zero_grad(set_to_none=True)
        loss.backward()
        backward = time.perf_counter()
        run["optimizer"].step()
        if round_ >= 2:
            split += [forward - began, backward - forward, time.perf_counter() - backward]
    split *= 100  # ms per step over 10 rounds
    print(f"{variant}: forward {split[0]:.0f} ms, backward {split[1]:.0f} ms, Adam {split[2]:.0f} ms "
          f"(load {os.getloadavg()[0]:.1f})", flush=True)
