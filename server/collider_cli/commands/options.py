"""Command-line options shared by several ``collider`` commands.

- :func:`finite_float`: the argparse type that refuses ``nan`` and ``inf``; :func:`require_finite`
  puts it on every float option of every command (``collider`` applies it once, in
  :func:`collider_cli.main.build_parser`, so options added later are covered too).
- :func:`add_models_argument`, :func:`add_device_argument`, :func:`add_quiet_argument`: the
  options that name the model repository, the torch device and the progress bar, declared once;
- :func:`add_placement_arguments` / :func:`placement_from_args` / :func:`load_placed_mesh`: the
  mesh placement options (``--scale``, ``--fit-size``, ``--z-up``, ``--units``,
  ``--meters-per-unit``) of every command that reads a mesh, applied with
  :class:`collider_server.making.placement.MeshPlacement`;
- :func:`add_cache_argument` / :func:`cache_dir` / :func:`cache_size_line`: the one cache folder
  of ``bench`` and the budget bake (``--cache``, default under the user's cache directory).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from collider_server.making.placement import MeshPlacement


def finite_float(text: str) -> float:
    """argparse type: a float that is neither NaN nor infinite."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def require_finite(parser: argparse.ArgumentParser) -> None:
    """Give every ``type=float`` option of ``parser`` and its subcommands :func:`finite_float`."""
    for action in parser._actions:
        if action.type is float:
            action.type = finite_float
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                require_finite(sub)


MODELS_HELP = ("model repository folder (default: $COLLIDER_MODELS, else ./models, else the shipped "
               "models)")
DEVICE_HELP = "torch device: cpu, cuda, cuda:N or auto (default auto: CUDA when present, else cpu)"


def add_models_argument(parser, purpose: str = "") -> None:
    """``--models DIR``, the model repository (None: :func:`~collider_server.engine.repository.
    default_models_dir`); ``purpose`` says what the command reads it for."""
    parser.add_argument("--models", type=Path, default=None, metavar="DIR",
                        help=f"{purpose}: {MODELS_HELP}" if purpose else MODELS_HELP)


def add_device_argument(parser, help: str = DEVICE_HELP) -> None:
    """``--device``: where the engine runs (None: CUDA when present, else the CPU)."""
    parser.add_argument("--device", default=None, help=help)


def add_quiet_argument(parser) -> None:
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def add_placement_arguments(parser: argparse.ArgumentParser, *, units: bool = True,
                            as_stored: bool = False) -> None:
    """Add the mesh placement options to ``parser`` (as a group "mesh placement").

    units : also add ``--units`` and ``--meters-per-unit`` (commands that make a collider)
    as_stored : the defaults are None, meaning "as the model was made" (``eval`` and others that
        read a mesh for an existing model); :func:`placement_from_args` then returns None unless
        an option was given.
    """
    group = parser.add_argument_group(
        "mesh placement", "applied to the mesh file's coordinates: --z-up first, then the scale"
        + (" (default: as the model was made)" if as_stored else ""))
    group.add_argument("--scale", type=finite_float, default=None if as_stored else 1.0,
                       help="multiply mesh coordinates by this" + ("" if as_stored else " (default 1)"))
    group.add_argument("--fit-size", type=finite_float, default=None,
                       help="instead of --scale: scale so the largest side is this long (in --units)")
    group.add_argument("--z-up", action="store_true", default=None if as_stored else False,
                       help="rotate a Y-up mesh to Z-up (the paper's frame)")
    if units:
        group.add_argument("--units", default=None if as_stored else "m",
                           help="length unit of the placed mesh, e.g. m, mm (default "
                                + ("the model's)" if as_stored else "m)"))
        group.add_argument("--meters-per-unit", type=finite_float, default=None,
                           help="metres in one unit (derived from --units for m, cm, mm, um, km, in, ft)")


def placement_from_args(args: argparse.Namespace) -> MeshPlacement | None:
    """The :class:`MeshPlacement` the options describe, checked (ValueError naming the option).

    With ``as_stored`` options and none given, None (use the model's stored transform)."""
    if args.scale is None and args.fit_size is None and not args.z_up:
        return None
    if args.scale is not None and args.fit_size is not None and args.scale != 1.0:
        raise ValueError("give --scale or --fit-size, not both")
    placement = MeshPlacement(
        scale=1.0 if args.scale is None else args.scale, fit_size=args.fit_size, z_up=bool(args.z_up),
        units=getattr(args, "units", None) or "m", meters_per_unit_override=getattr(args, "meters_per_unit", None))
    placement.check()
    return placement


def load_placed_mesh(args: argparse.Namespace):
    """(mesh in the collider frame, 4x4 transform applied, units, metres per unit) of
    ``args.mesh`` under the placement options."""
    from collider_server.making.mesh_files import load_mesh

    placement = placement_from_args(args)
    mesh, transform = placement.apply(load_mesh(args.mesh))
    return mesh, transform, placement.units, placement.meters_per_unit


# -- the cache of bench and the budget bake -------------------------------------------------------

CACHE_HELP = ("cache folder of baked grids, bench-trained networks and the budget bake's measured "
              "figures (default: $XDG_CACHE_HOME/neural-collider, else ~/.cache/neural-collider); "
              "its size is printed after each run, delete it to free the space")


def add_animation_arguments(parser: argparse.ArgumentParser, keyframes_help: str) -> None:
    """``--animation CACHE --fps F [--loop | --clamp] [--keyframes K]`` (bake and train)."""
    animation = parser.add_argument_group(
        "animation", "frame k is at k / FPS seconds; the animation lasts (frames - 1) / FPS")
    animation.add_argument("--animation", default=None, metavar="CACHE",
                           help="MESH's frames: a PC2 vertex cache (FILE.pc2, as `collider simulate` "
                                "and Blender write), or a quoted pattern of OBJ files with MESH's "
                                "faces ('frames/*.obj', ordered by the number in their names); "
                                "for a USD stage MESH (.usd, .usda, .usdc), MESH itself: its "
                                "meshes' time-sampled points")
    animation.add_argument("--fps", type=float, default=None,
                           help="frames per second of --animation (required with it)")
    ends = animation.add_mutually_exclusive_group()
    ends.add_argument("--loop", dest="loop", action="store_true", default=False,
                      help="beyond the ends the time wraps around (the last frame should be the first)")
    ends.add_argument("--clamp", dest="loop", action="store_false",
                      help="beyond the ends the first or last frame is held (the default)")
    animation.add_argument("--keyframes", type=int, default=None, help=keyframes_help)


def check_animation_arguments(args: argparse.Namespace) -> None:
    """The animation options need ``--animation``, and ``--animation`` needs ``--fps``
    (ValueError naming the option)."""
    from collider_server.making.animation_files import check_frame_rate

    if args.animation is None:
        if args.fps is not None or args.keyframes is not None or args.loop:
            raise ValueError("--fps, --keyframes and --loop/--clamp need --animation")
        return
    if args.fps is None:
        raise ValueError("--animation needs --fps (frames per second: a vertex cache does not say)")
    check_frame_rate(args.fps)


def load_placed_animation(args: argparse.Namespace, placement: MeshPlacement):
    """MESH's ``--animation`` at ``--fps``, placed: ``(AnimatedMesh, transform)``."""
    from collider_server.making.animation_files import cache_timing_warning, load_animation

    animation = load_animation(args.mesh, args.animation, args.fps, args.loop)
    warning = cache_timing_warning(animation)
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    return placement.apply_to_animation(animation)


def load_animated_source(info, args):
    """The exact animation of the animated model ``info`` (what eval measures it against, what
    view draws): ``--mesh`` OBJ and ``--animation`` CACHE at ``--fps`` (default: the rate the
    model was made at), looping as the model does, in the file's frame; ValueError in one line
    when they are missing or cannot be the model's animation (another frame count or duration)."""
    from collider_contract import Timeline
    from collider_server.making.animation_files import load_animation

    source = info.source
    rate = source.get("frame_rate_hz")
    made_from = (f"{info.name} was made from {source.get('mesh', '?')}.obj and {source.get('cache', '?')}, "
                 f"{source.get('frames', '?')} frames at {'?' if rate is None else f'{rate:g}'} fps")
    if args.animation is None:
        raise ValueError(f"{info.name} is animated: give the frames it was made from, --mesh OBJ "
                         f"--animation CACHE ({made_from})")
    fps = args.fps if args.fps is not None else source.get("frame_rate_hz")
    if fps is None:
        raise ValueError(f"{info.name} does not record its frame rate: give --fps")
    timeline = Timeline.from_dict(info.animation)
    animation = load_animation(args.mesh, args.animation, fps, timeline.loop)
    frames = animation.timeline.frames
    if source.get("frames") is not None and frames != source["frames"]:
        raise ValueError(f"{args.animation}: {frames} frames, but {made_from}")
    duration = animation.timeline.duration_s
    if not math.isclose(duration, timeline.duration_s, rel_tol=1e-9, abs_tol=0.0):
        raise ValueError(f"{args.animation} at {fps:g} fps lasts {duration:g} s, but {info.name}'s animation "
                         f"lasts {timeline.duration_s:g} s ({made_from})")
    return animation


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/neural-collider``, else ``~/.cache/neural-collider`` (the XDG base
    directory rule: the user's cache, not the working folder)."""
    import os

    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "neural-collider"


def add_cache_argument(parser) -> None:
    parser.add_argument("--cache", type=Path, default=None, metavar="DIR", help=CACHE_HELP)


def cache_dir(args: argparse.Namespace) -> Path:
    return args.cache if args.cache is not None else default_cache_dir()


def cache_size_line(cache: Path) -> str:
    """``cache /home/u/.cache/neural-collider: 152.3 MB in 7 files (...)``: its regular files
    (links not counted)."""
    files = [p for p in Path(cache).rglob("*") if p.is_file() and not p.is_symlink()] if Path(cache).is_dir() else []
    size = sum(p.stat().st_size for p in files)
    return (f"cache {cache}: {size / 1e6:.1f} MB in {len(files)} files (grids and networks a next run "
            "reuses; delete the folder to free the space, or pass --cache DIR)")
