"""Measure any collider against the exact signed distance of its mesh.

Point sets (seeded): uniform in the +-1 mm and +-10 mm bands around the surface (surface samples
moved along the face normal) and uniform in the collider's domain box. Truth: the exact SDF
(:class:`~collider_server.engine.meshes.ExactSDF`, float64). All figures are reported in millimetres and
degrees whatever the collider's units (converted with ``meters_per_unit``).

Per set: distance error mean / p99 / max; sign errors among points with |d| > 0.2 mm (percent);
normal angle error mean / p99 against the exact gradient (direction to the closest point);
contact error, the distance of the computed contact point to the true offset surface d = eps.
The same figures again for the points where the mesh's winding number is clear (below 0.1 or
above 0.9, ``clear_winding``), and the share of the others (``ambiguous_winding_percent``): near a
hole (the bunny's open base) inside and outside are not defined, the truth's sign is the winding
number's guess (inside above 0.5) and its distance jumps from -d to +d across the hole, where no
continuous collider can follow it (docs/accuracy.md, "Holes").
Plus: marching-cubes reconstruction vs the mesh (Chamfer-L1, mm), file size, query time.

An animated collider (:func:`evaluate_animated_collider`) is measured the same way at random
times drawn uniformly over its animation (so between its frames, where keyframe grids are
interpolated), each time against the exact interpolated mesh at that time
(:class:`~collider_server.engine.animated_meshes.ExactAtTimes`), the points of every time pooled.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..engine.animated_meshes import AnimatedMesh, ExactAtTimes
from ..engine.collider import Collider
from ..engine.meshes import ExactSDF, Mesh, unsigned_distance
from ..engine.skinning import RandomPoses, Skin, random_poses, skin_vertices
from .progress import progress
from .sampling import animated_band_sets, band_sets, box_points, random_times, surface_points
from .surface import distance_grid, level_surface

SIGN_THRESHOLD_M = 0.2e-3
#: Winding numbers between these are "ambiguous": the point is near a hole of the surface.
CLEAR_WINDING = (0.1, 0.9)


def point_sets(collider: Collider, mesh: Mesh, points: int, seed: int) -> dict[str, np.ndarray]:
    """The sets of the module docstring, ``points`` each: the bands, and ``box``."""
    sets = band_sets(mesh, points, seed, collider.info.meters_per_unit)
    sets["box"] = box_points(collider.domain_min, collider.domain_max, points, seed + 7)
    return sets


class Reference(NamedTuple):
    """The exact SDF at a set of points, which every collider measured there is compared with
    (:func:`exact_reference`): ``distance`` (n,) float64 (collider units, negative inside),
    ``normal`` (n, 3) float64 unit gradient, ``clear`` (n,) bool: the winding number is clear
    (:data:`CLEAR_WINDING`); ``points``: the array they were computed at (the only one they
    answer for: :func:`point_errors` refuses another)."""

    distance: np.ndarray
    normal: np.ndarray
    clear: np.ndarray
    points: np.ndarray


def exact_reference(sdf: ExactSDF, points: np.ndarray) -> Reference:
    """:class:`Reference` of ``sdf`` at ``points`` (n, 3) (collider frame): computed once for a
    point set that several colliders are measured on (a bench's candidates)."""
    truth, closest, face = sdf.query(points)
    winding = sdf.winding_number(points)
    return Reference(truth, sdf.gradient(points, truth, closest, face),
                     (winding < CLEAR_WINDING[0]) | (winding > CLEAR_WINDING[1]), points)


def point_errors(collider: Collider, sdf: ExactSDF, points: np.ndarray,
                 time: float | None = None, skeleton: dict | None = None,
                 reference: Reference | None = None) -> dict[str, np.ndarray]:
    """Per point of ``points`` (collider frame), ``collider`` asked at ``time`` seconds (an
    animated one; ``sdf`` the exact SDF of its surface at that time) and at the skeleton pose
    ``skeleton`` (a skinned one: ``{"clip": name}`` with ``time``, or ``{"joint_transforms": (J,
    4, 4)}``, the query's keywords) against ``sdf``: distance
    error (mm), whether the true sign is decided (|d| > 0.2 mm) and the sign wrong, normal angle
    error (deg), contact error (mm) and whether the winding number is clear. ``reference``:
    :func:`exact_reference` of ``sdf`` at ``points`` where the caller has it."""
    to_mm = 1000.0 * collider.info.meters_per_unit
    eps = collider.info.default_eps
    if reference is not None and reference.points is not points:
        raise ValueError("the reference was computed at other points than those measured")
    truth, true_normal, clear, _ = reference if reference is not None else exact_reference(sdf, points)
    result = collider.query(points, ["distance", "normal", "contact"], eps=eps, time=time, **(skeleton or {}))
    cosine = np.clip(np.einsum("ij,ij->i", result.normal.astype(np.float64), true_normal), -1.0, 1.0)
    return {
        "distance": np.abs(result.distance.astype(np.float64) - truth) * to_mm,
        "decided": np.abs(truth) * to_mm > SIGN_THRESHOLD_M * 1000.0,
        "sign_wrong": (result.distance < 0) != (truth < 0),
        "normal": np.degrees(np.arccos(cosine)),
        "contact": np.abs(sdf.signed_distance(result.contact.astype(np.float64)) - eps) * to_mm,
        "clear": clear,
    }


def pooled(errors: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Several :func:`point_errors` as one (the points of every time together)."""
    return {key: np.concatenate([e[key] for e in errors]) for key in errors[0]}


def summarize(errors: dict[str, np.ndarray]) -> dict:
    """The figures of :func:`point_errors`: for all points and, under ``clear_winding``, for
    those where the winding number is clear."""
    clear = errors["clear"]

    def figures(keep: np.ndarray) -> dict:
        if not keep.any():
            return {"points": 0}
        signed = keep & errors["decided"]
        distance, angle, contact = errors["distance"][keep], errors["normal"][keep], errors["contact"][keep]
        return {
            "points": int(keep.sum()),
            "distance_mean_mm": float(distance.mean()),
            "distance_p99_mm": float(np.percentile(distance, 99)),
            "distance_max_mm": float(distance.max()),
            "sign_errors_percent": float(100.0 * errors["sign_wrong"][signed].mean()) if signed.any() else 0.0,
            "normal_mean_deg": float(angle.mean()),
            "normal_p99_deg": float(np.percentile(angle, 99)),
            "contact_mean_mm": float(contact.mean()),
            "contact_p99_mm": float(np.percentile(contact, 99)),
        }

    return {**figures(np.ones(len(clear), dtype=bool)), "clear_winding": figures(clear),
            "ambiguous_winding_percent": float(100.0 * (1.0 - clear.mean())) if len(clear) else 0.0}


def error_figures(collider: Collider, sdf: ExactSDF, points: np.ndarray, time: float | None = None,
                  reference: Reference | None = None) -> dict:
    """Distance, sign, normal and contact errors of ``collider`` at ``points`` (collider frame,
    at ``time`` seconds for an animated one), for all of them and, under ``clear_winding``, for
    those where the winding number is clear."""
    return summarize(point_errors(collider, sdf, points, time, reference=reference))


def animated_error_figures(collider: Collider, animation: AnimatedMesh, times, points: int, seed: int,
                           sets: tuple[str, ...] = ("band_1mm", "band_10mm", "box"),
                           on_time=lambda: None, exact: ExactAtTimes | None = None) -> dict:
    """:func:`error_figures` of an animated ``collider`` at ``times`` (seconds) against the
    exact interpolated surface of ``animation`` (its frame and units) at each: ``points`` per
    set per time (:func:`~.sampling.animated_band_sets`; ``box``: uniform in the collider's
    domain), the errors of every time pooled per set. ``on_time()`` is called after each time;
    ``exact``: the truth's trees, kept across calls that measure several colliders."""
    exact = exact or ExactAtTimes(animation, keep=1)
    errors: dict[str, list] = {name: [] for name in sets}
    for i, (t, bands) in enumerate(animated_band_sets(animation, times, points, seed,
                                                      collider.info.meters_per_unit)):
        bands["box"] = box_points(collider.domain_min, collider.domain_max, points, seed + 7 + 10 * i)
        sdf = exact.at(t)[0]
        for name in sets:
            errors[name].append(point_errors(collider, sdf, bands[name], t))
        on_time()
    return {name: summarize(pooled(found)) for name, found in errors.items()}


def reconstruction_chamfer_mm(collider: Collider, mesh: Mesh, resolution: int = 128,
                              samples: int = 50_000, seed: int = 0, sdf: ExactSDF | None = None) -> float:
    """Chamfer-L1 (mean of both directions, not squared, mm) between the marching-cubes zero
    level set of ``collider`` on a ``resolution``^3 grid over its domain and ``mesh`` (``sdf``:
    its :class:`ExactSDF` where the caller has one)."""
    grid = distance_grid(lambda points: collider.query(points, ["distance"]).distance,
                         collider.domain_min, collider.domain_max, resolution)
    surface = level_surface(grid)
    if surface is None:
        return float("inf")
    recon = Mesh(*surface, "reconstruction")
    to_mm = 1000.0 * collider.info.meters_per_unit
    recon_points, _ = surface_points(recon, samples, seed)
    mesh_points, _ = surface_points(mesh, samples, seed + 1)
    recon_to_mesh = np.abs((sdf or ExactSDF(mesh)).query(recon_points)[0])
    # A level set does not cross itself: the distance to its faces, without ExactSDF's union and
    # sign (their self-intersection test and winding numbers were half the check's time).
    mesh_to_recon = unsigned_distance(recon, mesh_points)
    return float(0.5 * (recon_to_mesh.mean() + mesh_to_recon.mean()) * to_mm)


#: Points the query time is measured on, the first of the +-1 mm band (where a cloth's colliding
#: points are). A time per point depends on where the points are: docs/accuracy.md, "Query time".
QUERY_POINTS = 50_000


def query_seconds_per_million(collider: Collider, points: np.ndarray, repeats: int = 2,
                              at: float | None = None, skeleton: dict | None = None) -> float:
    """Best wall time of a distance + normal + contact query (at ``at`` seconds: an animated
    collider; at the pose ``skeleton``, the query's keywords: a skinned one), scaled to 1M
    points."""
    best = float("inf")
    for _ in range(repeats):
        started = time.perf_counter()
        collider.query(points, ["distance", "normal", "contact"], time=at, **(skeleton or {}))
        best = min(best, time.perf_counter() - started)
    return best * 1e6 / len(points)


def evaluate_collider(collider: Collider, mesh: Mesh, points: int = 100_000, seed: int = 1234,
                      reconstruction: bool = True, path: Path | None = None,
                      show_progress: bool = True) -> dict:
    """All figures of the module docstring as a JSON-ready dict. ``mesh`` must be in the
    collider's frame and units (apply ``info.source["transform"]`` first)."""
    if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or points < 1:
        raise ValueError(f"points (per set) must be a positive integer, got {points!r}")
    sdf = ExactSDF(mesh)
    sets = point_sets(collider, mesh, points, seed)
    steps = len(sets) + 1 + int(reconstruction)
    report: dict = {}
    with progress(steps, f"eval {collider.info.name}", "step", show_progress) as bar:
        for name, set_points in sets.items():
            report[name] = error_figures(collider, sdf, set_points)
            bar.update(1)
        timed = sets["band_1mm"][:QUERY_POINTS]
        report["query_seconds_per_million"] = query_seconds_per_million(collider, timed)
        report["query_points"] = len(timed)
        bar.update(1)
        if reconstruction:
            report["chamfer_l1_mm"] = reconstruction_chamfer_mm(collider, mesh, seed=seed, sdf=sdf)
            bar.update(1)
    return {**report, **_about(collider, path)}


def evaluate_animated_collider(collider: Collider, animation: AnimatedMesh, points: int = 100_000,
                               times: int = 16, seed: int = 1234, path: Path | None = None,
                               show_progress: bool = True) -> dict:
    """The figures of :func:`evaluate_collider` for an animated ``collider`` at ``times`` random
    times (:func:`~.sampling.random_times`: uniform over the animation, between its frames)
    against the exact interpolated surface of ``animation`` (the frames it was made from, in the
    collider's frame and units), ``points`` per set split evenly over the times, pooled. No
    reconstruction; the query time is measured at the first time. Adds ``times_s`` (the times,
    seconds), ``duration_s`` and ``points_per_time``."""
    if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or points < 1:
        raise ValueError(f"points (per set) must be a positive integer, got {points!r}")
    at = random_times(animation.timeline, times, seed)
    per_time = -(-points // times)
    with progress(times + 1, f"eval {collider.info.name}", "time", show_progress) as bar:
        report = animated_error_figures(collider, animation, at, per_time, seed,
                                        on_time=lambda: bar.update(1))
        probe = animation.mesh_at(float(at[0]))
        timed = band_sets(probe, min(per_time, QUERY_POINTS), seed, collider.info.meters_per_unit)["band_1mm"]
        report["query_seconds_per_million"] = query_seconds_per_million(collider, timed, at=float(at[0]))
        report["query_points"] = len(timed)
        bar.update(1)
    return {**report, "times_s": at.tolist(), "duration_s": animation.timeline.duration_s,
            "points_per_time": per_time, "seed": seed, **_about(collider, path)}


def pose_query(poses: RandomPoses, i: int) -> tuple[float | None, dict]:
    """How pose ``i`` of ``poses`` is asked of a skinned collider: ``(time, skeleton keywords)``:
    a clip pose by its clip and time (the query's clip path), a perturbed one (or one of a skin
    without clips) by its joint transforms."""
    if poses.perturbed[i] or poses.clips[i] is None:
        return None, {"joint_transforms": poses.transforms[i]}
    return float(poses.times[i]), {"clip": poses.clips[i]}


def skinned_error_figures(collider: Collider, skin: Skin, poses: RandomPoses, points: int, seed: int,
                          sets: tuple[str, ...] = ("band_1mm", "band_10mm", "box"),
                          on_pose=lambda: None) -> dict:
    """:func:`error_figures` of a skinned ``collider`` (kind ``skinned`` or ``neural-skinned``)
    at each of ``poses`` (asked as :func:`pose_query` says) against the exact SDF of ``skin``
    posed there (linear blend skinning, the union of a self-overlapping skin: what the exact
    ``skinned`` kind answers), ``points`` per set per pose (pose ``i``'s bands drawn from ``seed +
    10 i``; ``box`` uniform in the collider's domain), pooled per set. ``skin`` is the truth's, in
    the collider's frame and units."""
    errors: dict[str, list] = {name: [] for name in sets}
    for i in range(len(poses)):
        mesh = Mesh(skin_vertices(skin, poses.transforms[i]), skin.faces, "posed")
        sdf = ExactSDF(mesh)
        bands = band_sets(mesh, points, seed + 10 * i, collider.info.meters_per_unit)
        bands["box"] = box_points(collider.domain_min, collider.domain_max, points, seed + 7 + 10 * i)
        time_s, skeleton = pose_query(poses, i)
        for name in sets:
            errors[name].append(point_errors(collider, sdf, bands[name], time_s, skeleton))
        on_pose()
    return {name: summarize(pooled(found)) for name, found in errors.items()}


#: The pose sets of a skinned evaluation, in the order they are reported.
SKINNED_POSE_SETS = ("clip_times", "random_poses")


def skinned_pose_sets(skin: Skin, times: int, poses: int, seed: int) -> dict[str, RandomPoses]:
    """The two pose sets a skinned model is measured at (``collider eval`` and ``collider
    bench``), drawn by :func:`~collider_server.engine.skinning.random_poses`: ``clip_times``,
    ``times`` random clips at uniform random times (none turned), and ``random_poses``, ``poses``
    random clip times with every joint's local rotation turned."""
    return {"clip_times": random_poses(skin, times, seed, perturbed_share=0.0),
            "random_poses": random_poses(skin, poses, seed + 1, perturbed_share=1.0)}


def pose_set_figures(collider: Collider, skin: Skin, drawn: dict[str, RandomPoses], points: int, seed: int,
                     sets: tuple[str, ...] = ("band_1mm", "band_10mm", "box"), on_pose=lambda: None) -> dict:
    """Per pose set of ``drawn`` (:func:`skinned_pose_sets`): :func:`skinned_error_figures` with
    ``points`` per point set split evenly over the set's poses, plus ``points_per_pose`` and
    ``poses`` (each pose's clip, time in seconds, and whether it was turned)."""
    report = {}
    for offset, (name, drawn_poses) in enumerate(drawn.items()):
        per_pose = -(-points // len(drawn_poses))
        report[name] = {
            **skinned_error_figures(collider, skin, drawn_poses, per_pose, seed + 1000 * offset, sets, on_pose),
            "points_per_pose": per_pose,
            "poses": [{"clip": c, "time_s": float(t), "perturbed": bool(p)}
                      for c, t, p in zip(drawn_poses.clips, drawn_poses.times, drawn_poses.perturbed)]}
    return report


def evaluate_skinned_collider(collider: Collider, skin: Skin, points: int = 100_000, times: int = 16,
                              poses: int = 16, seed: int = 1234, path: Path | None = None,
                              show_progress: bool = True) -> dict:
    """The figures of :func:`evaluate_collider` for a skinned ``collider`` in two pose sets of
    :func:`~collider_server.engine.skinning.random_poses` (seeded): ``clip_times``, ``times``
    random clips at uniform random times (asked by clip and time), and ``random_poses``, ``poses``
    random clip times with every joint's local rotation then turned by up to
    :data:`~collider_server.engine.skinning.PERTURB_DEG` about a random axis (asked by joint
    transforms); ``points`` per set split evenly over each set's poses, pooled, against the exact
    skin at each pose (:func:`skinned_error_figures`). No reconstruction; the query time is
    measured at the first random pose. Each set adds ``poses`` (each pose's clip, time, and
    whether it was turned) and ``points_per_pose``."""
    if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or points < 1:
        raise ValueError(f"points (per set) must be a positive integer, got {points!r}")
    drawn = skinned_pose_sets(skin, times, poses, seed)
    report: dict = {"perturb_deg": drawn["random_poses"].perturb_deg, "seed": seed}
    with progress(times + poses + 1, f"eval {collider.info.name}", "pose", show_progress) as bar:
        report.update(pose_set_figures(collider, skin, drawn, points, seed, on_pose=lambda: bar.update(1)))
        first = drawn["random_poses"]
        probe = Mesh(skin_vertices(skin, first.transforms[0]), skin.faces, "posed")
        timed = band_sets(probe, min(points, QUERY_POINTS), seed, collider.info.meters_per_unit)["band_1mm"]
        report["query_seconds_per_million"] = query_seconds_per_million(
            collider, timed, skeleton={"joint_transforms": first.transforms[0]})
        report["query_points"] = len(timed)
        bar.update(1)
    return {**report, **_about(collider, path)}


def _about(collider: Collider, path: Path | None) -> dict:
    """What every evaluation report says of the collider beside its errors."""
    return {"file_bytes": int(path.stat().st_size) if path is not None else None,
            "training_seconds": collider.info.settings.get("training", {}).get("seconds"),
            "device": collider.device,
            "evaluated": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def penetration(frames, colliders) -> dict:
    """How deep simulated points went into exact surfaces: for ``frames``, a sequence of ``(t
    seconds, (n, 3) points, world frame, metres)``, and ``colliders``, a list of ``(name,
    distance, pose_at)``: ``distance(points, t)`` the exact signed distance at collider-frame
    points at simulation time ``t`` (collider units; :func:`exact_distance`), ``pose_at: t ->
    (4, 4)`` collider -> world; each point taken into each collider's frame at its frame's time.

    Returns ``{"max_depth_m": ..., "min_distance_m": ..., "frames": ..., "by_model": {name:
    depth_m}}``: the deepest penetration (>= 0, metres) over all, and per collider name;
    ``min_distance_m`` is the smallest signed distance of any point (negative: inside), which
    shows how close the points came (about eps when a cloth rests on the collider)."""
    from collider_contract import as_pose

    by_model: dict[str, float] = {}
    closest = float("inf")
    for name, distance_at, pose_at in colliders:
        worst = 0.0
        for t, points in frames:
            pose = as_pose(pose_at(t))
            distance = distance_at(pose.to_local(points), t) * pose.scale  # world units
            if len(distance):
                worst = max(worst, float(-distance.min()))
                closest = min(closest, float(distance.min()))
        by_model[name] = max(by_model.get(name, 0.0), worst)
    return {"max_depth_m": max(by_model.values(), default=0.0), "min_distance_m": closest,
            "frames": len(frames), "by_model": by_model}


class SurfaceCrossings:
    """Which simulated points crossed exact surfaces during a step, not only which are inside at
    a written frame: a point that passes through a thin part and out again within a frame is
    outside at both frames.

    Fed every step (:meth:`step`), it keeps per point and collider the sign of its exact signed
    distance and how far it may have come since that was measured (conservative advancement): a
    point ``|d|`` from the surface cannot reach it before it and the surface have moved ``|d|``
    between them, so it is measured again only once its own displacement plus the surface's
    largest move (``moves``) since its last measure add up to ``|d|``. A point whose sign went
    from outside to inside between two measures crossed the surface in that step.

    colliders : ``(name, distance, pose_at)`` as :func:`penetration` takes them
    """

    def __init__(self, colliders):
        self.colliders = list(colliders)
        self.previous = None
        self.sign: list[np.ndarray] = []
        self.slack: list[np.ndarray] = []
        self.crossed: list[np.ndarray] = []
        self.deepest = [0.0] * len(self.colliders)
        self.measured = 0  # exact distances computed (its cost)
        self.steps = 0

    def _measure(self, k: int, points: np.ndarray, t: float) -> np.ndarray:
        from collider_contract import as_pose

        _, distance_at, pose_at = self.colliders[k]
        pose = as_pose(pose_at(t))
        self.measured += len(points)
        return distance_at(pose.to_local(points), t) * pose.scale  # world units

    def step(self, t: float, points: np.ndarray, moves) -> None:
        """After the step that ended at ``t`` (seconds): ``points`` (n, 3), world frame, and
        ``moves``, per collider the largest displacement of any point of its surface over that
        step (world units; the collision hook's ``collider_moves``)."""
        points = np.asarray(points, dtype=np.float64)
        if self.previous is None:  # the first measure: every point
            for k in range(len(self.colliders)):
                d = self._measure(k, points, t)
                self.sign.append(d >= 0)
                self.slack.append(np.abs(d))
                self.crossed.append(np.zeros(len(points), dtype=bool))
                self.deepest[k] = max(self.deepest[k], float(-d.min(initial=0.0)))
            self.previous = points.copy()
            return
        self.steps += 1
        travelled = np.linalg.norm(points - self.previous, axis=1)
        for k in range(len(self.colliders)):
            self.slack[k] -= travelled + moves[k]
            due = np.flatnonzero(self.slack[k] <= 0.0)
            if not len(due):
                continue
            d = self._measure(k, points[due], t)
            outside = d >= 0
            self.crossed[k][due] |= self.sign[k][due] & ~outside
            self.sign[k][due] = outside
            self.slack[k][due] = np.abs(d)
            self.deepest[k] = max(self.deepest[k], float(-d.min(initial=0.0)))
        self.previous = points.copy()

    def result(self) -> dict:
        """``{"crossed_points": ..., "crossed_by_model": {name: count}, "inside_at_end": ...,
        "max_depth_at_a_step_m": ..., "steps": ..., "exact_distances": ...}``: how many points
        crossed a surface from outside to inside during some step (a point counted once per
        collider), how many of them are inside at the end, and the deepest any measure found."""
        crossed = {name: int(c.sum()) for (name, _, _), c in zip(self.colliders, self.crossed)}
        inside_end = sum(int((c & ~s).sum()) for c, s in zip(self.crossed, self.sign))
        return {"crossed_points": sum(crossed.values()), "crossed_by_model": crossed,
                "inside_at_end": inside_end, "max_depth_at_a_step_m": max(self.deepest, default=0.0),
                "steps": self.steps, "exact_distances": self.measured}


def exact_distance(exact, time_at=None):
    """``distance(points, t)`` for :func:`penetration`: an :class:`ExactSDF` (a still mesh), or
    an :class:`~collider_server.engine.animated_meshes.ExactAtTimes` (a deforming one) asked at
    ``time_at(t)``, the animation's time at simulation time ``t`` (seconds)."""
    if time_at is None:
        return lambda points, t: exact.signed_distance(points)
    return lambda points, t: exact.at(time_at(t))[0].signed_distance(points)


def times_lines(report: dict) -> list[str]:
    """An animated evaluation's times: how many, over which range, and each one."""
    times = report.get("times_s")
    if not times:
        return []
    shown = ", ".join(f"{t:.4f}" for t in times[:8]) + (", ..." if len(times) > 8 else "")
    return [(f"at {len(times)} random times in [0, {report['duration_s']:g}) s, uniform (seed {report['seed']}; "
            f"between frames), {report['points_per_time']:,} points per set at each, pooled, against the "
            f"exact interpolated mesh at that time"), f"times (s): {shown}"]


def pose_set_lines(report: dict) -> list[str]:
    """What a skinned evaluation's pose set ``report`` (one of :data:`SKINNED_POSE_SETS`) was."""
    poses = report["poses"]
    turned = sum(p["perturbed"] for p in poses)
    clips = sorted({p["clip"] for p in poses if p["clip"] is not None})
    what = (f"{len(poses)} random poses: random clip times ({', '.join(clips) or 'the rest pose'}), every "
            "joint's local rotation then turned about a random axis (asked by joint transforms)") if turned else (
            f"{len(poses)} random clip times ({', '.join(clips)}; asked by clip and time)")
    return [(f"{what}, {report['points_per_pose']:,} points per set at each, pooled, against the exact skin "
             "(its union) at that pose")]


def format_report(name: str, kind: str, report: dict) -> str:
    """A plain-text table of :func:`evaluate_collider`'s figures: each set, then the same set
    without the points of ambiguous winding number ("w clear"), when it has any; a skinned
    evaluation's (:func:`evaluate_skinned_collider`) once per pose set."""
    header = ("set", "dist mean", "p99", "max", "sign err", "normal mean", "p99", "contact mean", "p99")
    line = "{:<10} {:>10} {:>8} {:>8} {:>9} {:>12} {:>7} {:>13} {:>8}"
    rows = [f"{name} ({kind})", *times_lines(report)]
    if "random_poses" in report:
        rows.append(f"random poses: up to {report['perturb_deg']:g} deg per joint off the clip (seed {report['seed']})")
    ambiguous = []
    for key, part in [(k, report[k]) for k in SKINNED_POSE_SETS if k in report] or [("", report)]:
        if key:
            rows += pose_set_lines(part)
        rows += [line.format(*header), line.format("", "mm", "mm", "mm", "%", "deg", "deg", "mm", "mm")]
        ambiguous += [f"{key.replace('_', ' ')} {where}".strip() for where in set_rows(part, rows)]
    if ambiguous:
        rows.append(f"w clear: without the points near holes, where the mesh's winding number is between "
                    f"{CLEAR_WINDING[0]} and {CLEAR_WINDING[1]} ({', '.join(ambiguous)} of the points)")
    if "chamfer_l1_mm" in report:
        rows.append(f"reconstruction Chamfer-L1: {report['chamfer_l1_mm']:.4f} mm (marching cubes 128^3)")
    at = f" at t = {report['times_s'][0]:.4f} s" if report.get("times_s") else ""
    at = " at the first random pose" if "random_poses" in report else at
    # Which points were timed: a time per point depends on where the points are (docs/accuracy.md).
    timed = f" ({report['query_points']:,} points of the +-1 mm band, best of 2)" if "query_points" in report else ""
    rows.append(f"query (distance+normal+contact){at}: {report['query_seconds_per_million']:.2f} s per 1M points "
                f"on {report['device']}{timed}")
    if report.get("file_bytes") is not None:
        rows.append(f"model file: {report['file_bytes']:,} bytes")
    if report.get("training_seconds") is not None:
        rows.append(f"training time: {report['training_seconds'] / 60:.1f} min")
    return "\n".join(rows)


def set_rows(report: dict, rows: list[str]) -> list[str]:
    """Append the rows of each point set of ``report`` (figures of one pose set, or of the whole
    evaluation) to ``rows``; returns where points of ambiguous winding number were left out."""
    numbers = "{:<10} {:>10.4f} {:>8.4f} {:>8.4f} {:>9.3f} {:>12.2f} {:>7.2f} {:>13.4f} {:>8.4f}"
    ambiguous = []
    for key in ("band_1mm", "band_10mm", "box"):
        if key not in report:
            continue
        label = key.replace("band_", "+-")
        for row_label, r in ((label, report[key]), ("  w clear", report[key].get("clear_winding"))):
            if r is None or not r.get("points") or (row_label != label and not report[key]["ambiguous_winding_percent"]):
                continue
            rows.append(numbers.format(row_label, r["distance_mean_mm"], r["distance_p99_mm"], r["distance_max_mm"],
                                       r["sign_errors_percent"], r["normal_mean_deg"], r["normal_p99_deg"],
                                       r["contact_mean_mm"], r["contact_p99_mm"]))
        if report[key].get("ambiguous_winding_percent"):
            ambiguous.append(f"{label} {report[key]['ambiguous_winding_percent']:.2f} %")
    return ambiguous
