"""One simulation run: scene -> OBJ + PC2 + PNG + report, with a progress bar and, after the
first measured steps, the run's expected duration. Ctrl-C (KeyboardInterrupt) ends a run with
the same outputs for the steps that ran, the report marked interrupted."""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from collider_contract import transform_points
from collider_contract.point_cache import PC2Writer, write_obj

from .cloth import quad_faces
from .motion import pose_function
from .output import PC2Frames, write_preview
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


#: The duration estimate is made once the run has measured at least this many seconds and steps.
ESTIMATE_AFTER_S = 3.0
ESTIMATE_AFTER_STEPS = 20
#: Points of the probe query that measures what a collider query costs per point.
PROBE_POINTS = 20_000


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C (or what the caller raises as KeyboardInterrupt) ended the run; its outputs for
    the steps that ran are written. ``report`` and ``frames`` are :func:`run_scene`'s;
    ``interrupt`` is the KeyboardInterrupt that ended it."""

    def __init__(self, report, frames, interrupt: KeyboardInterrupt):
        super().__init__(f"interrupted after {report.steps} of {report.steps_planned} steps")
        self.report, self.frames, self.interrupt = report, frames, interrupt


def query_cost_per_point(client, scene: Scene, hook) -> float | None:
    """Seconds per point of one query, asked as the collision ``hook`` asks (its fields, contacts
    of the colliding points only when it does), at :data:`PROBE_POINTS` points spread over the
    first collider's domain box (collider frame), measured now: what each vertex inside a
    collider's box costs a step."""
    if client is None or not scene.colliders:
        return None
    info = {m.name: m for m in client.list_models()}.get(scene.colliders[0].model)
    if info is None:
        return None
    points = np.random.default_rng(0).uniform(info.domain_min, info.domain_max, (PROBE_POINTS, 3))
    # An animated collider is asked at its first frame (it refuses a query without a time), a
    # skinned one at its clip's first pose (a pose as the run asks, not the rest pose).
    ask = {"fields": hook.fields, "only_colliding": hook.only_colliding,
           "time": 0.0 if info.animated or info.skinned else None,
           "clip": hook.clips[0]}
    client.query(info.name, points[:1000], **ask)  # warm-up
    started = time.perf_counter()
    client.query(info.name, points, **ask)
    return (time.perf_counter() - started) / PROBE_POINTS


@dataclass(frozen=True)
class DurationEstimate:
    """What a run will take, from its first measured steps (seconds).

    steps : the run's steps; measured : the steps measured; per_step_s : their mean wall time;
    worst_per_step_s : a step once every vertex is inside a collider's box (each step then
        queries every vertex, at the probe's cost per point), None without colliders;
    per_point_s : the probe's seconds per queried point (None without colliders)
    """

    steps: int
    measured: int
    per_step_s: float
    worst_per_step_s: float | None
    per_point_s: float | None

    @property
    def seconds(self) -> float:
        return self.per_step_s * self.steps

    @property
    def worst_seconds(self) -> float | None:
        return None if self.worst_per_step_s is None else max(self.worst_per_step_s, self.per_step_s) * self.steps


def duration_estimate(scene: Scene, sim: Simulator, done: int, total: int, elapsed: float,
                      per_point: float | None) -> DurationEstimate:
    """The :class:`DurationEstimate` after ``done`` steps that took ``elapsed`` seconds."""
    worst = None
    if per_point is not None and sim.hook is not None:
        others = (elapsed - sim.timings.query_s) / done
        worst = others + per_point * scene.cloth.width * scene.cloth.height * len(scene.colliders)
    return DurationEstimate(total, done, elapsed / done, worst, per_point)


def run_scene(scene: Scene, client, out_dir: Path, *, show_progress: bool = True,
              steps: int | None = None, preview: bool = True, backend: str = "embedded",
              collider_points: dict[str, np.ndarray] | None = None,
              on_step=None, on_estimate=None) -> tuple[RunReport, PC2Frames]:
    """Simulate ``scene`` (``steps`` overrides its step count), writing into ``out_dir``:
    ``NAME.obj``, ``NAME.pc2``, ``NAME.png`` and ``NAME.report.json``.

    on_estimate : called once with a :class:`DurationEstimate` after the first measured steps
        (``ESTIMATE_AFTER_S`` seconds and ``ESTIMATE_AFTER_STEPS`` steps; not at all for a run
        shorter than that)
    Raises :class:`RunInterrupted` (a KeyboardInterrupt) on Ctrl-C, after writing the outputs
    of the steps that ran (the report's ``interrupted`` set).

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
    # The probe query only when someone asked for the estimate (it is two extra queries).
    per_point = (query_cost_per_point(client, scene, sim.hook)
                 if sim.hook is not None and on_estimate is not None else None)
    bar = _progress(total, stem, show_progress)
    started = time.perf_counter()
    per_frame_colliding = []
    interrupt = None
    done = 0
    with PC2Writer(out_dir / f"{stem}.pc2", c.width * c.height) as pc2:
        def keep_frame(t=None):
            vertices = sim.vertices.astype(np.float32)
            pc2.write(vertices)
            times.append(sim.t if t is None else t)
            per_frame_colliding.append(sim.hook.stats.colliding_last if sim.hook else 0)

        keep_frame()
        try:
            for i in range(1, total + 1):
                sim.step()
                done = i
                if i % scene.frame_every == 0 or i == total:
                    keep_frame()
                if on_step is not None:
                    on_step(sim, i)
                if (on_estimate is not None and i < total and i >= ESTIMATE_AFTER_STEPS
                        and time.perf_counter() - started >= ESTIMATE_AFTER_S):
                    on_estimate(duration_estimate(scene, sim, i, total, time.perf_counter() - started,
                                                  per_point))
                    on_estimate = None
                if bar is not None and (i % 50 == 0 or i == total):
                    bar.update(i - bar.n)
                    if sim.hook is not None:
                        bar.set_postfix(colliding=sim.hook.stats.colliding_last, refresh=False)
        except KeyboardInterrupt as exc:  # the outputs of the steps that ran, then re-raised
            interrupt = exc
            # A step cut short leaves the state of the last whole step (its new positions are
            # committed at its end): that state is the last frame, at that step's time.
            if times[-1] < done * scene.dt_s - 0.5 * scene.dt_s:
                keep_frame(done * scene.dt_s)
    if bar is not None:
        bar.close()
    frames = PC2Frames(out_dir / f"{stem}.pc2", times, c.width * c.height)
    wall = time.perf_counter() - started
    stats = sim.hook.stats if sim.hook else None
    report = RunReport(
        scene=scene.name, backend=backend, vertices=c.width * c.height, steps=done,
        steps_planned=total, interrupted=interrupt is not None,
        dt_s=scene.dt_s, frames=len(frames), effects=sim.effects,
        fields=stats.fields if stats else [], wall_s=wall, timings=sim.timings,
        points_total=stats.points_total if stats else 0,
        points_sent=stats.points_sent if stats else 0, queries=stats.queries if stats else 0,
        colliding_max=stats.colliding_max if stats else 0,
        colliding_last=stats.colliding_last if stats else 0,
        deepest_penetration_m=stats.deepest_penetration_m if stats else 0.0,
        false_contacts=stats.false_contacts if stats else 0,
        per_frame_colliding=per_frame_colliding,
    )
    if preview:
        chosen = sorted({i if i >= 0 else len(frames) + i for i in scene.preview_frames
                         if -len(frames) <= i < len(frames)})
        shown: dict[int, list[np.ndarray]] = {i: [] for i in chosen}  # each panel shows the colliders at its frame's pose
        for spec in scene.colliders:
            pts = (collider_points or {}).get(spec.model)
            if pts is not None:
                for i in chosen:
                    t = frames[i][0]
                    pose = pose_function(spec)(t)
                    shown[i].append(transform_points(pose, pts(t) if callable(pts) else pts))
        write_preview(out_dir / f"{stem}.png", {i: frames[i][1] for i in chosen}, c.width,
                      c.height, {i: frames[i][0] for i in chosen}, f"{scene.name}", shown, scene.up)
    (out_dir / f"{stem}.report.json").write_text(json.dumps(report.to_dict(), indent=2,
                                                            default=float))
    if interrupt is not None:
        raise RunInterrupted(report, frames, interrupt)
    return report, frames
