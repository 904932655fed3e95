"""``collider view NAME`` (a collider in the browser) and ``collider view --replay out/SCENE``
(a finished cloth run). Needs the ``[view]`` extra (viser); see :mod:`collider_cli.views.collider`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .options import (
    add_device_argument,
    add_models_argument,
    add_placement_arguments,
    add_quiet_argument,
    load_animated_source,
    placement_from_args,
)


def register(subparsers) -> None:
    view = subparsers.add_parser(
        "view", help="look at a collider, or replay a cloth run, in the browser",
        description="Serve an interactive 3D view on http://HOST:PORT/ (extra [view]: "
                    "pip install 'neural-collider[view]'). `collider view NAME --mesh MESH`: the "
                    "collider's surface coloured by its error against the exact mesh (mm), the "
                    "mesh as a wireframe, the domain box, a level slider (eps offset surface), a "
                    "probe. An animated model adds a time slider and play (its exact mesh: "
                    "--mesh OBJ --animation CACHE, the files it was baked from). A skinned model "
                    "shows its skinned mesh and bones, posed by a clip and a time. "
                    "`collider view --replay out/SCENE`: replay a `collider simulate` "
                    "output (OBJ + PC2). Ctrl-C stops it.")
    view.add_argument("model", nargs="?", help="model name in the repository, or a .safetensors path")
    view.add_argument("--mesh", default=None,
                      help="the mesh the collider was made from: colour by error, show as wireframe "
                           "(placed as the model was made unless placement options are given)")
    view.add_argument("--animation", default=None, metavar="CACHE",
                      help="an animated model: the vertex cache (PC2, or a quoted pattern of OBJ "
                           "files) of --mesh it was baked from, as given to `collider bake`")
    view.add_argument("--fps", type=float, default=None,
                      help="frames per second of --animation (default: the rate the model was "
                           "baked at)")
    view.add_argument("--replay", type=Path, default=None, metavar="OUT/SCENE",
                      help="replay a run's output prefix (OBJ + PC2), e.g. out/drape_bunny")
    view.add_argument("--scene", default=None,
                      help="with --replay: the scene file or name, to show its colliders "
                           "(default: the output's name if it is a shipped scene)")
    view.add_argument("--resolution", type=int, default=None,
                      help="marching-cubes grid samples per axis over the domain (default 96; "
                           "64 for an animated model, one grid per time step)")
    view.add_argument("--clip-mm", type=float, default=None,
                      help="error colour scale, +- mm (default: p95 of the surface's |error|)")
    view.add_argument("--up", default=None, choices=["+x", "+y", "+z", "-x", "-y", "-z"],
                      help="up axis of the collider frame in the view (default +z for a model "
                           "placed with --z-up, else +y: the mesh file's Y-up)")
    view.add_argument("--host", default="127.0.0.1",
                      help="address to listen on (default 127.0.0.1; another warns: no authentication)")
    view.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    add_models_argument(view)
    add_device_argument(view)
    add_quiet_argument(view)
    add_placement_arguments(view, units=False, as_stored=True)
    view.set_defaults(func=run_view)


def run_view(args: argparse.Namespace) -> int:
    from ..views.page import require_viser

    if (args.model is None) == (args.replay is None):
        raise ValueError("give a model NAME or --replay OUT/SCENE (one of them)")
    if not 1 <= args.port <= 65535:
        raise ValueError(f"--port must be 1..65535, got {args.port}")
    require_viser()  # before any work: the missing extra is said first
    if args.replay is not None:
        return run_replay(args)
    return run_collider_view(args)


def run_collider_view(args: argparse.Namespace) -> int:
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.mesh_files import load_mesh

    from ..views.collider import serve_collider_view
    from ..views.page import url_of, wait_until_interrupted

    collider = ModelRepository(args.models).load(args.model, args.device)
    info = collider.info
    if collider.skinned:
        return run_skinned_view(args, collider)
    if not collider.animated and (args.animation, args.fps) != (None, None):
        raise ValueError(f"{info.name} is static: --animation and --fps are for animated models")
    if args.animation is not None and args.mesh is None:
        raise ValueError("--animation needs --mesh (the OBJ whose vertices it moves)")
    mesh = None
    stored = np.asarray(info.source.get("transform", np.eye(4)), dtype=np.float64)
    if args.mesh is not None:
        mesh = load_animated_source(info, args) if collider.animated else load_mesh(args.mesh)
        placement = placement_from_args(args)
        if placement is None:  # as the model was made: its stored source transform
            if not np.allclose(stored, np.eye(4)):
                mesh = mesh.transformed(stored)
        elif collider.animated:
            mesh, _ = placement.apply_to_animation(mesh)
        else:
            mesh, _ = placement.apply(mesh)
        for what, arg, key, sha in (("mesh", args.mesh, "sha256", mesh.sha256),
                                    ("vertex cache", args.animation, "cache_sha256",
                                     getattr(mesh, "cache_sha256", ""))):
            made = info.source.get(key)
            if made and sha and made != sha:
                print(f"collider view: warning: {arg} is not the {what} {info.name} was made "
                      "from (sha256 differs)", file=sys.stderr)
    up = args.up or view_up(stored)
    resolution = args.resolution if args.resolution is not None else 64 if collider.animated else 96
    page = serve_collider_view(collider, mesh, host=args.host, port=args.port,
                               resolution=resolution, up=up, clip_mm=args.clip_mm,
                               show_progress=not args.quiet)
    wait_until_interrupted(page.server, f"view of {collider.info.name} at {url_of(page.server)}  "
                                        "(Ctrl-C to stop)")
    return 0


def run_skinned_view(args: argparse.Namespace, collider) -> int:
    """A skinned model: the character posed by a clip and a time (:mod:`..views.skinned`)."""
    from ..views.page import url_of, wait_until_interrupted
    from ..views.skinned import serve_skinned_view

    given = [f"--{name.replace('_', '-')}" for name in ("mesh", "animation", "fps", "resolution", "clip_mm")
             if getattr(args, name) is not None]
    if given:
        raise ValueError(f"{collider.info.name} is skinned: its surface is the skinned mesh itself; "
                         f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} for the other kinds")
    stored = np.asarray(collider.info.source.get("transform", np.eye(4)), dtype=np.float64)
    page = serve_skinned_view(collider, host=args.host, port=args.port, up=args.up or view_up(stored))
    wait_until_interrupted(page.server, f"view of {collider.info.name} at {url_of(page.server)}  "
                                        "(Ctrl-C to stop)")
    return 0


def view_up(transform) -> str:
    """The view's up axis for a model made with the placement ``transform`` (its stored
    ``source["transform"]``): +z when the placement turned a Y-up mesh Z-up (``--z-up``), else +y
    (the mesh file's own Y-up, whatever its scale)."""
    from collider_server.making.placement import MeshPlacement

    return "+z" if MeshPlacement.z_up_of(transform) else "+y"


def run_replay(args: argparse.Namespace) -> int:
    from collider_client import Client
    from collider_client.sim.scene import SCENES_DIR, load_scene, resolve_scene

    from ..views.cloth import serve_replay
    from ..views.page import url_of, wait_until_interrupted

    prefix = args.replay
    if prefix.suffix in (".obj", ".pc2"):
        prefix = prefix.with_suffix("")
    scene = client = infos = None
    if args.scene is not None:
        scene = load_scene(resolve_scene(args.scene))
    elif (SCENES_DIR / f"{prefix.name}.toml").is_file():
        scene = load_scene(SCENES_DIR / f"{prefix.name}.toml")
    try:
        if scene is not None and scene.colliders:
            client = Client(models=args.models, device=args.device)
            infos = {m.name: m for m in client.list_models()}
        page = serve_replay(prefix, args.host, args.port, scene, client, infos)
        wait_until_interrupted(page.server, f"replaying {len(page.frames)} frames of {prefix} at "
                                            f"{url_of(page.server)}  (Ctrl-C to stop)")
    finally:
        if client is not None:
            client.close()
    return 0
