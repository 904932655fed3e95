"""``collider train`` and ``collider eval``."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from .diagnostics import print_mesh_check, sign_check_line
from .hints import again_with, command, models_options, placement_options
from .options import (
    add_animation_arguments,
    add_device_argument,
    add_models_argument,
    add_placement_arguments,
    add_quiet_argument,
    check_animation_arguments,
    load_animated_source,
    load_placed_animation,
    placement_from_args,
)


def register(subparsers) -> None:
    from collider_server.engine.kinds.neural import ANIMATED_PRESETS, DEFAULT_ANIMATED_PRESET, PRESETS
    from collider_server.making.training import DEFAULT_STEPS, TrainConfig

    defaults = TrainConfig()
    train = subparsers.add_parser(
        "train", help="train a neural collider from a mesh (or an animated one)",
        description="Train a neural collider of MESH. With --animation, one network for the whole "
                    "animation, validated at random times against the exact interpolated mesh: "
                    "keyframe feature tables blended in time (preset keyframes, any motion), or the "
                    "rest pose's grid carried by deformation fields fitted to the frames (preset "
                    "deformed, a smooth deformation such as a twist or a squash: docs/neural.md).")
    train.add_argument("mesh", help="mesh file (OBJ, PLY, STL, OFF, GLB; an OBJ with --animation), or a skinned "
                                    "character (glTF .gltf/.glb with a skin, USD): its articulated network, kind "
                                    "neural-skinned, answering at any pose of its skeleton")
    train.add_argument("--name", required=True, help="model name (file NAME.safetensors)")
    train.add_argument("--preset", default=None, choices=sorted({**PRESETS, **ANIMATED_PRESETS}),
                       help=f"network (default {defaults.preset}: a feature grid + tiny MLP, the fastest to "
                            "train and to query; paper-bunny / paper-dragon reproduce the paper. With "
                            "--animation the default is the animated preset that measures better after a short "
                            "trial of each (deformed, keyframes), charged to --max-minutes; docs/neural.md)")
    train.add_argument("--samples", type=int, default=defaults.samples, help="cached training samples")
    train.add_argument("--steps", type=int, default=None,
                       help="cap on optimiser steps (default: none with --max-minutes, which then runs to the "
                            f"end of its budget; {DEFAULT_STEPS:,} without)")
    train.add_argument("--batch-size", type=int, default=defaults.batch_size)
    train.add_argument("--learning-rate", type=float, default=defaults.learning_rate,
                       help="initial Adam learning rate (default: the preset's, 1e-2 grid / 1e-3 paper)")
    train.add_argument("--normal-weight", type=float, default=defaults.normal_weight,
                       help="weight of the 1 - cos(normal) term (default: the preset's, 0.1 grid / 0.05 paper; 0: pure L1)")
    train.add_argument("--max-minutes", type=float, default=None,
                       help="time budget of the training (after the exact-SDF samples): the learning-rate "
                            "schedule, validations, progress bar and stop follow the clock; keeps the best weights")
    train.add_argument("--seed", type=int, default=defaults.seed)
    train.add_argument("--threads", type=int, default=None, help="CPU threads for torch")
    add_animation_arguments(train, "feature tables of preset keyframes, evenly spaced from the first frame to the last "
                                   f"(default: the preset's, {ANIMATED_PRESETS[DEFAULT_ANIMATED_PRESET].keyframes})")
    train.add_argument("--deformation-resolution", type=int, default=None, metavar="N",
                       help="cells per side of preset deformed's deformation fields (implies --preset deformed; "
                            f"default: the preset's, {ANIMATED_PRESETS['deformed'].deformation_resolution}): finer "
                            "fields follow a larger bend (the fit prints how far they miss) at (N + 1)^3 x 12 bytes "
                            "per frame; docs/neural.md")
    add_placement_arguments(train)
    add_models_argument(train, "where the model is written")
    train.add_argument("--runs", type=Path, default=None, metavar="DIR",
                       help="folder of the resumable checkpoints (default: runs/ beside the model folder)")
    train.add_argument("--checkpoint", type=Path, default=None,
                       help="resumable checkpoint file (default: RUNS/NAME.ckpt.safetensors)")
    add_device_argument(train)
    add_quiet_argument(train)
    train.set_defaults(func=run_train)

    evaluate = subparsers.add_parser(
        "eval", help="measure a collider against the exact mesh SDF",
        description="Measure MODEL against the exact signed distance of the mesh it was made from: "
                    "distance, sign, normal and contact errors in the +-1 mm and +-10 mm bands "
                    "around the surface and in its domain box. An animated model is measured at "
                    "--times random times drawn uniformly over its animation (between its "
                    "frames), against the exact interpolated mesh at each time: give the frames "
                    "it was made from, --mesh OBJ --animation CACHE. A skinned model (kind skinned "
                    "or neural-skinned) is measured at --times random clip times and at --poses "
                    "random poses off its clips (a random clip time, then every joint's local "
                    "rotation turned about a random axis by up to 15 degrees), each against the "
                    "exact skin of --mesh CHARACTER (its glTF or USD file) at that pose, reported "
                    "apart.")
    evaluate.add_argument("model", help="model name or .safetensors path (any kind)")
    evaluate.add_argument("--mesh", required=True, help="the mesh it was made from (its original file; "
                                                         "an animated model: its OBJ; a skinned model: "
                                                         "its character file)")
    evaluate.add_argument("--points", type=int, default=100_000,
                          help="points per band (an animated model: over all its times)")
    evaluate.add_argument("--seed", type=int, default=1234)
    evaluate.add_argument("--no-reconstruction", action="store_true", help="skip marching cubes")
    evaluate.add_argument("--no-save", action="store_true", help="do not write the figures into the model")
    evaluate.add_argument("--store-anyway", action="store_true",
                          help="write the figures into the model even when --mesh or the placement "
                               "is not the model's source (otherwise refused, exit 2)")
    evaluate.add_argument("--report", type=Path, default=None, help="also write the figures as JSON here")
    animated = evaluate.add_argument_group("animated models")
    animated.add_argument("--animation", default=None, metavar="CACHE",
                          help="the vertex cache (PC2, or a quoted pattern of OBJ files) the model was "
                               "made from, as given to `collider bake --animation`")
    animated.add_argument("--fps", type=float, default=None,
                          help="frames per second of --animation (default: the rate the model was made at)")
    animated.add_argument("--times", type=int, default=None,
                          help="random times the model is measured at (default 16; a skinned model: "
                               "random times of random clips)")
    skinned = evaluate.add_argument_group("skinned models")
    skinned.add_argument("--poses", type=int, default=None,
                         help="random poses off the clips a skinned model is measured at (default 16)")
    add_models_argument(evaluate)
    add_device_argument(evaluate)
    add_quiet_argument(evaluate)
    add_placement_arguments(evaluate, as_stored=True)
    evaluate.set_defaults(func=run_eval)


def run_train(args) -> int:
    from collider_server.engine.kinds.neural import DEFAULT_ANIMATED_PRESET, DEFAULT_PRESET
    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.repository import ModelRepository, check_name, check_writable_folder
    from collider_server.making.mesh_files import load_mesh
    from collider_server.making.training import (
        TrainConfig,
        check_preset,
        choose_animated_preset,
        read_checkpoint_state,
        remaining_minutes,
        train_animated_neural,
        train_neural,
    )

    check_name(args.name)
    from collider_server.making.characters import is_skinned_character

    if args.animation is None and is_skinned_character(args.mesh):
        return run_train_character(args)
    check_animation_arguments(args)
    animated = args.animation is not None
    fields = args.deformation_resolution
    if fields is not None and not animated:
        raise ValueError("--deformation-resolution needs --animation (the deformed preset's fields follow its frames)")
    # An animation without --preset (or --keyframes or --deformation-resolution, one preset's options)
    # gets the animated preset that suits its motion, measured once it is loaded.
    choose = animated and args.preset is None and args.keyframes is None and fields is None
    default_preset = ("deformed" if fields is not None else DEFAULT_ANIMATED_PRESET) if animated else DEFAULT_PRESET
    architecture = {} if args.keyframes is None else {"keyframes": args.keyframes}
    if fields is not None:
        architecture["deformation_resolution"] = fields
    config = TrainConfig(
        preset=args.preset or default_preset, samples=args.samples,
        steps=args.steps, batch_size=args.batch_size,
        learning_rate=args.learning_rate, normal_weight=args.normal_weight,
        max_minutes=args.max_minutes, seed=args.seed, threads=args.threads,
        architecture=architecture,
    )
    check_preset(config, animated)
    placement = placement_from_args(args)
    if animated:
        mesh, transform = load_placed_animation(args, placement)
    else:
        mesh, transform = placement.apply(load_mesh(args.mesh))
    repository = ModelRepository(args.models)
    checkpoint = args.checkpoint or (args.runs or repository.root.parent / "runs") / f"{args.name}.ckpt.safetensors"
    # Both folders are proved writable now, not after the training budget is spent.
    repository.check_writable()
    check_writable_folder(checkpoint.parent, "checkpoint folder")
    if animated:
        from collider_server.making.mesh_check import check_animation

        check = check_animation(mesh)
        for line in check.lines():
            print(line)
    else:
        check = print_mesh_check(mesh)
    extra = {}
    resumed = read_checkpoint_state(checkpoint).get("run", {}).get("settings", {}).get("preset") \
        if choose and checkpoint.is_file() else None
    if resumed is not None:  # the checkpoint's run goes on: its preset, not a new measurement
        print(f"preset {resumed}: the preset of the run {checkpoint} resumes (--preset to choose)")
        config = replace(config, preset=resumed)
    elif choose:
        choice = choose_animated_preset(mesh, config, placement.meters_per_unit, args.device, not args.quiet)
        print(choice.reason)
        # The choice's minutes are the budget's.
        config = replace(config, preset=choice.preset, max_minutes=remaining_minutes(config, choice))
        extra["deformation"] = choice.fit
    try:
        result = (train_animated_neural if animated else train_neural)(
            mesh, args.name, config, units=placement.units,
            meters_per_unit=placement.meters_per_unit, transform=transform,
            device=args.device, checkpoint=checkpoint, show_progress=not args.quiet, **extra,
        )
    except KeyboardInterrupt:  # what the run made: its checkpoint, which the same command resumes
        if checkpoint.is_file():
            print(f"interrupted: {checkpoint} keeps the run up to its last validation; the same command "
                  f"resumes it: `{again_with(args)}`", file=sys.stderr)
        raise
    result.collider.info.source["check"] = check.to_dict()
    result.collider.info.source["path"] = str(Path(args.mesh).resolve())
    path = save_collider(result.collider, repository.path(args.name))
    history = checkpoint.with_name(checkpoint.name + ".history.json")
    history.write_text(json.dumps(result.history, indent=1))
    print(f"wrote {path} ({path.stat().st_size:,} bytes): {result.summary()}")
    print(f"checkpoint {checkpoint} (resumable; its history beside it)")
    if animated:
        from .models import describe_animation

        network = {"keyframes": "keyframe tables", "deformed": "a rest pose and one deformation field per frame"}
        print(f"animated: {describe_animation(result.collider.info.animation)} "
              f"({network.get(config.preset, config.preset)}); "
              f"source {mesh.timeline.frames} frames at {mesh.timeline.frame_rate_hz:g} fps")
        return 0
    print(sign_check_line(result.collider, mesh, check))
    print("next: " + command("eval", args.name, "--mesh", args.mesh, *models_options(args), *placement_options(args)))
    return 0


def run_train_character(args) -> int:
    """``collider train CHARACTER``: the articulated network of a skinned character (glTF or USD;
    kind ``neural-skinned``, docs/neural.md), answering at any pose of its skeleton."""
    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.characters import skinned_from_file
    from collider_server.making.training import TrainConfig
    from collider_server.making.training.articulated import train_articulated

    if args.fps is not None or args.keyframes is not None:
        raise ValueError("--fps and --keyframes are for vertex caches; a skinned character brings its own clips")
    if args.preset is not None:
        raise ValueError(f"--preset is for meshes and vertex caches; a skinned character ({args.mesh}) trains "
                         "the articulated network (docs/neural.md)")
    if args.checkpoint is not None or args.runs is not None:
        raise ValueError("an articulated network's run keeps no checkpoint (--checkpoint, --runs); it trains "
                         "within its --max-minutes")
    config = TrainConfig(samples=args.samples, steps=args.steps, batch_size=args.batch_size,
                         learning_rate=args.learning_rate, normal_weight=args.normal_weight,
                         max_minutes=args.max_minutes, seed=args.seed, threads=args.threads)
    config.check()
    placement = placement_from_args(args)
    repository = ModelRepository(args.models)
    repository.check_writable()  # before the training, not after
    exact, read, _ = skinned_from_file(args.mesh, args.name, placement, loop=args.loop)
    for note in read.notes:
        print(f"{args.mesh}: {note}")
    result = train_articulated(exact.skin, args.name, config, units=placement.units,
                               meters_per_unit=placement.meters_per_unit, loop=args.loop,
                               source=exact.info.source, show_progress=not args.quiet, say=print)
    path = save_collider(result.collider, repository.path(args.name))
    print(f"wrote {path} ({path.stat().st_size:,} bytes, kind neural-skinned: "
          f"{len(exact.info.skeleton['joints'])} joints): {result.summary()}")
    return 0


def run_eval(args) -> int:
    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.evaluation import format_report

    repo = ModelRepository(args.models)
    path = repo.resolve(args.model)
    collider = repo.load(args.model, args.device)
    check_units(collider.info, args)
    for option, value in (("--times", args.times), ("--poses", args.poses)):
        if value is not None and value < 1:
            raise ValueError(f"{option} must be a positive number of random {option[2:]}, got {value}")
    if collider.skinned:
        report, differs = eval_skinned(collider, path, args)
    else:
        report, differs = eval_mesh(collider, path, args)
    print(format_report(collider.info.name, collider.info.kind, report))
    if args.report is not None:
        args.report.write_text(json.dumps(report, indent=2))
    if args.no_save:
        return 0
    if differs and not args.store_anyway:
        raise ValueError(f"figures not written into {path}: {'; '.join(differs)} (measured against "
                         "another mesh; pass --store-anyway to store them, --no-save to only print)")
    # Not the file's size: storing the figures changes it (the file tells its own size).
    collider.info.accuracy = {key: value for key, value in report.items() if key != "file_bytes"}
    save_collider(collider, path)
    print(f"figures written into {path}")
    return 0


def eval_mesh(collider, path, args) -> tuple[dict, list[str]]:
    """``collider eval`` of a static or animated model: its report and why ``--mesh`` (and
    ``--animation``) is not its source (empty when it is)."""
    from collider_server.making.evaluation import evaluate_animated_collider, evaluate_collider
    from collider_server.making.mesh_files import load_mesh

    if args.poses is not None:
        raise ValueError(f"{collider.info.name} is not skinned: --poses is for skinned models")
    if not collider.animated and (args.animation, args.fps, args.times) != (None, None, None):
        raise ValueError(f"{collider.info.name} is static: --animation, --fps and --times are for animated "
                         "models (measure it with --mesh alone)")
    stored = np.asarray(collider.info.source.get("transform", np.eye(4)), dtype=np.float64)
    placement = placement_from_args(args)
    raw = load_animated_source(collider.info, args) if collider.animated else load_mesh(args.mesh)
    transform = stored if placement is None else placement.transform(
        raw.frame(0) if collider.animated else raw)  # an animation is placed by its first frame
    placed = raw if np.allclose(transform, np.eye(4)) else raw.transformed(transform)
    differs = report_differences(collider.info, raw, transform, args)
    if collider.animated:
        report = evaluate_animated_collider(collider, placed, points=args.points, times=args.times or 16,
                                            seed=args.seed, path=path, show_progress=not args.quiet)
    else:
        report = evaluate_collider(collider, placed, points=args.points, seed=args.seed,
                                   reconstruction=not args.no_reconstruction, path=path,
                                   show_progress=not args.quiet)
    return report, differs


def eval_skinned(collider, path, args) -> tuple[dict, list[str]]:
    """``collider eval`` of a skinned model (kind ``skinned`` or ``neural-skinned``) against the
    character file ``--mesh`` placed as the model was made: random clip times and random poses
    (:func:`~collider_server.making.evaluation.evaluate_skinned_collider`)."""
    from collider_server.engine.meshes import Mesh
    from collider_server.making.characters import read_character
    from collider_server.making.evaluation import evaluate_skinned_collider
    from collider_server.making.placement import transformed_skin

    if (args.animation, args.fps) != (None, None):
        raise ValueError(f"{collider.info.name} is skinned: --animation and --fps are for vertex caches; give "
                         "its character file (--mesh CHARACTER), --times and --poses")
    read = read_character(args.mesh)
    stored = np.asarray(collider.info.source.get("transform", np.eye(4)), dtype=np.float64)
    placement = placement_from_args(args)
    transform = stored if placement is None else placement.transform(Mesh(read.skin.vertices, read.skin.faces))
    skin = read.skin if np.allclose(transform, np.eye(4)) else transformed_skin(read.skin, transform)
    model_joints = collider.info.skeleton.get("joints", [])
    if skin.skeleton.joint_count != len(model_joints) or len(skin.vertices) != len(collider.skin.vertices):
        raise ValueError(f"{args.mesh}: {skin.skeleton.joint_count} joints and {len(skin.vertices):,} vertices, "
                         f"but {collider.info.name} has {len(model_joints)} and {len(collider.skin.vertices):,}: "
                         "not the character it was made from")
    differs = report_differences(collider.info, read, transform, args)
    report = evaluate_skinned_collider(collider, skin, points=args.points, times=args.times or 16,
                                       poses=args.poses or 16, seed=args.seed, path=path,
                                       show_progress=not args.quiet)
    return report, differs


def report_differences(info, source, transform, args) -> list[str]:
    """:func:`source_differences`, said on stderr (stdout stays the report alone)."""
    differs = source_differences(info, source, transform, args.mesh, args.animation)
    if differs:
        storing = "not stored" if not args.store_anyway else "stored anyway (--store-anyway)"
        print(f"collider eval: warning: {'; '.join(differs)}: figures {storing}", file=sys.stderr)
    return differs


def check_units(info, args) -> None:
    """``--units`` / ``--meters-per-unit`` of ``eval`` say which unit the placed mesh is in: it
    must be the model's (errors are converted to mm with it); ValueError naming both otherwise."""
    from collider_server.making.placement import meters_per_unit

    if args.units is None and args.meters_per_unit is None:
        return
    given = meters_per_unit(args.units or "m", args.meters_per_unit)
    if abs(given - info.meters_per_unit) > 1e-12 * max(given, info.meters_per_unit):
        raise ValueError(f"--units {args.units or 'm'} ({given:g} m per unit) is not the unit {info.name} was made in "
                         f"({info.units}, {info.meters_per_unit:g} m per unit); give the placement it was made with "
                         f"(`{command('info', info.name, *models_options(args))}` shows it)")


def source_differences(info, mesh, transform: np.ndarray, mesh_arg: str, cache_arg: str | None = None) -> list[str]:
    """Why ``mesh`` (or an animated mesh, its vertex cache given as ``cache_arg``) placed by
    ``transform`` is not the source the model ``info`` was made from (file contents by sha256,
    then placement); empty when it is, or when the model records none."""
    differs = []
    sha = info.source.get("sha256")
    if sha and mesh.sha256 and sha != mesh.sha256:
        differs.append(f"{mesh_arg} is not the mesh {info.name} was made from "
                       f"(sha256 {mesh.sha256[:12]}, model's source {sha[:12]})")
    sha = info.source.get("cache_sha256")
    if cache_arg is not None and sha and mesh.cache_sha256 and sha != mesh.cache_sha256:
        differs.append(f"{cache_arg} is not the vertex cache {info.name} was made from "
                       f"(sha256 {mesh.cache_sha256[:12]}, model's source {sha[:12]})")
    stored = np.asarray(info.source.get("transform", np.eye(4)), dtype=np.float64)
    if not np.allclose(transform, stored, rtol=1e-9, atol=1e-12):
        differs.append(f"the mesh placement differs from {info.name}'s (transform "
                       f"{np.round(transform, 6).tolist()}, model's {np.round(stored, 6).tolist()})")
    return differs
