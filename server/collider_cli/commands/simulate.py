"""``collider simulate SCENE``: run a scene file with the reference Verlet cloth simulator."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from collider_client.sim.scene import resolve_scene, shipped_scenes

from .options import DEVICE_HELP, add_device_argument, add_models_argument, add_quiet_argument


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="run a cloth scene (TOML) against the colliders",
        description="Simulate a cloth scene with the reference Verlet simulator. SCENE is a TOML "
                    f"file or a shipped scene name ({', '.join(shipped_scenes())}). Writes "
                    "OBJ + PC2 (Blender: import the OBJ, add a Mesh Cache modifier with the PC2), "
                    "a PNG preview and a report.")
    p.add_argument("scene", help="scene file or shipped scene name")
    p.add_argument("--server", default=None,
                   help="URL of a running `collider serve` (default: the engine in process)")
    p.add_argument("--token", default=None, help="bearer token for --server")
    add_models_argument(p, "embedded engine")
    add_device_argument(p, "embedded engine: " + DEVICE_HELP)
    p.add_argument("--threads", type=int, default=None,
                   help="embedded engine CPU threads (default: cores - 1, at least 1, as the server)")
    p.add_argument("--output", type=Path, default=Path("out"), help="output folder (default out/)")
    p.add_argument("--steps", type=int, default=None, help="simulate only this many steps")
    p.add_argument("--no-preview", action="store_true", help="skip the PNG")
    add_quiet_argument(p)
    p.add_argument("--check-mesh", action="append", default=[], metavar="MODEL=MESH",
                   help="also measure penetration of every output frame against the exact SDF of "
                        "MESH (collider frame) for collider MODEL; for a skinned MODEL, MESH is its "
                        "character file (glTF or USD), skinned in the scene's clip at each frame's "
                        "time (the exact union at that pose); repeatable")
    p.add_argument("--check-animation", action="append", default=[], metavar="MODEL=CACHE",
                   help="with --check-mesh for an animated MODEL: its vertex cache (the PC2 or "
                        "'frames/*.obj' it was baked from): each frame is measured against the "
                        "exact interpolated mesh at that frame's time; repeatable")
    view = p.add_argument_group("live view (extra [view]: pip install 'neural-collider[view]')")
    view.add_argument("--view", action="store_true",
                      help="show the run live in the browser (play / pause / step); the view "
                           "stays up after the run until Ctrl-C")
    view.add_argument("--host", default="127.0.0.1",
                      help="address the view listens on (default 127.0.0.1; another warns: no authentication)")
    view.add_argument("--port", type=int, default=8080, help="port of the view (default 8080)")
    view.add_argument("--paused", action="store_true", help="with --view: start paused")
    p.set_defaults(func=run_simulate)


def estimate_line(stem: str, estimate) -> str:
    """A run's :class:`~collider_client.sim.run.DurationEstimate` in words (one line)."""
    from collider_server.making.progress import format_duration

    text = (f"{stem}: {estimate.steps:,} steps; the first {estimate.measured:,} took "
            f"{1e3 * estimate.per_step_s:.1f} ms each: about {format_duration(estimate.seconds)} at that rate")
    worst = estimate.worst_seconds
    if worst is not None and worst > 1.05 * estimate.seconds:
        text += (f"; about {format_duration(worst)} ({1e3 * estimate.worst_per_step_s:.0f} ms a step) if the whole "
                 f"cloth comes inside the colliders' boxes (a query costs {1e6 * estimate.per_point_s:.2f} us per "
                 "point here; fast vertices that need several queries a step, and a busier machine, add to it; "
                 "the progress bar keeps the estimate up to date)")
    return text


def run_simulate(args: argparse.Namespace) -> int:
    from collider_client import Client, ColliderError
    from collider_client.sim.run import RunInterrupted, run_scene
    from collider_client.sim.scene import load_scene

    scene = load_scene(resolve_scene(args.scene))
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    if args.view:  # a missing extra is said before any work, not after the run
        from ..views.page import require_viser

        require_viser()
    checks = model_files(args.check_mesh, "--check-mesh", "MESH")
    caches = model_files(args.check_animation, "--check-animation", "CACHE")
    # Checked before the run, not reported after it.
    unused = sorted(set(checks) - {c.model for c in scene.colliders})
    if unused:
        raise ValueError(f"--check-mesh names model(s) {unused} that the scene does not use; its "
                         f"colliders: {sorted({c.model for c in scene.colliders}) or 'none'}")
    for model, mesh_path in checks.items():
        if not mesh_path.is_file():
            raise FileNotFoundError(f"--check-mesh {model}={mesh_path}: no such file")
    lone = sorted(set(caches) - set(checks))
    if lone:
        raise ValueError(f"--check-animation {lone[0]}=...: give its mesh too (--check-mesh "
                         f"{lone[0]}=MESH)")
    client = None
    if scene.colliders:
        if args.server:
            client = Client(args.server, token=args.token)
        else:
            import os

            threads = args.threads or max(1, (os.cpu_count() or 2) - 1)
            client = Client(models=args.models, device=args.device, threads=threads)
    placed = placed_meshes(client, checks, caches) if checks else {}
    # The PNG shows each collider's surface (a few thousand points, an animated one's at each
    # panel's time): the exact mesh's where --check-mesh gives one, else the model's own.
    shown = {model: shown_points(mesh, spec) for model, mesh in placed.items()
             for spec in scene.colliders if spec.model == model}
    if not args.no_preview and client is not None:
        shown.update(model_surfaces(client, [spec for spec in scene.colliders if spec.model not in shown]))
    server = None
    crossings = None
    try:
        on_step = None
        if args.view:
            server, on_step = start_live_view(args, scene, client)
        if placed:
            crossings, on_step = crossing_check(scene, placed, on_step)
        report, frames = run_scene(
            scene, client, args.output, show_progress=not args.quiet, steps=args.steps,
            preview=not args.no_preview, backend="remote" if args.server else "embedded",
            collider_points=shown, on_step=on_step,
            on_estimate=lambda e: print(estimate_line(scene.path.stem, e), file=sys.stderr, flush=True))
    except BaseException as exc:  # Ctrl-C or an error mid-run: do not leave the view's port open
        if server is not None:
            server.stop()
        if isinstance(exc, ColliderError):  # a server that is down or refuses: one line
            raise ValueError(str(exc)) from None
        if isinstance(exc, RunInterrupted):  # what the steps that ran made, then the exit status
            print(exc.report.text())
            print(written_line(args, scene) + (" (no exact check of an interrupted run)" if placed else ""))
            raise exc.interrupt from None
        raise
    finally:
        if client is not None:
            client.close()
    if placed:
        import json

        from collider_client.sim.motion import pose_function
        from collider_server.making.evaluation import penetration

        report.exact_check = {
            **penetration(frames, [(spec.model, exact_check(placed[spec.model], spec), pose_function(spec))
                                   for spec in scene.colliders if spec.model in placed]),
            **crossings.result()}
        (args.output / f"{scene.path.stem}.report.json").write_text(
            json.dumps(report.to_dict(), indent=2, default=float))
    print(report.text())
    print(written_line(args, scene))
    if server is not None:
        from ..views.page import url_of, wait_until_interrupted

        wait_until_interrupted(server, f"run finished; the view stays at {url_of(server)} "
                                       "(Ctrl-C to stop)")
    return 0


def written_line(args, scene) -> str:
    stem = scene.path.stem
    written = ".pc2, .report.json" if args.no_preview else ".pc2, .png, .report.json"
    return f"wrote {args.output / (stem + '.obj')}, {written}"


def crossing_check(scene, placed: dict, on_step=None):
    """The per-step half of ``--check-mesh``: a
    :class:`~collider_server.making.evaluation.SurfaceCrossings` of the placed exact meshes, and
    the run's per-step callback that feeds it (after ``on_step``, the live view's, if any).
    Each step it is told how far each collider's surface moved (the hook's bound; without
    collisions, every point is measured every step)."""
    import math

    from collider_client.sim.motion import pose_function
    from collider_server.making.evaluation import SurfaceCrossings

    specs = [(k, spec) for k, spec in enumerate(scene.colliders) if spec.model in placed]
    crossings = SurfaceCrossings([(spec.model, exact_check(placed[spec.model], spec), pose_function(spec))
                                  for _, spec in specs])

    def step(sim, i):
        if on_step is not None:
            on_step(sim, i)
        hook = sim.hook
        if hook is None:
            moves = [math.inf] * len(specs)
        else:
            every = hook.collider_moves([c.pose(sim.t) for c in hook.colliders], sim.t, scene.dt_s)
            moves = [every[k] for k, _ in specs]
        crossings.step(sim.t, sim.vertices, moves)

    return crossings, step


def model_files(items: list[str], option: str, what: str) -> dict[str, Path]:
    """``MODEL=PATH`` options as {model: path}; a malformed one is a ValueError."""
    files = {}
    for item in items:
        model, sep, path = item.partition("=")
        if not sep or not model or not path:
            raise ValueError(f"{option} wants MODEL={what}, got {item!r}")
        files[model] = Path(path)
    return files


def placed_meshes(client, checks: dict[str, Path], caches: dict[str, Path] | None = None) -> dict:
    """Each ``--check-mesh`` file (model name -> path), placed as its model was made (the
    model's ``source.transform``: --scale / --fit-size / --z-up), so that it lies in the collider
    frame like the model: model name -> :class:`~collider_server.engine.meshes.Mesh`, or for an
    animated model (its ``--check-animation`` cache) an
    :class:`~collider_server.engine.animated_meshes.AnimatedMesh` run at its source's frame rate
    and the model's loop, or for a skinned model (its character file) the exact skinned collider
    of that file (:func:`placed_skin`)."""
    import numpy as np

    from collider_client import ColliderError
    from collider_server.making.animation_files import load_animation
    from collider_server.making.mesh_files import load_mesh

    caches = caches or {}
    try:
        infos = {m.name: m for m in client.list_models()}
    except ColliderError as exc:  # a server that is down: one line
        client.close()
        raise ValueError(str(exc)) from None
    placed = {}
    for model, path in checks.items():
        info = infos.get(model)
        transform = np.asarray(info.source.get("transform", np.eye(4)), dtype=np.float64) \
            if info is not None else np.eye(4)
        if info is not None and info.skinned:
            if model in caches:
                raise ValueError(f"--check-animation {model}: the model is skinned; its character file "
                                 f"(--check-mesh {model}=CHARACTER) brings its clips")
            placed[model] = placed_skin(model, path, transform, info)
            continue
        if info is not None and info.animated:
            if model not in caches:
                raise ValueError(f"--check-mesh {model}: the model is animated; give its vertex "
                                 f"cache too (--check-animation {model}=CACHE)")
            mesh = load_animation(path, caches[model], info.source.get("frame_rate_hz", info.timeline.frame_rate_hz),
                                  info.timeline.loop)
        elif model in caches:
            raise ValueError(f"--check-animation {model}: the model is not animated")
        else:
            mesh = load_mesh(path)
        placed[model] = mesh if np.allclose(transform, np.eye(4)) else mesh.transformed(transform)
    return placed


def placed_skin(model: str, path: Path, transform, info):
    """The exact ``skinned`` collider of the character file ``path`` placed by ``transform`` (the
    skinned model ``info``'s: it lies in the collider frame like the model), looping as the model
    does: what ``--check-mesh`` measures a skinned model's frames against. ValueError (one line)
    for a file that is not a character or not the model's (another skeleton or vertex count)."""
    import numpy as np

    from collider_server.making.characters import read_character
    from collider_server.making.placement import transformed_skin
    from collider_server.making.skinned import skinned_collider

    read = read_character(path)
    skin = read.skin if np.allclose(transform, np.eye(4)) else transformed_skin(read.skin, transform)
    joints = len(info.skeleton.get("joints", []))
    if skin.skeleton.joint_count != joints or [c.name for c in skin.clips] != [
            c["name"] for c in info.skeleton.get("clips", [])]:
        raise ValueError(f"--check-mesh {model}={path}: {skin.skeleton.joint_count} joints, clips "
                         f"{[c.name for c in skin.clips]}, but {model} has {joints} joints, clips "
                         f"{[c['name'] for c in info.skeleton.get('clips', [])]}: not its character")
    return skinned_collider(skin, model, loop=bool(info.skeleton.get("loop", True)))


def exact_check(mesh, spec):
    """``distance(points, t)`` of the exact (placed) ``mesh`` for scene collider ``spec`` at
    simulation time ``t``: an animated one at the animation time the collision hook asks
    (``collider_client.response.animation_time``: the spec's time offset and loop), a skinned
    one (:func:`placed_skin`) in the spec's clip at that time."""
    from collider_client.response import ColliderPlacement, animation_time
    from collider_server.engine.animated_meshes import AnimatedMesh, ExactAtTimes
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.evaluation import exact_distance

    if getattr(mesh, "skinned", False):
        at = skinned_time(mesh, spec)
        return lambda points, t: mesh.posed(*at(t)).exact.signed_distance(points)
    if not isinstance(mesh, AnimatedMesh):
        return exact_distance(ExactSDF(mesh))
    placement = ColliderPlacement(spec.model, None, spec.time_offset_s, spec.loop)
    line = mesh.timeline
    # The hook's time, run by the scene's loop rule (held ends, not the model's wrap).
    scene_line = line.with_loop(spec.loop)
    return exact_distance(ExactAtTimes(AnimatedMesh(mesh.frames, mesh.faces, scene_line, mesh.name)),
                          lambda t: animation_time(placement, line, t)[0])


def skinned_time(collider, spec):
    """For the exact skinned ``collider`` of scene collider ``spec``: ``t -> (clip time, pose)``,
    the arguments of ``collider.posed`` at simulation time ``t``: the spec's clip (None: the
    first) at the animation time the collision hook asks it (its time offset and loop)."""
    from collider_client.response import ColliderPlacement, animation_time
    from collider_contract import SkeletonPose, Timeline

    clip = collider.skin.clip(spec.clip)
    line = Timeline.of_clip(clip.duration_s, loop=collider.loop)
    placement = ColliderPlacement(spec.model, None, spec.time_offset_s, spec.loop, spec.clip)
    pose = SkeletonPose(clip=clip.name)
    return lambda t: (animation_time(placement, line, t)[0], pose)


def shown_points(mesh, spec, count: int = 4000):
    """Surface points of the placed exact ``mesh`` for the PNG: (m, 3), collider frame; for an
    animated one a function of the simulation time (seconds)."""
    from collider_server.engine.animated_meshes import AnimatedMesh

    if getattr(mesh, "skinned", False):  # the exact skinned collider of a character (placed_skin)
        at = skinned_time(mesh, spec)
        return lambda t: surface_sample(mesh.posed(*at(t)).exact.mesh.vertices, count)
    if not isinstance(mesh, AnimatedMesh):
        return surface_sample(mesh.vertices, count)
    import numpy as np

    from collider_client.response import ColliderPlacement, animation_time

    pick = np.random.default_rng(0).choice(mesh.vertex_count, min(count, mesh.vertex_count), replace=False)
    placement = ColliderPlacement(spec.model, None, spec.time_offset_s, spec.loop)
    return lambda t: mesh.vertices_at(animation_time(placement, mesh.timeline, t)[0])[pick]


def model_surfaces(client, specs, resolution: int = 48, count: int = 4000) -> dict:
    """Per model of the scene colliders ``specs``, its surface as the model itself answers it,
    for the PNG: marching cubes (:mod:`collider_server.making.surface`) of the distance the
    client answers on a ``resolution``^3 grid over the model's domain, ``count`` of its vertices
    (m, 3), collider frame; for an animated or skinned model a function of the simulation time
    (its animation time, a skinned one's in its clip, as the collision hook asks it). A model the scene names that the client
    does not know is left out (the run refuses it)."""
    from collider_client import ColliderError
    from collider_client.response import ColliderPlacement, animation_time
    from collider_server.making.surface import distance_grid, level_surface

    if not specs:
        return {}
    try:
        infos = {m.name: m for m in client.list_models()}
    except ColliderError as exc:  # a server that is down: one line
        client.close()
        raise ValueError(str(exc)) from None

    def surface(info, time, clip=None):
        def distance(points):
            return client.query(info.name, points, fields=["distance"], time=time,
                                clip=clip).distance

        grid = distance_grid(distance, info.domain_min, info.domain_max, resolution)
        mesh = level_surface(grid)
        return surface_sample(mesh[0], count) if mesh is not None else None

    shown = {}
    for spec in specs:
        info = infos.get(spec.model)
        if info is None or spec.model in shown:
            continue
        clip = None
        if info.skinned:  # asked in its clip at the animation time, as the hook asks it
            try:
                timeline = info.clip_timeline(spec.clip)
            except ValueError:  # a clip the model lacks: the run refuses it
                continue
            clip = spec.clip or info.skeleton["clips"][0]["name"]
        else:
            timeline = info.timeline
        if timeline is None:
            points = surface(info, None)
            if points is not None:
                shown[spec.model] = points
        else:
            placement = ColliderPlacement(spec.model, None, spec.time_offset_s, spec.loop)
            shown[spec.model] = (lambda t, info=info, placement=placement, timeline=timeline,
                                 clip=clip: _or_none(
                surface(info, animation_time(placement, timeline, t)[0], clip)))
    return shown


def _or_none(points):
    """``points``, or an empty (0, 3) array where a surface was not found."""
    import numpy as np

    return np.zeros((0, 3)) if points is None else points


def surface_sample(vertices, count: int = 4000):
    """(m, 3) float64: up to ``count`` of ``vertices``, a fixed random pick (seed 0)."""
    import numpy as np

    pick = np.random.default_rng(0).choice(len(vertices), min(count, len(vertices)), replace=False)
    return np.asarray(vertices[pick], dtype=np.float64)


def start_live_view(args: argparse.Namespace, scene, client):
    """Start the browser view of the run (``--view``); returns the viser server and the
    per-step callback for :func:`run_scene`."""
    from collider_client.sim.cloth import grid_positions

    from ..views.cloth import ClothView, LiveControls
    from ..views.page import start_server, url_of

    # The models first: a server that is down fails here, before the view opens.
    infos = {m.name: m for m in client.list_models()} if client is not None else None
    server = start_server(args.host, args.port)
    c = scene.cloth
    rest = grid_positions(c.width, c.height, c.spacing_m, c.origin_m, c.axes).reshape(-1, 3)
    view = ClothView(server, scene, rest, client, infos)
    total = scene.steps if args.steps is None else args.steps
    controls = LiveControls(server, view, total, paused=args.paused)
    print(f"view at {url_of(server)}  (Ctrl-C to stop)", flush=True)
    return server, controls.on_step
