"""One simulation run: scene -> OBJ + PC2 + PNG + report, with a progress bar."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from collider_contract import transform_points

from .cloth import quad_faces
from .motion import pose_function
from .output import PC2Frames, PC2Writer, write_obj, write_preview
from .scene import Scene, check_models
from .simulator import RunReport, Simulator


def _progress(total: int, desc: str, enabled: bool):
    try:
        from tqdm import tqdm
    except ImportError:  # tqdm comes with the server extras; the light client runs without it
        return None
    return tqdm(total=total, desc=desc, unit="step", disable=not enabled, smoothing=0.1)


#: Bytes of simulator state per cloth vertex: about sixteen (H, W, 3) float64 arrays live during
#: a step (positions, previous and rest positions, forces, accelerations, spring temporaries).
STATE_BYTES_PER_VERTEX = 16 * 3 * 8
#: Above this much memory or output a run warns before it starts.
WARN_BYTES = 1 << 30


def resource_estimate(scene: Scene, steps: int) -> dict[str, int]:
    """Bytes a run of ``steps`` will need: ``memory`` (simulator state), ``pc2`` (every frame,
    float32) and ``obj`` (the first frame as text, about 30 bytes a vertex and a quad)."""
    c = scene.cloth
    vertices = c.width * c.height
    frames = steps // scene.frame_every + 2
    return {"memory": vertices * STATE_BYTES_PER_VERTEX, "pc2": 32 + frames * vertices * 12,
            "obj": 30 * (vertices + (c.width - 1) * (c.height - 1))}


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not a POSIX system
        return None


def check_resources(scene: Scene, steps: int) -> dict[str, int]:
    """Refuse a run whose state would not fit in this machine's memory; warn on stderr when it
    needs more than 1 GiB of memory or writes more than 1 GiB. Returns the estimate."""
    need = resource_estimate(scene, steps)
    c = scene.cloth
    physical = _physical_memory()
    if physical is not None and need["memory"] > 0.8 * physical:
        raise ValueError(f"{scene.path}: a {c.width} x {c.height} cloth needs about "
                         f"{need['memory'] / 2**30:.1f} GiB of memory, more than this machine's "
                         f"{physical / 2**30:.1f} GiB allow; lower cloth.width / cloth.height")
    output = need["pc2"] + need["obj"]
    if need["memory"] > WARN_BYTES or output > WARN_BYTES:
        print(f"warning: {scene.path}: a {c.width} x {c.height} cloth: about "
              f"{need['memory'] / 2**30:.1f} GiB of memory and {output / 2**30:.1f} GiB written "
              f"(PC2 {need['pc2'] / 2**30:.1f} GiB for {steps // scene.frame_every + 1} frames)",
              file=sys.stderr)
    return need


def run_scene(scene: Scene, client, out_dir: Path, *, show_progress: bool = True,
              steps: int | None = None, preview: bool = True, backend: str = "embedded",
              collider_points: dict[str, np.ndarray] | None = None,
              on_step=None) -> tuple[RunReport, list]:
    """Simulate ``scene`` (``steps`` overrides its step count), writing into ``out_dir``:
    ``NAME.obj``, ``NAME.pc2``, ``NAME.png`` and ``NAME.report.json``.

    collider_points : model name -> (m, 3) surface points in the collider frame, or a function
        of the simulation time (seconds) giving them (an animated collider), drawn in the
        preview (optional)
    on_step : called as ``on_step(sim, i)`` after step ``i`` (1-based), e.g. by the live viewer
        (``collider simulate --view``), which may block there to pause the run
    Returns the report and the frames written, a sequence of (t, (W*H, 3) float32 positions)
    read back from the PC2 file (:class:`PC2Frames`: frames are streamed to disk, not kept).
    """
    if preview:
        try:
            import matplotlib  # noqa: F401
        except ImportError:  # checked before the run, not after an hour of it
            raise ValueError("the PNG preview needs matplotlib (pip install matplotlib, or the "
                             "server extras); or pass --no-preview") from None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    infos = None
    if client is not None and scene.colliders:
        infos = {m.name: m for m in client.list_models()}
        check_models(scene, infos)
    total = scene.steps if steps is None else steps
    check_resources(scene, total)
    sim = Simulator(scene, client, infos)
    stem = scene.path.stem
    c = scene.cloth
    write_obj(out_dir / f"{stem}.obj", sim.vertices, quad_faces(c.width, c.height), stem)
    times: list[float] = []
    bar = _progress(total, stem, show_progress)
    started = time.perf_counter()
    per_frame_colliding = []
    with PC2Writer(out_dir / f"{stem}.pc2", c.width * c.height) as pc2:
        def keep_frame():
            vertices = sim.vertices.astype(np.float32)
            pc2.write(vertices)
            times.append(sim.t)
            per_frame_colliding.append(sim.hook.stats.colliding_last if sim.hook else 0)

        keep_frame()
        for i in range(1, total + 1):
            sim.step()
            if i % scene.frame_every == 0 or i == total:
                keep_frame()
            if on_step is not None:
                on_step(sim, i)
            if bar is not None and (i % 50 == 0 or i == total):
                bar.update(i - bar.n)
                if sim.hook is not None:
                    bar.set_postfix(colliding=sim.hook.stats.colliding_last, refresh=False)
    if bar is not None:
        bar.close()
    frames = PC2Frames(out_dir / f"{stem}.pc2", times, c.width * c.height)
    wall = time.perf_counter() - started
    stats = sim.hook.stats if sim.hook else None
    report = RunReport(
        scene=scene.name, backend=backend, vertices=c.width * c.height, steps=total,
        dt_s=scene.dt_s, frames=len(frames), effects=sim.effects,
        fields=stats.fields if stats else [], wall_s=wall, timings=sim.timings,
        points_total=stats.points_total if stats else 0,
        points_sent=stats.points_sent if stats else 0, queries=stats.queries if stats else 0,
        colliding_max=stats.colliding_max if stats else 0,
        colliding_last=stats.colliding_last if stats else 0,
        deepest_penetration_m=stats.deepest_m if stats else 0.0,
        per_frame_colliding=per_frame_colliding,
    )
    if preview:
        chosen = sorted({i if i >= 0 else len(frames) + i for i in scene.preview_frames
                         if -len(frames) <= i < len(frames)})
        shown = {i: [] for i in chosen}  # each panel shows the colliders at its frame's pose
        for spec in scene.colliders:
            pts = (collider_points or {}).get(spec.model)
            if pts is not None:
                for i in chosen:
                    t = frames[i][0]
                    pose = pose_function(spec)(t)
                    shown[i].append(transform_points(pose, pts(t) if callable(pts) else pts))
        write_preview(out_dir / f"{stem}.png", {i: frames[i][1] for i in chosen}, c.width,
                      c.height, {i: frames[i][0] for i in chosen}, f"{scene.name}", shown)
    (out_dir / f"{stem}.report.json").write_text(json.dumps(report.to_dict(), indent=2,
                                                            default=float))
    return report, frames
