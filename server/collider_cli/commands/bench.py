"""``collider bench MESH``: what accuracy costs in time, every collider kind of a mesh measured here
(the error-budget bake that builds on it: :mod:`.budget`)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from .diagnostics import print_mesh_check
from .options import (
    add_cache_argument,
    add_device_argument,
    add_models_argument,
    add_placement_arguments,
    add_quiet_argument,
    cache_dir,
    cache_size_line,
    load_placed_mesh,
)

SUFFIXES = {"k": 1_000, "M": 1_000_000}


def _ints(text: str) -> tuple[int, ...]:
    """``"10k,40k,1M"`` or ``"10000,40000"`` -> (10000, 40000, ...)."""
    values = []
    for item in (v.strip().replace("_", "") for v in text.split(",")):
        if not item:
            continue
        factor = SUFFIXES.get(item[-1], 1)
        try:
            values.append(int(item[:-1] if factor > 1 else item) * factor)
        except ValueError:
            raise ValueError(f"expected comma-separated integers (10k, 1M allowed), got {text!r}") from None
    return tuple(values)


def register(subparsers) -> None:
    bench = subparsers.add_parser(
        "bench", help="what accuracy costs in time: every collider kind of a mesh, measured here",
        description="Builds kdtree, mesh, voxel grids (up to --max-memory) and the neural presets "
                    "of MESH, measures their errors against the exact SDF (+-1 mm and +-10 mm "
                    "bands) and their query time (10k, 40k, 1M points; distance, and "
                    "distance+normal+contact; embedded and through a real `collider serve`; CPU, "
                    "and CUDA when present), every collider timed in interleaved rounds (median, "
                    "spread, process CPU time; unstable figures retimed, no front called from "
                    "them: docs/accuracy.md). Writes bench.json (every raw figure and the machine), "
                    "bench.md (tables) and bench-DEVICE.png (error vs time, Pareto front).")
    bench.add_argument("mesh", help="mesh file (OBJ, PLY, STL, OFF, GLB), or a skinned character (glTF with a skin, USD)")
    add_placement_arguments(bench)
    bench.add_argument("--quick", action="store_true",
                       help="a small run (about a minute): 10k and 40k points, voxel 32 and 64, 5 rounds")
    bench.add_argument("--kinds", default=None, help="comma-separated subset of kdtree,mesh,voxel,neural")
    bench.add_argument("--resolutions", default=None, help="voxel resolutions to try (default 64,128,256,512)")
    bench.add_argument("--max-memory", default=None,
                       help="largest collider memory, e.g. 128MiB (default); voxel grids stop before it")
    bench.add_argument("--train-minutes", type=float, default=None,
                       help="train each neural preset without a trained model of this mesh for this long "
                            "(with --animation: the 4D network); default 0: list them as not measured")
    bench.add_argument("--presets", default=None,
                       help="comma-separated neural presets to include (default: every preset)")
    bench.add_argument("--sizes", default=None, help="points per query call (default 10k,40k,1M)")
    bench.add_argument("--accuracy-points", type=int, default=None, help="points per band (default 40000)")
    bench.add_argument("--repeats", type=int, default=None,
                       help="timing rounds: most timed calls per cell (default 5)")
    bench.add_argument("--cell-seconds", type=float, default=None,
                       help="a cell leaves the rounds once its calls took this long (default 10; the reference "
                            "cells after 3 calls at least)")
    bench.add_argument("--no-served", action="store_true", help="skip the served (HTTP) half")
    add_device_argument(bench, "cpu or cuda (default: cpu, and cuda when present)")
    bench.add_argument("--threads", type=int, default=None,
                       help="CPU threads of the engine, embedded and served (default: all cores but one, "
                            "as `collider serve` computes with)")
    bench.add_argument("--seed", type=int, default=0)
    add_models_argument(bench, "searched for trained neural models of MESH")
    animated = bench.add_argument_group(
        "animated colliders", "with --animation, MESH (an OBJ) and its frames are benched: the animated "
        "mesh kind (exact), voxel keyframe grids at each --resolutions and --keyframes and, with "
        "--train-minutes, the 4D network (preset keyframes) trained here; errors at "
        "--times random times between frames, queries (distance, and distance+normal+contact+velocity) "
        "at one random time; --quick: voxel 16 and 32, 5 keyframes and every frame, 4 times")
    animated.add_argument("--animation", default=None, metavar="CACHE",
                          help="MESH's frames: a PC2 vertex cache or a quoted pattern of OBJ files "
                               "(as `collider bake --animation`)")
    animated.add_argument("--fps", type=float, default=None, help="frames per second of --animation")
    ends = animated.add_mutually_exclusive_group()
    ends.add_argument("--loop", dest="loop", action="store_true", default=False,
                      help="beyond the ends the time wraps around")
    ends.add_argument("--clamp", dest="loop", action="store_false", help="the end frames are held (default)")
    animated.add_argument("--keyframes", default=None,
                          help="voxel keyframe counts, 'all' = one per frame (default 5,13,all)")
    animated.add_argument("--times", type=int, default=None,
                          help="random times the errors are measured at (default 8; a character: random clip "
                               "times)")
    skinned = bench.add_argument_group(
        "skinned characters", "when MESH is a skinned character (glTF with a skin, USD), its exact skinned "
        "kind and the articulated networks (kind neural-skinned) of --models made from it are benched: errors "
        "at --times random clip times (asked by clip and time) and at --poses random poses (every joint turned, "
        "asked by joint transforms), apart, against the exact skin at each pose; queries "
        "(distance, and distance+normal+contact+velocity) at one random clip time and at one random pose; "
        "--kinds: some of skinned,neural-skinned; --loop as the model; --quick: 4 times, 4 poses")
    skinned.add_argument("--poses", type=int, default=None,
                         help="random poses off the clips the errors are measured at (default 8)")
    bench.add_argument("--output", type=Path, default=None,
                       help="folder of the results: bench.json, bench.md, bench-DEVICE.png (default out/bench-MESH)")
    add_cache_argument(bench)
    add_quiet_argument(bench)
    bench.set_defaults(func=run_bench_command)


def bench_config(args, character: bool = False):
    """The :class:`~collider_cli.bench.run.BenchConfig` of the options (``character``: a skinned
    character's bench, whose --kinds are its own)."""
    from ..bench import QUICK, BenchConfig
    from ..bench.budget import size_bytes

    base = QUICK if args.quick else BenchConfig()
    plan = base.plan
    if args.kinds is not None and not character:
        plan = dataclasses.replace(plan, kinds=tuple(k.strip() for k in args.kinds.split(",") if k.strip()))
    if args.resolutions is not None:
        plan = dataclasses.replace(plan, resolutions=_ints(args.resolutions))
    if args.max_memory is not None:
        plan = dataclasses.replace(plan, max_memory_bytes=size_bytes(args.max_memory))
    if args.train_minutes is not None:
        plan = dataclasses.replace(plan, train_minutes=args.train_minutes)
    if args.presets is not None:
        plan = dataclasses.replace(plan, presets=tuple(p.strip() for p in args.presets.split(",") if p.strip()))
    timing = base.timing
    if args.repeats is not None:
        timing = dataclasses.replace(timing, repeats=args.repeats)
    if args.cell_seconds is not None:
        timing = dataclasses.replace(timing, cell_budget_s=args.cell_seconds)
    devices = None
    if args.device is not None:
        devices = (args.device,)
    return dataclasses.replace(
        base, plan=plan, timing=timing, devices=devices, seed=args.seed, threads=args.threads,
        sizes=_ints(args.sizes) if args.sizes else base.sizes,
        accuracy_points=args.accuracy_points if args.accuracy_points is not None else base.accuracy_points,
        paths=("embedded",) if args.no_served else base.paths)


def animated_plan_config(args):
    """The :class:`~collider_cli.bench.animated.AnimatedPlanConfig` of ``--animation``'s options."""
    from ..bench.animated import QUICK_PLAN, AnimatedPlanConfig
    from ..bench.budget import size_bytes

    if args.presets is not None:
        raise ValueError("--presets is for a static mesh; with --animation the neural kind is the 4D "
                         "network (preset keyframes), trained for --train-minutes")
    plan = QUICK_PLAN if args.quick else AnimatedPlanConfig()
    if args.train_minutes is not None:
        plan = dataclasses.replace(plan, train_minutes=args.train_minutes)
    if args.kinds is not None:
        plan = dataclasses.replace(plan, kinds=tuple(k.strip() for k in args.kinds.split(",") if k.strip()))
    if args.resolutions is not None:
        plan = dataclasses.replace(plan, resolutions=_ints(args.resolutions))
    if args.keyframes is not None:
        counts = [k.strip() for k in args.keyframes.split(",") if k.strip()]
        plan = dataclasses.replace(plan, keyframes=tuple(None if k == "all" else _ints(k)[0] for k in counts))
    if args.max_memory is not None:
        plan = dataclasses.replace(plan, max_memory_bytes=size_bytes(args.max_memory))
    if args.times is not None:
        plan = dataclasses.replace(plan, times=args.times)
    plan.check()
    return plan


def run_bench_command(args) -> int:
    from collider_server.making.characters import is_skinned_character

    from ..bench import run_bench
    from ..bench.report import interrupted_line, summary, write_outputs

    character = args.animation is None and is_skinned_character(args.mesh)
    config = bench_config(args, character)
    config.check()
    _check_device(config.devices)
    output = args.output or Path("out") / f"bench-{Path(args.mesh).stem}"
    cache = cache_dir(args)
    if character:
        report = run_skinned(args, config, cache)
    elif args.animation is not None:
        report = run_animated(args, config, cache)
    elif args.poses is not None:
        raise ValueError("--poses is for a skinned character (glTF with a skin, USD)")
    elif (args.fps, args.keyframes, args.times) != (None, None, None) or args.loop:
        raise ValueError("--fps, --loop/--clamp, --keyframes and --times need --animation")
    else:
        mesh, transform, units, meters_per_unit = load_placed_mesh(args)
        check = print_mesh_check(mesh, file=sys.stderr)
        report = run_bench(mesh, transform, config, units=units, meters_per_unit=meters_per_unit,
                           models_root=args.models, cache=cache, mesh_path=str(args.mesh),
                           show_progress=not args.quiet)
        report["mesh"]["check"] = check.to_dict()
    add_hints(report, args)
    paths = write_outputs(report, output)
    print(summary(report))
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    print(cache_size_line(cache))
    print(sign_line(report))
    if report.get("interrupted"):
        print(interrupted_line(paths), file=sys.stderr)
        raise KeyboardInterrupt  # the exit status of an interrupted run, its figures written
    return 0


def run_animated(args, config, cache: Path) -> dict:
    """The animated bench of ``args.mesh`` and ``--animation`` (placed as every command does)."""
    from collider_server.making.animation_files import check_frame_rate, load_animation
    from collider_server.making.mesh_check import check_animation

    from ..bench.animated import run_animated_bench
    from .options import placement_from_args

    plan = animated_plan_config(args)
    if args.fps is None:
        raise ValueError("--animation needs --fps (frames per second: a vertex cache does not say)")
    check_frame_rate(args.fps)
    placement = placement_from_args(args)
    animation, transform = placement.apply_to_animation(
        load_animation(args.mesh, args.animation, args.fps, args.loop))
    check = check_animation(animation)  # the first frame's topology, every frame's crossings
    for line in check.lines():
        print(line, file=sys.stderr)
    report = run_animated_bench(animation, transform, config, plan, units=placement.units,
                                meters_per_unit=placement.meters_per_unit, cache=cache,
                                mesh_path=str(args.mesh), cache_path=str(args.animation),
                                show_progress=not args.quiet)
    report["mesh"]["check"] = check.to_dict()
    return report


def run_skinned(args, config, cache: Path) -> dict:
    """The skinned bench of the character ``args.mesh`` (placed as every command does)."""
    import time

    from collider_server.making.characters import skinned_from_file
    from collider_server.making.placement import MeshPlacement

    from ..bench.skinned import QUICK_PLAN, SkinnedPlanConfig, run_skinned_bench
    from .options import placement_from_args

    kept = [option for option, value in (("--resolutions", args.resolutions), ("--max-memory", args.max_memory),
                                         ("--train-minutes", args.train_minutes), ("--presets", args.presets),
                                         ("--fps", args.fps), ("--keyframes", args.keyframes)) if value is not None]
    if kept:
        raise ValueError(f"{', '.join(kept)}: not for a skinned character; its bench measures the exact skinned "
                         f"kind and the articulated networks of the repository (train one with `collider train "
                         f"{args.mesh} --name NAME`)")
    plan = QUICK_PLAN if args.quick else SkinnedPlanConfig()
    if args.kinds is not None:
        plan = dataclasses.replace(plan, kinds=tuple(k.strip() for k in args.kinds.split(",") if k.strip()))
    if args.times is not None:
        plan = dataclasses.replace(plan, times=args.times)
    if args.poses is not None:
        plan = dataclasses.replace(plan, poses=args.poses)
    plan.check()
    started = time.perf_counter()
    placement = placement_from_args(args) or MeshPlacement()
    exact, read, transform = skinned_from_file(args.mesh, "skinned", placement, loop=args.loop, padding=plan.padding)
    seconds = time.perf_counter() - started
    for note in read.notes:
        print(f"{args.mesh}: {note}", file=sys.stderr)
    return run_skinned_bench(exact, read, transform, config, plan, cache=cache, models_root=args.models,
                             mesh_path=str(args.mesh), exact_seconds=seconds, show_progress=not args.quiet)


def add_hints(report: dict, args) -> None:
    """A pasteable command to each "not measured" entry that a command can fix."""
    from .hints import again_with, command, models_options, placement_options

    for skipped in report["skipped"]:
        preset = skipped.get("preset")
        if preset is not None and args.animation is not None:
            skipped["reason"] += f"; measure it with `{again_with(args, '--train-minutes', '3')}` (trains it 3 minutes)"
        elif preset is not None:
            name = f"{Path(args.mesh).stem}-{preset}"
            skipped["reason"] += (f"; measure it with `{again_with(args, '--train-minutes', '3')}` (trains each such "
                                  f"preset 3 minutes) or train it first with `"
                                  + command("train", args.mesh, "--name", name, "--preset", preset,
                                            *placement_options(args), *models_options(args), "--max-minutes", "15")
                                  + "`")
        elif skipped.get("model") is not None:
            skipped["reason"] += f" (see `{command('info', skipped['model'], *models_options(args))}`)"


def sign_line(report: dict) -> str:
    """The closing line on the sign: each collider's measured sign errors in the +-1 mm band."""
    figures = ", ".join(f"{r['label']} {r['accuracy']['band_1mm']['sign_errors_percent']:.2f} %"
                        for r in report["colliders"])
    return ("sign errors, +-1 mm band (points farther than 0.2 mm from the surface, against the exact "
            f"winding-number sign): {figures or 'none measured'}")


def _check_device(devices) -> None:
    if devices is None:
        return
    for device in devices:
        if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
            raise ValueError(f"--device must be cpu or cuda, got {device!r}")
        if device.startswith("cuda"):
            import torch

            if not torch.cuda.is_available():
                raise ValueError("--device cuda: no CUDA GPU on this machine")
