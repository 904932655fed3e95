"""``collider animate NAME``: write one of the project's generated animations (OBJ + PC2), and
optionally bake it into animated colliders (:mod:`collider_server.making.animations`); the walker
also as a skinned glTF character (:mod:`collider_server.making.walker`), baked as kind
``skinned``."""

from __future__ import annotations

import inspect
from pathlib import Path

from .options import add_device_argument, add_models_argument, add_quiet_argument


def register(subparsers) -> None:
    from collider_server.making.animations import GENERATED

    listed = "; ".join(f"{name}: {what}" for name, what in GENERATED.items())
    p = subparsers.add_parser(
        "animate", help="write a generated animation (OBJ + PC2) and bake it",
        description=f"Write NAME.obj and NAME.pc2 (metres, z up) into --output. {listed}. "
                    "With --bake, also bake them into the model repository (kind mesh: model "
                    "NAME; kind voxel: model NAME-voxel; kind skinned, the walker only: model "
                    "NAME-skinned from NAME.glb, z up like the others).")
    p.add_argument("name", choices=sorted(GENERATED), help="which animation")
    p.add_argument("--output", type=Path, default=Path("out/animations"),
                   help="folder of NAME.obj and NAME.pc2 (default out/animations)")
    p.add_argument("--mesh", type=Path, default=None,
                   help="twisting-bunny: the bunny OBJ (default examples/meshes/stanford-bunny.obj); spot-bend: "
                        "the spot OBJ (default examples/meshes/spot.obj); under the working folder, else the "
                        "source checkout's")
    p.add_argument("--frames", type=int, default=None,
                   help="frames over the same motion and duration (default: as above; e.g. "
                        "twisting-bunny --frames 61 is 61 frames at 30 fps over its 2 s)")
    p.add_argument("--bake", default=None, metavar="KINDS",
                   help="also bake: some of mesh, voxel (and skinned for the walker), e.g. mesh,voxel")
    p.add_argument("--resolution", type=int, default=128, help="voxel samples per axis (default 128)")
    p.add_argument("--keyframes", type=int, default=None,
                   help="voxel grids over the animation (default: one per frame)")
    add_models_argument(p, "where --bake writes")
    add_device_argument(p)
    add_quiet_argument(p)
    p.set_defaults(func=run_animate)


#: The mesh file each generated animation of a mesh reads when ``--mesh`` is not given: under the
#: working directory, else under the source checkout (:func:`default_mesh`).
MESHES = {"twisting-bunny": Path("examples/meshes/stanford-bunny.obj"), "spot-bend": Path("examples/meshes/spot.obj")}


def default_mesh(name: str) -> Path:
    """:data:`MESHES`' file of ``name`` under the working directory if it is there, else the
    source checkout's (an editable install run from another folder), else the relative path (its
    reader then says it is missing)."""
    from collider_server.engine.repository import CHECKOUT

    local = MESHES[name]
    if local.is_file() or not (CHECKOUT / local).is_file():
        return local
    return CHECKOUT / local


def make_animation(name: str, mesh: Path | None = None, frames: int | None = None):
    """The generated animation ``name`` (:data:`~collider_server.making.animations.GENERATED`),
    with ``frames`` frames over its duration when given (the frame rate follows); ``mesh``: the
    file of an animation of a mesh (default :data:`MESHES`')."""
    from collider_server.making import animations
    from collider_server.making.animation_files import read_obj

    if name == "walker":
        from collider_server.making.walker import make_walker, walk_animation

        return walk_animation(make_walker(), frames)
    function = {"arm": animations.bending_arm, "pulsing-sphere": animations.pulsing_sphere,
                "twisting-bunny": animations.twisting_bunny, "spot-bend": animations.bending_spot}[name]
    timing = {}
    if frames is not None:
        # The generator's own duration: its default frames and rate.
        defaults = inspect.signature(function).parameters
        duration_s = (defaults["frames"].default - 1) / defaults["fps"].default
        timing = {"frames": frames, "fps": (frames - 1) / duration_s}
    if name in MESHES:
        return function(read_obj(mesh or default_mesh(name)), **timing)
    made = function(**timing)
    return made[0] if name == "pulsing-sphere" else made


def run_animate(args) -> int:
    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.animation_files import load_animation, write_animation
    from collider_server.making.bake import ANIMATED_KINDS, bake_animated_collider

    if args.frames is not None and args.frames < 2:
        raise ValueError(f"--frames must be an integer >= 2, got {args.frames}")
    kinds = [] if args.bake is None else [k.strip() for k in args.bake.split(",") if k.strip()]
    bakeable = list(ANIMATED_KINDS) + (["skinned"] if args.name == "walker" else [])
    unknown = sorted(set(kinds) - set(bakeable))
    if unknown or (args.bake is not None and not kinds):
        raise ValueError(f"--bake takes some of {bakeable} for {args.name}, got {args.bake!r}")
    repository = ModelRepository(args.models)
    if kinds:
        repository.check_writable()
    animation = make_animation(args.name, args.mesh, args.frames)
    timeline = animation.timeline
    obj, pc2 = write_animation(animation, args.output, args.name)
    ends = "looping" if timeline.loop else "clamped"
    print(f"wrote {obj} and {pc2}: {timeline.frames} frames at {timeline.frame_rate_hz:g} fps "
          f"({timeline.duration_s:g} s, {ends}), {animation.vertex_count:,} vertices, metres")
    if args.name == "walker":
        character = write_walker_character(args.output)
    if "skinned" in kinds:
        bake_walker_skinned(character, repository, f"{args.name}-skinned")
        kinds.remove("skinned")
    # Baked from the files just written, as `collider bake` would: the model records them.
    written = load_animation(obj, pc2, timeline.frame_rate_hz, timeline.loop)
    for kind in kinds:
        name = args.name if kind == "mesh" else f"{args.name}-voxel"
        collider = bake_animated_collider(written, kind, name, resolution=args.resolution,
                                          keyframes=args.keyframes, device=args.device,
                                          show_progress=not args.quiet)
        path = save_collider(collider, repository.path(name))
        print(f"wrote {path} ({path.stat().st_size:,} bytes, kind {kind}, animated); the same as: "
              f"collider bake {obj} --animation {pc2} --fps {timeline.frame_rate_hz:g} "
              f"--{'loop' if timeline.loop else 'clamp'} "
              f"--kind {kind} --name {name}"
              + (f" --resolution {args.resolution}" + (f" --keyframes {args.keyframes}"
                                                       if args.keyframes else "")
                 if kind == "voxel" else ""))
    return 0


def write_walker_character(folder: Path) -> Path:
    """``folder/walker.glb``: the walker as a skinned glTF character (metres, Y up), its body cut
    into a left and a right primitive (a seam down the middle the reader welds)."""
    import numpy as np

    from collider_server.making.gltf_writer import write_gltf
    from collider_server.making.walker import make_walker

    skin = make_walker().skin()
    centres = skin.vertices[skin.faces].mean(axis=1)[:, 0]
    path = write_gltf(skin, Path(folder) / "walker.glb", name="walker",
                      parts=[np.flatnonzero(centres >= 0), np.flatnonzero(centres < 0)])
    clips = ", ".join(f"{c.name} ({c.duration_s:g} s)" for c in skin.clips)
    print(f"wrote {path} ({path.stat().st_size:,} bytes): the skinned character, "
          f"{skin.skeleton.joint_count} joints, clips {clips}, metres, Y up")
    return path


def bake_walker_skinned(character: Path, repository, name: str) -> None:
    """The ``skinned`` model ``name`` of ``character``, z up like the walk's OBJ + PC2."""
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.characters import skinned_from_file
    from collider_server.making.placement import MeshPlacement

    collider, _, _ = skinned_from_file(character, name, MeshPlacement(z_up=True), loop=True)
    path = save_collider(collider, repository.path(name))
    print(f"wrote {path} ({path.stat().st_size:,} bytes, kind skinned); the same as: collider bake "
          f"{character} --kind skinned --z-up --loop --name {name}")
