"""What a query is: its points, fields, pose, ``eps`` and mode, validated once for every backend.

:class:`ModelQuery` asks one collider; :class:`SceneQuery` asks several, each with its own pose.
``build`` validates values from the Python API (the engine's ``Collider.query``, both SDK backends);
``from_body`` reads a decoded wire body (the HTTP service) and then applies the same checks, so
that the same input gets the same answer or the same :class:`~.errors.QueryError` (same status,
problem code and message) wherever it is asked. ``to_body`` is what the SDK sends.

Points are world frame, in the collider's world units (metres for the shipped models); a pose
maps the collider frame to the world frame; ``eps`` is in world units, ``None`` meaning the
collider's default (:func:`~.answers.default_eps`). ``time`` (seconds) says when an animated
collider is asked (a static one ignores it); ``pose_velocity`` (the pose's time derivative, 4x4,
1/s and world units/s) says how a moving collider's frame moves, for the ``velocity`` field.
A skinned collider is asked at a skeleton pose (:mod:`.skeleton`): ``clip`` with ``time``, or
``joint_transforms`` with optional ``joint_velocities``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from . import wire
from .errors import QueryError
from .pose import IDENTITY, MAX_COORDINATE_M, Pose, PoseError, as_pose
from .skeleton import SKELETON_KEYS, SkeletonPose, check_skeleton_pose

#: The fields a query can ask for, in canonical order.
FIELDS = ("distance", "normal", "contact", "collides", "velocity")
#: Fields that need the SDF gradient; asking only for the others skips gradient work.
GRADIENT_FIELDS = frozenset({"normal", "contact", "velocity"})
DEFAULT_FIELDS = ("distance",)
#: Most points in one call, whatever the backend: bounds the memory of one answer. (The HTTP
#: service has a smaller limit of its own, ``max_request_points``.)
MAX_POINTS = 200_000_000
#: Keys of a wire body besides a query's own: the service reads ``deadline_ms``.
TRANSPORT_KEYS = frozenset({"deadline_ms"})
#: The keys of a model query's wire body (besides :data:`TRANSPORT_KEYS`), ``points`` required:
#: the one list the reader, the OpenAPI schema and the refusals' messages follow.
QUERY_KEYS = ("points", "fields", "pose", "eps", "only_colliding", "time", "pose_velocity", *SKELETON_KEYS)
#: The keys of a scene query's wire body (besides :data:`TRANSPORT_KEYS`), the first two required.
SCENE_KEYS = ("points", "colliders", "fields", "eps", "only_colliding", "time")
#: The keys of a scene collider given as a map (the wire's only form), ``model`` required.
COLLIDER_KEYS = ("model", "pose", "time", "pose_velocity", *SKELETON_KEYS)
#: The largest ``|time|``, seconds (about 32 years): far beyond any animation, and where float64
#: still resolves a nanosecond.
MAX_TIME_S = 1e9


def check_fields(fields: Iterable[str] | str) -> tuple[str, ...]:
    """A field selection (one name or several) as a tuple in canonical order."""
    if isinstance(fields, str):
        fields = [fields]
    fields = list(fields)
    unknown = [f for f in fields if f not in FIELDS]
    if unknown:
        raise QueryError(f"unknown field(s) {unknown}; valid fields are {list(FIELDS)}",
                         code="unknown-field")
    if not fields:
        raise QueryError(f"no fields asked for; choose from {list(FIELDS)}", code="unknown-field")
    return tuple(f for f in FIELDS if f in fields)


def check_points(points) -> np.ndarray:
    """Query points as an (n, 3) float32 or float64 array (integers become float64), finite and
    within the coordinate range, world units."""
    try:
        array = np.asarray(points)
    except (TypeError, ValueError) as exc:  # ragged nested lists, objects numpy cannot convert
        raise QueryError(f"points must be an (n, 3) array of numbers: {exc}", code="bad-points") from None
    if array.dtype.kind not in "fiu":
        raise QueryError(f"points must be float32, float64 or integers, got {array.dtype}",
                         code="bad-points")
    if array.ndim == 1 and array.size == 0:
        array = array.reshape(0, 3)
    if array.ndim != 2 or array.shape[1] != 3:
        raise QueryError(f"points must have shape (n, 3), got {list(array.shape)}", code="bad-points")
    if len(array) > MAX_POINTS:
        raise QueryError(f"too many points in one call: {len(array)} > {MAX_POINTS}",
                         status=413, code="too-many-points")
    if array.dtype not in (np.float32, np.float64):
        array = array.astype(np.float64)
    # Two reductions over all coordinates, no temporaries (a NaN propagates and fails the
    # comparison); rows only for the message.
    if array.size and not max(array.max(), -array.min()) <= MAX_COORDINATE_M:
        finite = np.isfinite(array).all(axis=1)
        if not finite.all():
            bad = int(np.flatnonzero(~finite)[0])
            raise QueryError(f"points contain NaN or Inf (first at row {bad}: {array[bad].tolist()})",
                             code="bad-points")
        bad = int(np.flatnonzero(~(np.abs(array) <= MAX_COORDINATE_M).all(axis=1))[0])
        raise QueryError(f"points outside the coordinate range +-{MAX_COORDINATE_M:g} (world units; "
                         f"first at row {bad}: {array[bad].tolist()})", code="bad-points")
    return array


def check_eps(eps) -> float | None:
    """The collision offset: ``None`` (the collider's default), or a finite number of world units
    in ``[0, MAX_COORDINATE_M]`` (the coordinate range: a large eps is odd but well defined; a
    negative one would put contacts inside the surface)."""
    if eps is None:
        return None
    value = check_number(eps, "eps")
    if not 0 <= value <= MAX_COORDINATE_M:
        raise QueryError(f"eps={value} is outside [0, {MAX_COORDINATE_M:g}] (world units)",
                         code="eps-out-of-range")
    return value


def check_pose(pose, where: str = "pose") -> Pose:
    """A pose (4x4 array-like, :class:`Pose` or ``None`` for the identity) validated; the refusal
    names ``where`` it was given (``pose``, ``colliders[2].pose``)."""
    try:
        return as_pose(pose)
    except PoseError as exc:
        message = str(exc)  # its own messages start with "pose ..."
        raise QueryError(message if message.startswith(where) else f"{where}: {message}",
                         code="bad-pose") from None


def check_time(time, where: str = "time") -> float | None:
    """When an animated collider is asked: ``None`` (a static collider's query), or a finite
    number of seconds within +-:data:`MAX_TIME_S`."""
    if time is None:
        return None
    value = check_number(time, where, code="bad-time")
    if abs(value) > MAX_TIME_S:
        raise QueryError(f"{where}={value} is outside +-{MAX_TIME_S:g} s", code="bad-time")
    return value


def check_pose_velocity(value, where: str = "pose_velocity",
                        code: str = "bad-pose-velocity") -> np.ndarray | None:
    """The time derivative of a pose (4x4: d(s R)/dt in 1/s, dt/dt in world units/s, bottom row
    zero), or None (a pose that does not move). Its entries are bounded by the coordinate
    range. (A joint's velocity follows the same rule, refused with its own ``code``.)"""
    if value is None:
        return None
    try:
        m = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise QueryError(f"{where} must be a 4x4 matrix of numbers: {exc}", code=code) from None
    if m.shape != (4, 4):
        raise QueryError(f"{where} must be a 4x4 matrix, got shape {m.shape}", code=code)
    if not (np.isfinite(m).all() and (np.abs(m) <= MAX_COORDINATE_M).all()):
        raise QueryError(f"{where} must hold finite numbers within +-{MAX_COORDINATE_M:g}",
                         code=code)
    if m[3].any():
        raise QueryError(f"{where} bottom row must be [0, 0, 0, 0] (a pose's bottom row does not "
                         f"change), got {m[3].tolist()}", code=code)
    return m


@dataclass(frozen=True)
class SceneCollider:
    """One collider of a scene query: a model name, its pose (4x4, collider -> world, or None for
    the identity) and, optionally, the time it is asked at (seconds; None: the scene query's
    own) and its pose's velocity (4x4, see :func:`check_pose_velocity`); a skinned model's
    skeleton pose: ``clip`` or ``joint_transforms`` (J, 4, 4) with ``joint_velocities``
    (:mod:`.skeleton`)."""

    model: str
    pose: Any = None
    time: float | None = None
    pose_velocity: Any = None
    clip: str | None = None
    joint_transforms: Any = None
    joint_velocities: Any = None


class Placed(NamedTuple):
    """A validated scene collider: ``model`` name, ``pose``, ``time`` (seconds or None),
    ``pose_velocity`` ((4, 4) or None) and ``skeleton`` (a skinned model's pose, or None)."""

    model: str
    pose: Pose
    time: float | None = None
    pose_velocity: np.ndarray | None = None
    skeleton: SkeletonPose | None = None


#: What a scene collider must be, for the refusals (from :data:`COLLIDER_KEYS`).
COLLIDER_FORM = ('{"model": name} with optional '
                 + ", ".join(f'"{key}"' for key in COLLIDER_KEYS if key != "model"))


def _is_collider_map(item) -> bool:
    return (isinstance(item, dict) and isinstance(item.get("model"), str)
            and set(item) <= set(COLLIDER_KEYS))


def check_colliders(items: Sequence, time=None) -> tuple[Placed, ...]:
    """A scene's colliders, validated: from :class:`SceneCollider`, ``(model, pose)`` pairs,
    ``{"model": name, "pose": 4x4, "time": s, "pose_velocity": 4x4}`` maps (all but ``model``
    optional) or bare model names; ``time`` is the time of those that give none."""
    if isinstance(items, (str, bytes, dict)) or not isinstance(items, Sequence) or not items:
        raise QueryError(f"colliders must be a non-empty list of {COLLIDER_FORM}, got {items!r:.200}",
                         code="bad-colliders")
    out = []
    for i, given in enumerate(items):
        item = given
        if isinstance(item, SceneCollider):
            item = {"model": item.model, "pose": item.pose, "time": item.time,
                    "pose_velocity": item.pose_velocity, "clip": item.clip,
                    "joint_transforms": item.joint_transforms,
                    "joint_velocities": item.joint_velocities}
        elif isinstance(item, str):
            item = {"model": item}
        elif isinstance(item, (tuple, list)) and len(item) == 2:
            item = {"model": item[0], "pose": item[1]}
        if not _is_collider_map(item):
            raise _bad_collider(i, given)  # named as the caller gave it
        own_time = check_time(item.get("time"), f"colliders[{i}].time")
        out.append(Placed(item["model"], check_pose(item.get("pose"), f"colliders[{i}].pose"),
                          own_time if own_time is not None else time,
                          check_pose_velocity(item.get("pose_velocity"), f"colliders[{i}].pose_velocity"),
                          check_skeleton_pose(**{k: item.get(k) for k in SKELETON_KEYS},
                                              where=f"colliders[{i}].")))
    return tuple(out)


def _bad_collider(index: int, item) -> QueryError:
    got = f"a map with keys {sorted(map(str, item))}" if isinstance(item, dict) else f"{item!r:.60}"
    return QueryError(f"colliders[{index}] must be {COLLIDER_FORM}, got {got}", code="bad-colliders")


@dataclass(frozen=True)
class ModelQuery:
    """A validated query of one collider.

    points : (n, 3) float32 or float64, world frame (finite, within the coordinate range)
    fields : the fields to answer, canonical order
    pose : collider frame -> world frame
    eps : collision offset, world units; None: the collider's default
    only_colliding : ``normal``, ``contact`` and ``velocity`` only where ``distance < eps``
    time : seconds, when an animated collider is asked (None: a static one)
    pose_velocity : (4, 4) the pose's time derivative, or None (a frame that does not move)
    skeleton : a skinned collider's skeleton pose (:class:`~.skeleton.SkeletonPose`), or None
    """

    points: np.ndarray
    fields: tuple[str, ...] = DEFAULT_FIELDS
    pose: Pose = IDENTITY
    eps: float | None = None
    only_colliding: bool = False
    time: float | None = None
    pose_velocity: np.ndarray | None = None
    skeleton: SkeletonPose | None = None

    @classmethod
    def build(cls, points, fields: Iterable[str] | str = DEFAULT_FIELDS, pose=None, eps=None,
              only_colliding: bool = False, time=None, pose_velocity=None, clip=None,
              joint_transforms=None, joint_velocities=None) -> ModelQuery:
        """Validate the Python API's arguments (checked in this order: fields, points, pose,
        eps, time, pose velocity, skeleton pose); raises :class:`~.errors.QueryError`."""
        return cls(fields=check_fields(fields), points=check_points(points), pose=check_pose(pose),
                   eps=check_eps(eps), only_colliding=bool(only_colliding), time=check_time(time),
                   pose_velocity=check_pose_velocity(pose_velocity),
                   skeleton=check_skeleton_pose(clip, joint_transforms, joint_velocities))

    @property
    def want_gradient(self) -> bool:
        return not GRADIENT_FIELDS.isdisjoint(self.fields)

    def to_body(self) -> dict[str, Any]:
        """The wire body (numpy arrays as values; :func:`~.wire.dumps` encodes them). Defaults
        are left out: a body without them is what every server version reads."""
        body: dict[str, Any] = {"points": self.points, "fields": list(self.fields)}
        if self.pose.source is not None:
            body["pose"] = self.pose.source
        for key in ("eps", "time", "pose_velocity"):
            if getattr(self, key) is not None:
                body[key] = getattr(self, key)
        if self.only_colliding:
            body["only_colliding"] = True
        if self.skeleton is not None:
            body.update(self.skeleton.to_body())
        return body

    @classmethod
    def from_body(cls, body: dict, max_points: int = MAX_POINTS) -> ModelQuery:
        """The query of a decoded wire body (:func:`~.wire.loads`); more than ``max_points``
        points is a 413. Checked in :meth:`build`'s order, then ``only_colliding``. Raises
        :class:`~.errors.QueryError`."""
        _check_keys(body, QUERY_KEYS, ("points",))
        return cls(fields=_wire_fields(body), points=_wire_points(body["points"], max_points),
                   pose=_wire_pose(body, "pose"), eps=check_eps(_optional(body, "eps")),
                   time=check_time(_optional(body, "time")),
                   pose_velocity=_wire_pose_velocity(body, "pose_velocity"),
                   skeleton=_wire_skeleton(body),
                   only_colliding=_wire_flag(body, "only_colliding"))


@dataclass(frozen=True)
class SceneQuery:
    """A validated query of several colliders: per point, the fields of the nearest one.

    colliders : :class:`Placed` per collider (model, pose, time, pose velocity), in the
        caller's order (the answer's ``collider`` field indexes it); the other fields as in
        :class:`ModelQuery`
    """

    points: np.ndarray
    colliders: tuple[Placed, ...]
    fields: tuple[str, ...] = DEFAULT_FIELDS
    eps: float | None = None
    only_colliding: bool = False

    @classmethod
    def build(cls, points, colliders: Sequence, fields: Iterable[str] | str = DEFAULT_FIELDS,
              eps=None, only_colliding: bool = False, time=None) -> SceneQuery:
        """Validate the Python API's arguments (:func:`check_colliders` lists the forms of
        ``colliders``; ``time``: theirs when they give none); raises
        :class:`~.errors.QueryError`."""
        fields = check_fields(fields)
        time = check_time(time)
        return cls(fields=fields, colliders=check_colliders(colliders, time),
                   points=check_points(points), eps=check_eps(eps),
                   only_colliding=bool(only_colliding))

    @property
    def want_gradient(self) -> bool:
        return not GRADIENT_FIELDS.isdisjoint(self.fields)

    def of_collider(self, index: int) -> ModelQuery:
        """The query that collider ``index`` answers for its part: these points under its pose,
        at its time."""
        placed = self.colliders[index]
        return ModelQuery(self.points, self.fields, placed.pose, self.eps, self.only_colliding,
                          placed.time, placed.pose_velocity, placed.skeleton)

    def to_body(self) -> dict[str, Any]:
        body = ModelQuery(self.points, self.fields, IDENTITY, self.eps, self.only_colliding).to_body()
        # Nested in a list, arrays travel as nested lists: wire.dumps encodes top-level arrays only.
        colliders = []
        for placed in self.colliders:
            item: dict[str, Any] = {"model": placed.model}
            if placed.pose.source is not None:
                item["pose"] = placed.pose.source.tolist()
            if placed.time is not None:
                item["time"] = placed.time
            if placed.pose_velocity is not None:
                item["pose_velocity"] = placed.pose_velocity.tolist()
            if placed.skeleton is not None:
                item.update(placed.skeleton.to_body(nested=True))
            colliders.append(item)
        body["colliders"] = colliders
        return body

    @classmethod
    def from_body(cls, body: dict, max_points: int = MAX_POINTS,
                  max_colliders: int | None = None) -> SceneQuery:
        """As :meth:`ModelQuery.from_body`; more than ``max_colliders`` colliders is a 413. A
        top-level ``time`` is the time of the colliders that give none."""
        _check_keys(body, SCENE_KEYS, ("points", "colliders"))
        fields = _wire_fields(body)  # build's order: fields, time, colliders, points, eps
        time = check_time(_optional(body, "time"))
        items = body["colliders"]
        if not isinstance(items, list):
            check_colliders(items)  # refuses it, saying what colliders must be
        if max_colliders is not None and len(items) > max_colliders:
            raise QueryError(f"{len(items)} colliders exceed max_scene_colliders={max_colliders}",
                             status=413, code="too-many-colliders")
        if not items:
            check_colliders(items)
        colliders = []
        for i, item in enumerate(items):  # on the wire a collider is a map, its arrays wire arrays
            if not _is_collider_map(item):
                raise _bad_collider(i, item)
            own_time = check_time(_optional(item, "time", f"colliders[{i}].time"),
                                  f"colliders[{i}].time")
            colliders.append(Placed(
                item["model"], _wire_pose(item, "pose", f"colliders[{i}].pose"),
                own_time if own_time is not None else time,
                _wire_pose_velocity(item, "pose_velocity", f"colliders[{i}].pose_velocity"),
                _wire_skeleton(item, f"colliders[{i}].")))
        return cls(fields=fields, colliders=tuple(colliders),
                   points=_wire_points(body["points"], max_points),
                   eps=check_eps(_optional(body, "eps")),
                   only_colliding=_wire_flag(body, "only_colliding"))


# -- reading wire bodies: the JSON / msgpack types first, then the checks above -----------------

_ABSENT = object()


def _check_keys(body: dict, allowed: tuple[str, ...], required: tuple[str, ...]) -> None:
    unknown = sorted(set(body) - set(allowed) - TRANSPORT_KEYS)
    if unknown:
        raise QueryError(f"unknown key(s) {unknown}; valid keys are {sorted({*allowed, *TRANSPORT_KEYS})}",
                         code="unknown-key")
    for key in required:
        if key not in body:
            raise QueryError(f"the body has no {key!r}", code=f"missing-{key}")


def _optional(body: dict, key: str, where: str | None = None):
    """``body[key]``, or None when absent. A key given as null is refused: the documented types
    have no null (leave the key out for its default)."""
    value = body.get(key, _ABSENT)
    if value is _ABSENT:
        return None
    if value is None:
        raise QueryError(f"{where or key} must not be null (leave it out for its default)",
                         code=f"bad-{key.replace('_', '-')}")
    return value


def check_number(value, name: str, *, positive: bool = False, code: str | None = None) -> float:
    """``value`` as a finite float (bools are not numbers; > 0 when ``positive``), else a refusal
    naming ``name`` with problem code ``code`` (default ``bad-<name>``)."""
    code = code or f"bad-{name.replace('_', '-')}"
    number = None
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_)):
        try:
            number = float(value)
        except OverflowError:  # a JSON integer with hundreds of digits
            number = None
    if number is None or not math.isfinite(number):
        raise QueryError(f"{name} must be a finite number, got {value!r:.60}", code=code)
    if positive and number <= 0:
        raise QueryError(f"{name} must be > 0, got {value!r:.60}", code=code)
    return number


def read_deadline_ms(body: dict) -> float | None:
    """A wire body's ``deadline_ms`` (milliseconds > 0: how long its caller waits), or None."""
    value = _optional(body, "deadline_ms")
    return None if value is None else check_number(value, "deadline_ms", positive=True)


def _wire_points(value, max_points: int) -> np.ndarray:
    """Points of a wire body: ``<f4`` or ``<f8`` arrays (JSON numbers read as float64), then
    :func:`check_points`; more than ``max_points`` is a 413."""
    try:
        array = wire.decode_array(value, "points")
    except wire.WireError as exc:
        raise QueryError(str(exc), code="bad-points") from None
    if array.dtype.kind == "b" or (array.size and array.dtype not in (np.float32, np.float64)):
        raise QueryError(f"points must be float32 or float64, got {array.dtype}", code="bad-points")
    if array.ndim == 1 and array.size == 0:
        array = array.reshape(0, 3).astype(np.float64)
    if array.ndim == 2 and array.shape[1] == 3 and len(array) > max_points:
        raise QueryError(f"{len(array)} points exceed max_request_points={max_points}", status=413,
                         code="too-many-points")
    return check_points(array)


def _wire_fields(body: dict) -> tuple[str, ...]:
    value = _optional(body, "fields")
    if value is None:
        return DEFAULT_FIELDS
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise QueryError(f"fields must be a list of strings, got {value!r:.60}", code="bad-fields")
    return check_fields(value)


def _wire_pose(body: dict, key: str, where: str | None = None) -> Pose:
    where = where or key
    value = body.get(key, _ABSENT)
    if value is _ABSENT:
        return IDENTITY
    if value is None:
        raise QueryError(f"{where} must be a 4x4 matrix, got null (leave it out for the identity)",
                         code="bad-pose")
    try:
        matrix = wire.decode_array(value, where)
    except wire.WireError as exc:
        raise QueryError(str(exc), code="bad-pose") from None
    if matrix.dtype.kind == "b":
        raise QueryError(f"{where}: must hold numbers, got {matrix.dtype}", code="bad-pose")
    return check_pose(matrix, where)


def _wire_pose_velocity(body: dict, key: str, where: str | None = None) -> np.ndarray | None:
    where = where or key
    value = _optional(body, key, where)
    if value is None:
        return None
    try:
        matrix = wire.decode_array(value, where)
    except wire.WireError as exc:
        raise QueryError(str(exc), code="bad-pose-velocity") from None
    if matrix.dtype.kind == "b":
        raise QueryError(f"{where}: must hold numbers, got {matrix.dtype}", code="bad-pose-velocity")
    return check_pose_velocity(matrix, where)


def _wire_skeleton(body: dict, where: str = "") -> SkeletonPose | None:
    """The skeleton pose of a wire body (or scene collider map): ``clip`` a string, the joint
    arrays wire arrays, then :func:`~.skeleton.check_skeleton_pose`."""
    values = {}
    for key in SKELETON_KEYS:
        code = f"bad-{key.replace('_', '-')}"
        value = _optional(body, key, f"{where}{key}")
        if value is not None and key != "clip":
            try:
                value = wire.decode_array(value, f"{where}{key}")
            except wire.WireError as exc:
                raise QueryError(str(exc), code=code) from None
            if value.dtype.kind == "b":
                raise QueryError(f"{where}{key}: must hold numbers, got {value.dtype}", code=code)
        values[key] = value
    return check_skeleton_pose(**values, where=where)


def _wire_flag(body: dict, key: str) -> bool:
    value = _optional(body, key)
    if value is None:
        return False
    if not isinstance(value, bool):
        raise QueryError(f"{key} must be true or false, got {value!r:.60}",
                         code=f"bad-{key.replace('_', '-')}")
    return value
