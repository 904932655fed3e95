"""``collider bake``, ``collider query`` and ``collider info``."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from collider_contract import FIELDS

from .budget import add_budget_arguments, budget_from_args
from .diagnostics import print_mesh_check, sign_check_line
from .options import (
    add_animation_arguments,
    add_cache_argument,
    add_device_argument,
    add_models_argument,
    add_placement_arguments,
    add_quiet_argument,
    check_animation_arguments,
    load_placed_animation,
    placement_from_args,
)


def register(subparsers) -> None:
    bake = subparsers.add_parser(
        "bake", help="make a voxel, mesh or kdtree collider from a mesh (or an animated one), "
                     "or a skinned one from a character",
        description="Make a collider from MESH. With --animation, an animated collider of MESH's "
                    "frames: kind mesh (exact at any time) or voxel (one grid per keyframe); "
                    "between frames the surface is the linear interpolation of the vertices. "
                    "With --kind skinned, MESH is a character (glTF 2.0 .gltf/.glb, or USD with "
                    "UsdSkel): its skin, skeleton and clips, answered exactly at any clip time or "
                    "joint pose (--loop: a clip's time wraps beyond its ends, else clamps).")
    bake.add_argument("mesh", help="mesh file (OBJ, PLY, STL, OFF, GLB; an OBJ or a USD stage "
                                   "with --animation; a .gltf/.glb/.usd character with --kind "
                                   "skinned)")
    bake.add_argument("--kind", choices=["voxel", "mesh", "kdtree", "skinned"], default="voxel")
    bake.add_argument("--name", required=True, help="model name (file NAME.safetensors)")
    bake.add_argument("--resolution", type=int, default=None,
                      help="voxel samples per axis (8..1024; default 256, 128 with --animation)")
    bake.add_argument("--padding", type=float, default=0.1, help="domain padding, fraction of the largest side")
    add_animation_arguments(bake, "voxel: grids evenly spaced from the first frame to the last "
                                  "(default: one per frame)")
    add_placement_arguments(bake)
    add_models_argument(bake, "where the model is written")
    add_device_argument(bake)
    add_quiet_argument(bake)
    add_budget_arguments(bake)
    add_cache_argument(bake)
    bake.set_defaults(func=run_bake)

    query = subparsers.add_parser("query", help="distance/normal/contact of points")
    query.add_argument("model", help="model name in the repository, or a .safetensors path")
    query.add_argument("coords", nargs="*", type=float, help="x y z [x y z ...], world frame")
    query.add_argument("--points", type=Path, help=".npy file of (n, 3) points instead")
    query.add_argument("--fields", default="distance,normal,contact,collides",
                       help=f"comma-separated subset of {','.join(FIELDS)}")
    query.add_argument("--eps", type=float, default=None, help="collision offset (default 1 mm)")
    query.add_argument("--time", type=float, default=None,
                       help="seconds: when an animated model is asked (required for one)")
    query.add_argument("--pose", type=Path, default=None, help=".npy or .json 4x4 pose, collider to world")
    query.add_argument("--clip", default=None,
                       help="a skinned model's clip, asked at --time (default: its first clip)")
    query.add_argument("--joint-transforms", type=Path, default=None,
                       help="a skinned model's pose instead of a clip: .npy or .json (J, 4, 4), "
                            "the joints' world transforms in the collider frame")
    query.add_argument("--joint-velocities", type=Path, default=None,
                       help=".npy or .json (J, 4, 4): the joint transforms' time derivatives, for "
                            "the velocity field (default: a still skeleton)")
    query.add_argument("--only-colliding", action="store_true",
                       help="normal and contact only for colliding points (others: normal 0, "
                            "contact = the point)")
    query.add_argument("--output", type=Path, default=None, help="write the fields to this .npz")
    add_models_argument(query)
    add_device_argument(query)
    query.set_defaults(func=run_query)

    info = subparsers.add_parser("info", help="what a model is: kind, size, domain, accuracy")
    info.add_argument("model", nargs="?", help="model name or path; omit to list the repository")
    add_models_argument(info)
    info.add_argument("--json", action="store_true", help="print the metadata as JSON")
    info.set_defaults(func=run_info)


def run_bake(args) -> int:
    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.repository import ModelRepository, check_name
    from collider_server.making.bake import bake_collider, check_bake_settings
    from collider_server.making.mesh_files import load_mesh

    check_name(args.name)
    budget = budget_from_args(args)
    if args.kind == "skinned" and budget is None:
        return run_bake_skinned(args)
    check_animation_arguments(args)
    if budget is not None:  # an error budget: bake picks the kind (commands.budget)
        if args.animation is not None:
            raise ValueError("--max-error picks among static colliders; bake an --animation with "
                             "--kind mesh or voxel")
        from .budget import run_budget_bake

        return run_budget_bake(args, budget)
    if args.cache is not None:
        raise ValueError("--cache is where the budget bake (--max-error) keeps what it measures; a plain "
                         "bake keeps nothing but the model")
    if args.animation is not None:
        return run_bake_animation(args)
    resolution = args.resolution or 256
    check_bake_settings(args.kind, resolution, args.padding)  # before the mesh check and the estimate
    placement = placement_from_args(args)
    mesh, transform = placement.apply(load_mesh(args.mesh))
    repository = ModelRepository(args.models)
    repository.check_writable()  # before the bake, not after
    check = print_mesh_check(mesh)
    if args.kind == "voxel":
        print(bake_estimate(mesh, resolution), file=sys.stderr, flush=True)
    collider = bake_collider(
        mesh, args.kind, args.name, resolution=resolution, padding=args.padding,
        units=placement.units, meters_per_unit=placement.meters_per_unit,
        device=args.device, show_progress=not args.quiet,
    )
    collider.info.source["transform"] = transform.tolist()
    collider.info.source["check"] = check.to_dict()
    collider.info.source["path"] = str(Path(args.mesh).resolve())
    path = save_collider(collider, repository.path(args.name))
    print(f"wrote {path} ({path.stat().st_size:,} bytes, kind {args.kind})")
    print(sign_check_line(collider, mesh, check))
    from .hints import command, models_options

    print("next: " + command("eval", args.name, "--mesh", args.mesh, *models_options(args)))
    return 0


def bake_estimate(mesh, resolution: int) -> str:
    """How long a voxel bake will take: resolution^3 exact distances at the rate measured now on
    slabs of that grid (:func:`~collider_server.making.bake.exact_seconds_per_point`)."""
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.bake import exact_seconds_per_point, padded_box
    from collider_server.making.progress import format_duration

    per_point = exact_seconds_per_point(ExactSDF(mesh), *padded_box(mesh, 0.1), resolution)
    return (f"bake voxel {resolution}^3: {resolution ** 3:,} exact distances, about "
            f"{format_duration(resolution ** 3 * per_point)} ({per_point * 1e6:.1f} us per point measured here)")


def run_bake_animation(args) -> int:
    """``collider bake MESH --animation CACHE --fps F``: an animated mesh or voxel collider."""
    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.bake import ANIMATED_KINDS, bake_animated_collider
    from collider_server.making.mesh_check import check_animation

    if args.kind not in ANIMATED_KINDS:
        raise ValueError(f"--kind {args.kind} cannot be animated; use one of {list(ANIMATED_KINDS)}")
    if args.kind == "mesh" and (args.keyframes is not None or args.resolution is not None):
        raise ValueError("--keyframes and --resolution are voxel settings (kind mesh is exact)")
    placement = placement_from_args(args)
    animation, transform = load_placed_animation(args, placement)
    repository = ModelRepository(args.models)
    repository.check_writable()  # before the bake, not after
    check = check_animation(animation)
    for line in check.lines():
        print(line)
    if args.kind == "voxel":  # said before the bake: the keyframes that would hold it
        from collider_server.making.keyframe_check import check_keyframes

        thin = check_keyframes(animation, args.keyframes or animation.timeline.frames)
        if not thin.holds:
            print(thin.warning(placement.meters_per_unit), file=sys.stderr, flush=True)
    collider = bake_animated_collider(
        animation, args.kind, args.name, resolution=args.resolution or 128,
        keyframes=args.keyframes, padding=args.padding, units=placement.units,
        meters_per_unit=placement.meters_per_unit, device=args.device,
        show_progress=not args.quiet)
    collider.info.source["transform"] = transform.tolist()
    collider.info.source["check"] = check.to_dict()
    path = save_collider(collider, repository.path(args.name))
    print(f"wrote {path} ({path.stat().st_size:,} bytes, kind {args.kind}, animated: "
          f"{describe_animation(collider.info.animation)})")
    from .hints import command, models_options

    print("next: " + command("eval", args.name, "--mesh", args.mesh, "--animation", args.animation,
                             *models_options(args)))
    return 0


def run_bake_skinned(args) -> int:
    """``collider bake CHARACTER --kind skinned``: the exact skinned collider of a character."""
    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.characters import skinned_from_file
    from collider_server.making.mesh_check import MeshCheck

    if args.animation is not None or args.fps is not None or args.keyframes is not None:
        raise ValueError("--animation, --fps and --keyframes are for vertex caches; a skinned "
                         "character brings its own clips")
    if args.resolution is not None or args.cache is not None:
        raise ValueError("--resolution and --cache are voxel and budget settings (kind skinned is exact)")
    placement = placement_from_args(args)
    repository = ModelRepository(args.models)
    repository.check_writable()  # before the bake, not after
    collider, read, _ = skinned_from_file(args.mesh, args.name, placement, loop=args.loop,
                                          padding=args.padding)
    for note in read.notes:
        print(f"{args.mesh}: {note}")
    for line in MeshCheck.from_dict(collider.info.source["check"]).lines():
        print(line)
    path = save_collider(collider, repository.path(args.name))
    skeleton = collider.info.skeleton
    print(f"wrote {path} ({path.stat().st_size:,} bytes, kind skinned: "
          f"{len(skeleton['joints'])} joints, {describe_clips(skeleton)})")
    return 0


def describe_clips(skeleton: dict, channels: list | None = None) -> str:
    """``2 clips (walk 1 s, wave 2 s), which loop``; with ``channels`` (the model's
    ``settings["channels"]`` layout) each clip's channel count too."""
    clips = skeleton.get("clips", [])
    if not clips:
        return "no clips (asked by joint transforms only)"
    counts = [sum(1 for c in channels or [] if c[0] == i) for i in range(len(clips))]
    listed = ", ".join(f"{c['name']} {c['duration_s']:g} s"
                       + (f" ({counts[i]} channels)" if channels is not None else "")
                       for i, c in enumerate(clips))
    ends = "loop (the time wraps around)" if skeleton.get("loop") else "clamp (hold their ends)"
    return f"{len(clips)} clip(s): {listed}; they {ends}"


def skeleton_lines(skeleton: dict) -> list[str]:
    """The joints as an indented tree, one line each (``pelvis``, ``  spine``, ...)."""
    names, parents = skeleton.get("joints", []), skeleton.get("parents", [])
    depth = []
    for parent in parents:
        depth.append(0 if parent < 0 else depth[parent] + 1)
    return [f"{'  ' * d}{name}" for name, d in zip(names, depth, strict=True)]


def describe_animation(animation: dict) -> str:
    """One line: frames, rate, duration and what happens beyond the ends."""
    ends = "loops (the time wraps around)" if animation["loop"] else "clamps (holds the end frames)"
    return (f"{animation['frames']} frames at {animation['frame_rate_hz']:g} fps, "
            f"{animation['duration_s']:g} s, {ends}")


def load_points(args) -> np.ndarray:
    if args.points is not None:
        if args.coords:
            raise ValueError("give either coordinates or --points, not both")
        try:
            return np.load(args.points, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{args.points}: cannot read points ({exc})") from None
    if not args.coords or len(args.coords) % 3:
        raise ValueError(f"give x y z triples (got {len(args.coords)} numbers) or --points FILE.npy")
    return np.asarray(args.coords, dtype=np.float64).reshape(-1, 3)


def load_pose(path: Path | None, what: str = "pose"):
    """The array in ``path`` (.json nested lists, else .npy), or None; a ValueError naming the
    file and ``what`` it should hold. (The query validates its shape and values.)"""
    if path is None:
        return None
    try:
        if path.suffix == ".json":
            return np.asarray(json.loads(path.read_text()), dtype=np.float64)
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read {what} ({exc})") from None


def run_query(args) -> int:
    from collider_server.engine.repository import ModelRepository

    fields = [f.strip() for f in args.fields.split(",") if f.strip()]
    points = load_points(args)
    collider = ModelRepository(args.models).load(args.model, args.device)
    result = collider.query(points, fields, pose=load_pose(args.pose), eps=args.eps,
                            only_colliding=args.only_colliding, time=args.time, clip=args.clip,
                            joint_transforms=load_pose(args.joint_transforms, "joint transforms"),
                            joint_velocities=load_pose(args.joint_velocities, "joint velocities"))
    values = result.fields()
    if args.output is not None:
        # np.savez appends ".npz" when it is missing; report the file it really writes.
        output = args.output if args.output.suffix == ".npz" else args.output.with_name(args.output.name + ".npz")
        np.savez(output, **values)
        print(f"wrote {output} ({len(points)} points)")
        return 0
    units = collider.info.units
    np.set_printoptions(precision=6, suppress=True)
    for i in range(len(points)):
        parts = [f"point {points[i].tolist()}"]
        for name, array in values.items():
            value = array[i].tolist() if array.ndim > 1 else array[i].item()
            unit = f" {units}" if name == "distance" else ""
            parts.append(f"{name}={value}{unit}")
        print("  ".join(parts))
    return 0


def finite_json(value, where: str = ""):
    """``value`` with every non-finite float replaced by None, and the paths of those replaced."""
    if isinstance(value, float) and not np.isfinite(value):
        return None, [where or "value"]
    if isinstance(value, dict):
        pairs = [(k, finite_json(v, f"{where}.{k}" if where else str(k))) for k, v in value.items()]
        return {k: v for k, (v, _) in pairs}, [b for _, (_, bad) in pairs for b in bad]
    if isinstance(value, (list, tuple)):
        items = [finite_json(v, f"{where}[{i}]") for i, v in enumerate(value)]
        return [v for v, _ in items], [b for _, bad in items for b in bad]
    return value, []


def run_info(args) -> int:
    from collider_server.engine.modelfile import read_info
    from collider_server.engine.repository import ModelRepository

    repo = ModelRepository(args.models)
    if args.model is None:
        names = repo.names()
        print(f"{repo.root}: {len(names)} model(s)")
        for name in names:
            size = repo.path(name).stat().st_size
            try:
                listed = read_info(repo.path(name))
                kind = listed.kind + (", animated" if listed.animation else "")
            except ValueError as exc:  # one damaged file must not hide the others
                kind = f"unreadable: {getattr(exc, 'problem', exc)}"
            print(f"  {name:<20} {size:>12,} bytes  {kind}")
        return 0
    path = repo.resolve(args.model)
    info = read_info(path)
    size = path.stat().st_size
    if args.json:
        # Strict JSON: a NaN or infinity stored by an older version becomes null (and is named).
        data, bad = finite_json({"path": str(path), "bytes": size, **info.to_dict()})
        for where in bad:
            print(f"collider info: warning: {where} is not a finite number; written as null",
                  file=sys.stderr)
        json.dump(data, sys.stdout, indent=2, allow_nan=False)
        print()
        return 0
    print(f"{info.name}  ({path}, {size:,} bytes)")
    print(f"  kind        {info.kind}{'  (approximate)' if info.approximate else ''}")
    print(f"  units       {info.units} ({info.meters_per_unit} m per unit), collider frame")
    print(f"  domain      {np.round(info.domain_min, 6).tolist()} .. {np.round(info.domain_max, 6).tolist()}")
    if info.animation:
        print(f"  animation   {describe_animation(info.animation)}; surface speed at most "
              f"{info.animation.get('max_surface_speed', 0.0):.4g} {info.units}/s")
    elif info.skeleton:
        print(f"  clips       {describe_clips(info.skeleton, info.settings.get('channels'))}")
        print(f"  skeleton    {len(info.skeleton['joints'])} joints (parents above children):")
        for line in skeleton_lines(info.skeleton):
            print(f"                {line}")
    else:
        print("  animation   none (static)")
    source = info.source
    if source:
        print(f"  source      {source.get('mesh')} sha256 {str(source.get('sha256', ''))[:16]} "
              f"({source.get('faces', '?')} faces)" + (f", {source['path']}" if source.get("path") else ""))
        if source.get("cache"):
            print(f"  cache       {source['cache']} sha256 {str(source.get('cache_sha256', ''))[:16]} "
                  f"({source.get('frames', '?')} frames at {source.get('frame_rate_hz', '?')} fps)")
            if "cache_start_frame" in source:
                print(f"  pc2 header  start frame {source['cache_start_frame']:g}, sample rate "
                      f"{source['cache_sample_rate']:g} (recorded, not applied: sample k plays at k / fps s)")
    print_source_check(source, info.accuracy)
    for note in source.get("notes", []):
        print(f"  read        {note}")
    for key, value in info.settings.items():
        if key != "channels":  # a skinned model's channel layout: counted per clip above
            print(f"  {key:<11} {value}")
    if info.accuracy:
        print(f"  accuracy    as `collider eval` measured it ({info.accuracy.get('evaluated', 'when: not recorded')})")
        for line in accuracy_lines(info):
            print(f"    {line}")
    else:
        print("  accuracy    not evaluated; " + eval_hint(info, path, args))
    return 0


def accuracy_lines(info) -> list[str]:
    """A model's stored evaluation as ``collider eval`` prints it (its table), less the model
    file's size: the report measured the file before the figures were stored in it (the true
    size heads ``collider info``). A report of another form is listed key by key."""
    from collider_server.making.evaluation import format_report

    report = {key: value for key, value in info.accuracy.items() if key != "file_bytes"}
    try:
        return format_report(info.name, info.kind, report).splitlines()[1:]
    except (KeyError, TypeError, ValueError):  # stored by another version: shown as it is
        return [f"{key}: {value}" for key, value in report.items()]


def print_source_check(source: dict, accuracy: dict | None) -> None:
    """The mesh check recorded when the model was made, and the measured sign errors."""
    from collider_server.making.mesh_check import MeshCheck

    if not source.get("check"):
        print("  mesh check  not recorded (made before models recorded it; `collider bake`, `train` and "
              "`bench` print it for a mesh file)")
        return
    lines = MeshCheck.from_dict(source["check"]).lines()
    print(f"  {lines[0]}")
    for line in lines[1:]:
        print(f"  {line}")
    band = (accuracy or {}).get("band_1mm")
    if band:
        print(f"  sign errors {band['sign_errors_percent']:.3f} % of the +-1 mm band points farther than 0.2 mm "
              "from the surface (the stored evaluation)")


def eval_hint(info, path, args) -> str:
    """How to evaluate the model: a pasteable ``collider eval`` when its mesh file is known and
    unchanged, else which mesh it needs."""
    from collider_server.making.mesh_files import file_sha256

    from .hints import command, models_options

    if info.skeleton:
        return (f"`collider eval {info.name} --mesh CHARACTER` measures it at random clip times and random "
                f"poses against its character file ({info.source.get('path') or info.source.get('mesh', '?')})")
    if info.animation:
        return (f"`collider eval {info.name} --mesh OBJ --animation CACHE` measures it at random times "
                f"against the frames it was made from ({info.source.get('mesh', '?')}.obj and "
                f"{info.source.get('cache', '?')})")
    mesh = info.source.get("path")
    if mesh and Path(mesh).is_file() and file_sha256(Path(mesh)) == info.source.get("sha256"):
        model = args.model if Path(args.model).name != args.model or args.model.endswith(".safetensors") else info.name
        return f"`{command('eval', model, '--mesh', mesh, *models_options(args))}` measures it"
    return (f"`collider eval` measures it against the mesh it was made from ({info.source.get('mesh', '?')}, "
            f"sha256 {str(info.source.get('sha256', ''))[:16]})")
