"""How a validated query is answered, given a way to evaluate a collider: the eps policy, the
fields' assembly in the world frame, and the scene rule. One home for the engine, the SDK's
embedded backend and the HTTP service, so that their answers are the same by construction.

Answering a :class:`~.queries.ModelQuery` is three steps:

1. :func:`prepare`: the points in the collider frame, whether the gradient is needed and below
   which distance (collide-only mode), the query's eps in world units (:func:`resolve_eps`) and
   its time;
2. an *evaluation* of the collider at those points and that time (:data:`Evaluate`: the engine's
   ``Collider.query_local``), which a batching server may join with other requests';
3. :func:`finish`: the fields in the world frame, given the resolved eps.

:func:`answer_model_query` is the three in a row. A :class:`~.queries.SceneQuery` prepares and
evaluates each collider, then :func:`finish_scene` keeps, per point, the nearest collider's fields
(:func:`nearest_collider`). The fields:

- ``distance`` : (n,) float32, world units, signed, negative inside;
- ``normal``   : (n, 3) float32, unit outward normal (normalised SDF gradient), world frame;
- ``contact``  : (n, 3), the point moved to the offset surface ``p + (eps - d) * normal``,
  world frame, in the dtype of the query points (float32 or float64);
- ``collides`` : (n,) bool, ``d < eps``;
- ``velocity`` : (n, 3) float32, world units per second, world frame: the velocity of the
  collider's surface where the point's contact is. It sums the motion of the collider's frame
  (``pose_velocity`` applied at the contact, in the collider frame) and the surface's own motion
  in its frame (an animated collider's: the exact kind's material velocity at the closest surface
  point; an SDF kind's normal speed ``-df/dt`` along the normal, with no tangential part, which an
  implicit surface does not define). Zero for a static collider under a still pose.

Collide-only mode (``only_colliding``): ``normal``, ``contact`` and ``velocity`` are computed only
for the points that collide; for the others ``normal`` and ``velocity`` are ``[0, 0, 0]`` and
``contact`` is the point itself.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import QueryError
from .pose import Pose, rotate_rows
from .queries import ModelQuery, SceneQuery
from .results import QueryResult
from .skeleton import SkeletonPose, require_skeleton_pose

#: The default collision offset: 1 mm, whatever the collider's units.
DEFAULT_EPS_METERS = 1e-3

#: ``evaluate(local, want_gradient, gradient_below, time) -> (distance, normal, velocity)``: a
#: collider's signed distance at collider-frame points ``local`` (m, 3) float64, collider units,
#: at ``time`` seconds (None for a static collider), and when ``want_gradient`` its unit normal
#: (m, 3) float64 and its surface's velocity in its own frame (m, 3) float64, collider units per
#: second (None: still), both only where ``distance`` is below ``gradient_below`` (None:
#: everywhere; a number or an (m,) array, collider units; the other rows zero). The engine's
#: ``Collider.query_local``. A skinned collider's evaluation takes a fifth argument, the
#: skeleton pose (:class:`~.skeleton.SkeletonPose`), given only when the query has one.
Evaluate = Callable[..., "tuple[np.ndarray, np.ndarray | None, np.ndarray | None]"]


def default_eps(meters_per_unit: float, pose: Pose) -> float:
    """The eps of a query that gives none: 1 mm in the collider's units (``meters_per_unit``
    metres each), times the pose's scale: world units."""
    return DEFAULT_EPS_METERS / meters_per_unit * pose.scale


def resolve_eps(eps: float | None, meters_per_unit: float, pose: Pose) -> float:
    """A query's eps in world units: its own (already checked by the query), or the default."""
    return default_eps(meters_per_unit, pose) if eps is None else eps


def gradient_threshold(eps: float, pose: Pose) -> float:
    """The collider-unit distance below which a collide-only query needs the gradient: ``eps``
    (world units) over the pose's scale, raised by a relative 1e-9 so that no point with
    ``distance * scale < eps`` is missed by rounding (one a hair above gets a normal it does not
    use; :func:`finish` zeroes it)."""
    local = eps / pose.scale
    return local + 1e-9 * max(abs(local), 1e-30)


@dataclass(frozen=True)
class Evaluation:
    """What answering a query asks of its collider.

    local : (n, 3) float64, the query's points in the collider frame and units
    want_gradient : whether ``normal``, ``contact`` or ``velocity`` was asked for
    gradient_below : collider units: a normal is needed only below this distance (collide-only),
        or None (everywhere, when ``want_gradient``)
    eps : the query's eps, world units (resolved: :func:`resolve_eps`)
    time : seconds, or None
    skeleton : a skinned collider's skeleton pose, or None
    """

    local: np.ndarray
    want_gradient: bool
    gradient_below: float | None
    eps: float
    time: float | None = None
    skeleton: SkeletonPose | None = None

    def run(self, evaluate: Evaluate) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """``evaluate`` at these points, time and skeleton pose: (distance (n,), normal (n, 3)
        or None, velocity (n, 3) or None), collider frame."""
        if self.skeleton is None:
            return evaluate(self.local, self.want_gradient, self.gradient_below, self.time)
        return evaluate(self.local, self.want_gradient, self.gradient_below, self.time,
                        self.skeleton)


def prepare(query: ModelQuery, meters_per_unit: float) -> Evaluation:
    """Step 1: what the query asks of a collider of ``meters_per_unit`` metres per unit."""
    eps = resolve_eps(query.eps, meters_per_unit, query.pose)
    below = (gradient_threshold(eps, query.pose)
             if query.only_colliding and query.want_gradient else None)
    return Evaluation(query.pose.to_local(query.points), query.want_gradient, below, eps, query.time,
                      query.skeleton)


def require_time(query: ModelQuery, animated: bool, where: str, skeleton: dict | None = None) -> None:
    """Refuse (422 ``missing-time``) a query without ``time`` of an animated collider ``where``
    (a static collider answers with or without one), and a skeleton pose that does not fit the
    collider (``skeleton``: its ``ModelInfo.skeleton``, empty for a model without one;
    :func:`~.skeleton.require_skeleton_pose`)."""
    require_skeleton_pose(query.skeleton, query.time, skeleton, where)
    if animated and query.time is None:
        raise QueryError(f"{where} is animated: give the time (seconds) to ask it at",
                         code="missing-time")


def finish(query: ModelQuery, eps: float, distance: np.ndarray, normal: np.ndarray | None,
           velocity: np.ndarray | None = None) -> QueryResult:
    """Step 3: the query's fields from the collider-frame ``distance``, ``normal`` and
    ``velocity`` that its evaluation gave, with ``eps`` its resolved eps (world units,
    :attr:`Evaluation.eps`): distances scaled to world units, normals rotated into the world
    frame, contacts ``p + (eps - d) * n`` and velocities (module docstring) computed in float64 in
    the world frame. In collide-only mode, points with ``distance >= eps`` get ``normal`` and
    ``velocity`` [0, 0, 0] and ``contact`` equal to the point (whatever the evaluation gave
    them)."""
    pose, points = query.pose, query.points
    distance = distance * pose.scale
    collides = distance < eps
    result = QueryResult()
    if "distance" in query.fields:
        result.distance = distance.astype(np.float32)
    if normal is not None:
        normal = pose.to_world_directions(normal)
        if query.only_colliding:
            normal = np.where(collides[:, None], normal, 0.0)
    if "normal" in query.fields:
        assert normal is not None  # these fields want the gradient: the evaluation gave it
        result.normal = normal.astype(np.float32)
    if "contact" in query.fields or "velocity" in query.fields:
        assert normal is not None
        # In float64 (normal is); a zero normal leaves the point where it is, the documented
        # contact of a free point.
        contact = (eps - distance)[:, None] * normal
        contact += points  # (in place: 1M points' contacts are 24 MB; p + x == x + p exactly)
    if "contact" in query.fields:
        result.contact = contact.astype(points.dtype, copy=False)
    if "collides" in query.fields:
        result.collides = collides
    if "velocity" in query.fields:
        world = np.zeros((len(points), 3))
        if velocity is not None:  # the surface's own motion, collider units/s -> world units/s
            world += pose.to_world_directions(velocity) * pose.scale
        if query.pose_velocity is not None:  # the frame's motion, at the contact
            rate = query.pose_velocity
            world += rotate_rows(pose.to_local(contact), rate[:3, :3]) + rate[:3, 3]  # (batch-invariant)
        if query.only_colliding:
            world = np.where(collides[:, None], world, 0.0)
        result.velocity = world.astype(np.float32)
    return result


def answer_model_query(query: ModelQuery, meters_per_unit: float, evaluate: Evaluate,
                       where: str = "the collider", animated: bool = False,
                       skeleton: dict | None = None) -> QueryResult:
    """The three steps: the fields of ``query`` from a collider (``evaluate``) of
    ``meters_per_unit`` metres per unit, ``animated`` or not, with a ``skeleton`` or not (its
    ``ModelInfo.skeleton``); ``where`` names it in a refusal (:func:`require_time`,
    :func:`check_finite`)."""
    require_time(query, animated, where, skeleton)
    evaluation = prepare(query, meters_per_unit)
    result = finish(query, evaluation.eps, *evaluation.run(evaluate))
    check_finite(result, query.points, where)
    return result


def nearest_collider(world_distance: np.ndarray) -> np.ndarray:
    """The scene rule: per point, the index of the collider with the smallest world-frame signed
    distance, compared in float64; a tie goes to the first collider in the list (the lowest
    index).

    world_distance : (k, n) float64, world units, one row per collider of the scene
    Returns (n,) int32 indices into the scene's colliders.
    """
    world_distance = np.asarray(world_distance)  # (float64 or not: the same order)
    if world_distance.ndim != 2 or len(world_distance) == 0:
        raise ValueError(f"world_distance must be (k, n) with k >= 1, got {world_distance.shape}")
    return np.argmin(world_distance, axis=0).astype(np.int32)


def finish_scene(query: SceneQuery, eps: Sequence[float], answers: Sequence) -> QueryResult:
    """A scene query's fields: per point, those of the nearest collider (:func:`nearest_collider`),
    as :func:`finish` gives them for that collider, and ``collider``, its (n,) int32 index.

    eps, answers : per collider, its resolved eps (world units) and the ``(distance, normal,
        velocity)`` its evaluation gave (normal and velocity may be None), collider frame
    """
    points, n = query.points, len(query.points)
    poses = [placed.pose for placed in query.colliders]
    nearest = nearest_collider(np.stack([answer[0] * pose.scale
                                         for answer, pose in zip(answers, poses, strict=True)]))
    dtypes = {"distance": np.float32, "normal": np.float32, "contact": points.dtype,
              "collides": np.bool_, "velocity": np.float32}
    out = {f: np.empty((n, 3) if f in ("normal", "contact", "velocity") else n, dtypes[f])
           for f in query.fields}
    for i, (answer, eps_i) in enumerate(zip(answers, eps, strict=True)):
        rows = np.flatnonzero(nearest == i)
        if not len(rows):
            continue
        own = query.of_collider(i)
        rows_of: list[Any] = [None if a is None else a[rows] for a in answer]
        part = finish(dataclasses.replace(own, points=points[rows]), eps_i, *rows_of)
        for name, values in part.fields().items():
            out[name][rows] = values
    result = QueryResult(**out, collider=nearest)
    check_finite(result, points, "the colliders")
    return result


def answer_scene_query(query: SceneQuery, meters_per_unit: Sequence[float],
                       evaluate: Sequence[Evaluate], animated: Sequence[bool] | None = None,
                       skeletons: Sequence[dict] | None = None) -> QueryResult:
    """The fields of a scene query, its colliders' units, evaluations, whether each is animated
    and each one's skeleton (``ModelInfo.skeleton``, empty for none) given in its order."""
    animated = list(animated) if animated is not None else [False] * len(query.colliders)
    skeletons = list(skeletons) if skeletons is not None else [{}] * len(query.colliders)
    for i, (is_animated, skeleton) in enumerate(zip(animated, skeletons, strict=True)):
        require_time(query.of_collider(i), is_animated, f"model {query.colliders[i].model!r}",
                     skeleton)
    evaluations = [prepare(query.of_collider(i), mpu)
                   for i, mpu in zip(range(len(query.colliders)), meters_per_unit, strict=True)]
    return finish_scene(query, [e.eps for e in evaluations],
                        [e.run(f) for e, f in zip(evaluations, evaluate, strict=True)])


def check_finite(result: QueryResult, points: np.ndarray, where: str, first_row: int = 0) -> None:
    """Refuse (422 ``out-of-range``) an answer that is not a finite number: the first such row of
    ``points`` (counted from ``first_row``) and its first field that is not finite are named.
    Inside the coordinate range every distance, normal and contact is finite; a velocity is too
    while the animation's frame rate and the pose's velocity are within their bounds. This guards
    the answer's encoding (the service never sends NaN or Infinity)."""
    floats = {name: v for name, v in result.fields().items() if v.dtype.kind == "f"}
    if all(np.isfinite(v).all() for v in floats.values()):  # one cheap check per field, rows only if not
        return
    bad = {name: ~(np.isfinite(v) if v.ndim == 1 else np.isfinite(v).all(axis=1))
           for name, v in floats.items()}
    row = int(np.flatnonzero(np.logical_or.reduce(list(bad.values())))[0])
    field = next(name for name, rows in bad.items() if rows[row])
    why = (f"the velocity of {where} there overflows float32 (world units per second, with the "
           "pose and pose_velocity given)" if field == "velocity" else
           f"it lies too far from {where} (world frame, with the pose given)")
    raise QueryError(f"points row {first_row + row} ({points[row].tolist()}) has no finite {field}: "
                     f"{why}", code="out-of-range")
