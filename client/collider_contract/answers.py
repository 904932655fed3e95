"""How a validated query is answered, given a way to evaluate a collider: the eps policy, the
fields' assembly in the world frame, and the scene rule. One home for the engine, the SDK's
embedded backend and the HTTP service, so that their answers are the same by construction.

Answering a :class:`~.queries.ModelQuery` is three steps:

1. :func:`prepare`: the points in the collider frame, whether the gradient is needed and below
   which distance (collide-only mode), and the query's eps in world units (:func:`resolve_eps`);
2. an *evaluation* of the collider at those points (:data:`Evaluate`: the engine's
   ``Collider.query_local``), which a batching server may join with other requests';
3. :func:`finish`: the fields in the world frame, given the resolved eps.

:func:`answer_model_query` is the three in a row. A :class:`~.queries.SceneQuery` prepares and
evaluates each collider, then :func:`finish_scene` keeps, per point, the nearest collider's fields
(:func:`nearest_collider`). The fields:

- ``distance`` : (n,) float32, world units, signed, negative inside;
- ``normal``   : (n, 3) float32, unit outward normal (normalised SDF gradient), world frame;
- ``contact``  : (n, 3), the point moved to the offset surface ``p + (eps - d) * normal``,
  world frame, in the dtype of the query points (float32 or float64);
- ``collides`` : (n,) bool, ``d < eps``.

Collide-only mode (``only_colliding``): ``normal`` and ``contact`` are computed only for the points
that collide; for the others ``normal`` is ``[0, 0, 0]`` and ``contact`` is the point itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from .errors import QueryError
from .pose import Pose
from .queries import ModelQuery, SceneQuery
from .results import QueryResult

#: The default collision offset: 1 mm, whatever the collider's units.
DEFAULT_EPS_METERS = 1e-3

#: ``evaluate(local, want_gradient, gradient_below) -> (distance, normal)``: a collider's signed
#: distance at collider-frame points ``local`` (m, 3) float64, collider units, and when
#: ``want_gradient`` its unit normal (m, 3) float64 (else None), only where ``distance`` is below
#: ``gradient_below`` (None: everywhere; a number or an (m,) array, collider units; the other
#: rows zero). The engine's ``Collider.query_local``.
Evaluate = Callable[[np.ndarray, bool, "float | np.ndarray | None"],
                    "tuple[np.ndarray, np.ndarray | None]"]


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
    want_gradient : whether ``normal`` or ``contact`` was asked for
    gradient_below : collider units: a normal is needed only below this distance (collide-only),
        or None (everywhere, when ``want_gradient``)
    eps : the query's eps, world units (resolved: :func:`resolve_eps`)
    """

    local: np.ndarray
    want_gradient: bool
    gradient_below: float | None
    eps: float

    def run(self, evaluate: Evaluate) -> tuple[np.ndarray, np.ndarray | None]:
        """``evaluate`` at these points: (distance (n,), normal (n, 3) or None), collider frame."""
        return evaluate(self.local, self.want_gradient, self.gradient_below)


def prepare(query: ModelQuery, meters_per_unit: float) -> Evaluation:
    """Step 1: what the query asks of a collider of ``meters_per_unit`` metres per unit."""
    eps = resolve_eps(query.eps, meters_per_unit, query.pose)
    below = (gradient_threshold(eps, query.pose)
             if query.only_colliding and query.want_gradient else None)
    return Evaluation(query.pose.to_local(query.points), query.want_gradient, below, eps)


def finish(query: ModelQuery, eps: float, distance: np.ndarray,
           normal: np.ndarray | None) -> QueryResult:
    """Step 3: the query's fields from the collider-frame ``distance`` and ``normal`` that its
    evaluation gave, with ``eps`` its resolved eps (world units, :attr:`Evaluation.eps`):
    distances scaled to world units, normals rotated into the world frame, contacts
    ``p + (eps - d) * n`` computed in float64 in the world frame. In collide-only mode, points
    with ``distance >= eps`` get ``normal`` [0, 0, 0] and ``contact`` equal to the point (whatever
    ``normal`` holds for them)."""
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
        result.normal = normal.astype(np.float32)
    if "contact" in query.fields:
        # In float64 (normal is); a zero normal leaves the point where it is, the documented
        # contact of a free point.
        contact = points + (eps - distance)[:, None] * normal
        result.contact = contact.astype(points.dtype)
    if "collides" in query.fields:
        result.collides = collides
    return result


def answer_model_query(query: ModelQuery, meters_per_unit: float, evaluate: Evaluate,
                       where: str = "the collider") -> QueryResult:
    """The three steps: the fields of ``query`` from a collider (``evaluate``) of
    ``meters_per_unit`` metres per unit; ``where`` names it in a refusal (:func:`check_finite`)."""
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

    eps, answers : per collider, its resolved eps (world units) and the ``(distance, normal or
        None)`` its evaluation gave, collider frame
    """
    points, n = query.points, len(query.points)
    poses = [pose for _, pose in query.colliders]
    nearest = nearest_collider(np.stack([d * pose.scale for (d, _), pose in zip(answers, poses)]))
    dtypes = {"distance": np.float32, "normal": np.float32, "contact": points.dtype,
              "collides": np.bool_}
    out = {f: np.empty((n, 3) if f in ("normal", "contact") else n, dtypes[f]) for f in query.fields}
    for i, (distance, normal) in enumerate(answers):
        rows = np.flatnonzero(nearest == i)
        if not len(rows):
            continue
        part = finish(ModelQuery(points[rows], query.fields, poses[i], query.eps, query.only_colliding),
                      eps[i], distance[rows], None if normal is None else normal[rows])
        for name, values in part.fields().items():
            out[name][rows] = values
    result = QueryResult(**out, collider=nearest)
    check_finite(result, points, "the colliders")
    return result


def answer_scene_query(query: SceneQuery, meters_per_unit: Sequence[float],
                       evaluate: Sequence[Evaluate]) -> QueryResult:
    """The fields of a scene query, its colliders' units and evaluations given in its order."""
    evaluations = [prepare(query.of_collider(i), mpu) for i, mpu in enumerate(meters_per_unit)]
    return finish_scene(query, [e.eps for e in evaluations],
                        [e.run(f) for e, f in zip(evaluations, evaluate)])


def check_finite(result: QueryResult, points: np.ndarray, where: str, first_row: int = 0) -> None:
    """Refuse (422 ``out-of-range``) an answer that is not a finite number: the first such row of
    ``points`` is named (counted from ``first_row``). Inside the coordinate range every answer is
    finite; this guards the answer's encoding (the service never sends NaN or Infinity)."""
    floats = [v for v in result.fields().values() if v.dtype.kind == "f"]
    if all(np.isfinite(v).all() for v in floats):  # one cheap check per field, rows only if not
        return
    bad = np.zeros(len(points), dtype=bool)
    for values in floats:
        bad |= ~(np.isfinite(values) if values.ndim == 1 else np.isfinite(values).all(axis=1))
    row = int(np.flatnonzero(bad)[0])
    raise QueryError(f"points row {first_row + row} ({points[row].tolist()}) has no finite answer: it "
                     f"lies too far from {where} (world frame, with the pose given)", code="out-of-range")
