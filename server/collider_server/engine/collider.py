"""The one query interface every collider kind implements.

A collider answers, for world-frame points, the fields a caller names:

- ``distance`` : (n,) float32, world units, signed, negative inside;
- ``normal``   : (n, 3) float32, unit outward normal (normalised SDF gradient), world frame;
- ``contact``  : (n, 3), the point moved to the offset surface ``p + (eps - d) * normal``,
  world frame, in the dtype of the query points (float32 or float64);
- ``collides`` : (n,) bool, ``d < eps``.

Subclasses only evaluate the SDF (and its gradient when asked) on collider-frame points inside
their domain; this module does validation, pose handling, chunking, the out-of-domain rule and the
assembly of the fields. Only the fields asked for are computed: no gradient work is done for
``distance`` or ``collides`` alone.

Collide-only mode (``only_colliding=True``): ``normal`` and ``contact`` are computed only for the
points that collide (``distance < eps``); the gradient is evaluated in a second pass over just
those points, after a distance-only pass over all of them. For the other points ``normal`` is
``[0, 0, 0]`` and ``contact`` is the point itself; ``collides`` tells the two apart. A cloth
simulator that only moves colliding points needs nothing more.
"""

from __future__ import annotations

import abc
import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar, Iterable

import numpy as np

from collider_contract import (
    GRADIENT_FIELDS,
    MAX_COORDINATE_M,
    Pose,
    QueryResult,
    as_pose,
    check_fields,
)

DEFAULT_EPS_METERS = 1e-3
MAX_POINTS_PER_CALL = 200_000_000


@dataclass
class ColliderInfo:
    """What a collider is; stored as JSON in its model file.

    name : model name (the file stem in a model repository)
    kind : "neural", "voxel", "mesh" or "kdtree"
    units : length unit of the collider frame, e.g. "m"
    meters_per_unit : metres in one unit (1.0 for metres); sets the default eps of 1 mm
    domain_min, domain_max : (3,) corners of the box, collider frame, where the model is defined
    source : the mesh it was made from (file name, sha256, faces, transform applied, ...)
    settings : kind-specific settings (architecture, resolution, training or baking options)
    accuracy : the latest evaluation against the exact SDF (filled by ``collider eval``)
    approximate : True when the kind is not exact by construction (kdtree)
    """

    name: str
    kind: str
    domain_min: list[float]
    domain_max: list[float]
    units: str = "m"
    meters_per_unit: float = 1.0
    source: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    accuracy: dict = field(default_factory=dict)
    approximate: bool = False

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ColliderInfo":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"unknown collider info keys: {sorted(unknown)}")
        return cls(**data)

    @property
    def default_eps(self) -> float:
        """1 mm expressed in the collider's units."""
        return DEFAULT_EPS_METERS / self.meters_per_unit

    def default_world_eps(self, pose: Pose) -> float:
        """The eps of a query that gives none: :attr:`default_eps` in world units under
        ``pose`` (collider units times the pose's scale)."""
        return self.default_eps * pose.scale


def check_points(points) -> np.ndarray:
    """Validate query points: an (n, 3) array of finite float32/float64 numbers."""
    try:
        array = np.asarray(points)
    except (TypeError, ValueError) as exc:  # ragged nested lists, objects numpy cannot convert
        raise ValueError(f"points must be an (n, 3) array of numbers: {exc}") from None
    if array.dtype.kind not in "fiu":
        raise ValueError(f"points must be numbers, got dtype {array.dtype}")
    if array.ndim == 1 and array.size == 0:
        array = array.reshape(0, 3)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {array.shape}")
    if len(array) > MAX_POINTS_PER_CALL:
        raise ValueError(f"too many points in one call: {len(array)} > {MAX_POINTS_PER_CALL}")
    if array.dtype not in (np.float32, np.float64):
        array = array.astype(np.float64)
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise ValueError(f"points contain NaN or Inf (first at row {bad}: {array[bad].tolist()})")
    inside = (np.abs(array) <= MAX_COORDINATE_M).all(axis=1)
    if not inside.all():
        bad = int(np.flatnonzero(~inside)[0])
        raise ValueError(f"points outside the coordinate range +-{MAX_COORDINATE_M:g} (world units; "
                         f"first at row {bad}: {array[bad].tolist()})")
    return array


def check_eps(eps: float) -> float:
    """Validate a collision offset: a finite number, world units (any sign: a negative eps asks
    for contact inside the surface; the HTTP service narrows it to ``[0, domain diagonal]``)."""
    try:
        value = float(eps)
    except (TypeError, ValueError):
        raise ValueError(f"eps must be a number, got {eps!r}") from None
    if not np.isfinite(value):
        raise ValueError(f"eps must be finite, got {value}")
    if abs(value) > MAX_COORDINATE_M:
        raise ValueError(f"eps={value:g} is outside the coordinate range +-{MAX_COORDINATE_M:g} "
                         "(world units)")
    return value


def unit_vectors(vectors: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Normalise rows of ``vectors``; rows of (near) zero length take the matching row of
    ``fallback`` (already unit), so the result never holds NaN."""
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.where(length < 1e-20, fallback, vectors / np.maximum(length, 1e-20))


def _domain_corner(value, name: str) -> np.ndarray:
    """A domain corner from (untrusted) metadata: (3,) float64, finite."""
    try:
        corner = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        corner = None
    if corner is None or corner.shape != (3,) or not np.isfinite(corner).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return corner


class Collider(abc.ABC):
    """Base class of every collider kind. See the module docstring for the fields."""

    kind: ClassVar[str]
    #: Points evaluated per chunk; bounds the memory of one call whatever its size.
    chunk_points: ClassVar[int] = 262_144
    #: Whether points outside the domain box get the conservative clamped answer.
    clamps_to_domain: ClassVar[bool] = True

    def __init__(self, info: ColliderInfo):
        self.info = info
        self.domain_min = _domain_corner(info.domain_min, "domain_min")
        self.domain_max = _domain_corner(info.domain_max, "domain_max")
        if not (self.domain_min < self.domain_max).all():
            raise ValueError(f"domain_min must be below domain_max on every axis, got "
                             f"{self.domain_min.tolist()} and {self.domain_max.tolist()}")
        if not (isinstance(info.meters_per_unit, (int, float)) and info.meters_per_unit > 0):
            raise ValueError(f"meters_per_unit must be a number > 0, got {info.meters_per_unit!r}")

    # -- what a kind implements -------------------------------------------------------------

    @abc.abstractmethod
    def evaluate(self, local: np.ndarray, want_gradient: bool):
        """SDF at collider-frame points ``local`` (m, 3) float64, inside the domain box.

        Returns ``(distance (m,), gradient (m, 3) or None)`` in collider units; the gradient need
        not be unit length and is only computed when ``want_gradient``.
        """

    @abc.abstractmethod
    def tensors(self) -> dict[str, np.ndarray]:
        """The arrays that, with :attr:`info`, define the collider (saved in the model file)."""

    @classmethod
    @abc.abstractmethod
    def from_tensors(cls, info: ColliderInfo, tensors: dict[str, np.ndarray], device=None):
        """Rebuild the collider from its saved arrays. Raises ValueError if they do not fit."""

    @property
    def device(self) -> str:
        return "cpu"

    def nbytes(self) -> int:
        """Memory of the collider's arrays in bytes."""
        return sum(int(a.nbytes) for a in self.tensors().values())

    # -- the query ----------------------------------------------------------------------------

    def query(
        self,
        points,
        fields: Iterable[str] | str = ("distance",),
        pose: "Pose | np.ndarray | None" = None,
        eps: float | None = None,
        only_colliding: bool = False,
    ) -> QueryResult:
        """Answer ``fields`` for world-frame ``points``.

        points : (n, 3) float32 or float64, world units and frame (n may be 0)
        fields : any of ``distance``, ``normal``, ``contact``, ``collides``
        pose : (4, 4) collider frame -> world frame (rigid, optionally uniform scale);
            ``None`` is the identity
        eps : collision offset, world units; ``None``: 1 mm in the collider's units times the
            pose's scale (:meth:`ColliderInfo.default_world_eps`)
        only_colliding : compute ``normal`` and ``contact`` only where ``distance < eps``; the
            other points get ``normal`` [0, 0, 0] and ``contact`` equal to the point
        Returns a :class:`QueryResult` holding exactly the fields asked for, world frame.
        """
        fields = check_fields(fields)
        points = check_points(points)
        pose = as_pose(pose)
        eps = self.info.default_world_eps(pose) if eps is None else check_eps(eps)
        want_gradient = not GRADIENT_FIELDS.isdisjoint(fields)
        below = gradient_threshold(eps, pose) if only_colliding and want_gradient else None
        distance, normal = self.query_local(pose.to_local(points), want_gradient, below)
        return assemble_result(points, pose, eps, fields, distance, normal, only_colliding)

    def query_local(self, local: np.ndarray, want_gradient: bool, gradient_below=None):
        """Distance and unit normal at collider-frame points, in chunks (bounded memory).

        local : (n, 3) float64, collider frame and units
        gradient_below : None (a normal for every point when ``want_gradient``), or a number or
            an (n,) float64 array, collider units: a normal only where ``distance`` is below it
            (:func:`gradient_threshold`); the other rows of ``normal`` are zero. An array lets a
            batch join requests with different eps and poses (+inf: every point; -inf: none).
        Returns ``(distance (n,) float64, normal (n, 3) float64 unit or None)``, collider frame.
        This is the step a batching server coalesces across requests; :func:`assemble_result`
        then turns it into one request's fields.
        """
        n = len(local)
        distance = np.empty(n)  # float64, as is normal
        normal = np.empty((n, 3)) if want_gradient else None
        if want_gradient and gradient_below is not None:
            gradient_below = np.broadcast_to(gradient_below, (n,))
        for start in range(0, n, self.chunk_points):
            stop = min(start + self.chunk_points, n)
            chunk = local[start:stop]
            if not want_gradient or gradient_below is None:
                d, g = self._evaluate_anywhere(chunk, want_gradient)
                distance[start:stop] = d
                if want_gradient:
                    normal[start:stop] = self._unit_normals(g, chunk)
                continue
            # Collide-only: distances of all, then the gradient pass over those below the bar.
            d, _ = self._evaluate_anywhere(chunk, False)
            distance[start:stop] = d
            normal[start:stop] = 0.0
            rows = np.flatnonzero(d < gradient_below[start:stop])
            if len(rows):
                _, g = self._evaluate_anywhere(chunk[rows], True)
                normal[start + rows] = self._unit_normals(g, chunk[rows])
        return distance, normal

    def _evaluate_anywhere(self, local: np.ndarray, want_gradient: bool):
        """:meth:`evaluate` extended outside the domain box by a conservative rule.

        With ``c`` the point clamped into the box and ``f(c)`` the model's value there:
        ``d(p) = |p - c| + max(f(c), 0)``, never below the distance to the box (a model knows
        nothing beyond its box; one whose values on the box are negative is cut off there). The
        normal is the direction to ``p`` from ``c - f(c) n(c)``, the surface point that ``c``'s
        own answer suggests: equal to ``n(c)`` on the box, so continuous with the inside, and
        tending to the direction away from the object far from it."""
        if not self.clamps_to_domain:
            return self.evaluate(local, want_gradient)
        clamped = np.clip(local, self.domain_min, self.domain_max)
        outside = (clamped != local).any(axis=1)
        if not outside.any():
            return self.evaluate(local, want_gradient)
        d, g = self.evaluate(clamped, want_gradient)
        away = local - clamped
        box_distance = np.linalg.norm(away, axis=1)
        d_box = d
        d = np.where(outside, np.maximum(d, 0.0) + box_distance, d)
        if want_gradient:
            away_unit = away / np.where(outside, box_distance, 1.0)[:, None]
            g_unit = unit_vectors(g, away_unit)
            g = np.where(outside[:, None], away + d_box[:, None] * g_unit, g)
        return d, g

    def _unit_normals(self, gradient: np.ndarray, local: np.ndarray) -> np.ndarray:
        # Where the gradient vanishes (the medial axis, e.g. a sphere's centre) fall back on the
        # direction from the domain centre, then +z, so a normal is always a unit vector.
        centre = 0.5 * (self.domain_min + self.domain_max)
        fallback = unit_vectors(local - centre, np.tile([0.0, 0.0, 1.0], (len(local), 1)))
        return unit_vectors(gradient, fallback)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.info.name!r} on {self.device}>"


def gradient_threshold(eps: float, pose: Pose) -> float:
    """The collider-unit distance below which a collide-only query needs the gradient: ``eps``
    (world units) over the pose's scale, raised by a relative 1e-9 so that no point with
    ``distance * scale < eps`` is missed by rounding (one a hair above gets a normal it does not
    use; :func:`assemble_result` zeroes it)."""
    local = eps / pose.scale
    return local + 1e-9 * max(abs(local), 1e-30)


def assemble_result(points: np.ndarray, pose: Pose, eps: float, fields: tuple[str, ...],
                    distance: np.ndarray, normal: np.ndarray | None,
                    only_colliding: bool) -> QueryResult:
    """One request's fields from collider-frame ``distance`` and ``normal`` (see
    :meth:`Collider.query_local`): distances scaled to world units, normals rotated into the
    world frame, contacts ``p + (eps - d) * n`` computed in float64 in the world frame.
    With ``only_colliding``, points with ``distance >= eps`` get ``normal`` [0, 0, 0] and
    ``contact`` equal to the point (whatever ``normal`` holds for them)."""
    distance = distance * pose.scale
    collides = distance < eps
    result = QueryResult()
    if "distance" in fields:
        result.distance = distance.astype(np.float32)
    if normal is not None:
        normal = pose.to_world_directions(normal)
        if only_colliding:
            normal = np.where(collides[:, None], normal, 0.0)
    if "normal" in fields:
        result.normal = normal.astype(np.float32)
    if "contact" in fields:
        # In float64 (normal is); a zero normal leaves the point where it is, the documented
        # contact of a free point.
        contact = points + (eps - distance)[:, None] * normal
        result.contact = contact.astype(points.dtype)
    if "collides" in fields:
        result.collides = collides
    return result


def nearest_collider(world_distance: np.ndarray) -> np.ndarray:
    """The scene rule, the one both backends use: per point, the index of the collider with the
    smallest world-frame signed distance, compared in float64; a tie goes to the first collider
    in the list (the lowest index).

    world_distance : (k, n) float64, world units, one row per collider of the scene
    Returns (n,) int32 indices into the scene's colliders.
    """
    world_distance = np.asarray(world_distance)  # (float64 or not: the same order)
    if world_distance.ndim != 2 or len(world_distance) == 0:
        raise ValueError(f"world_distance must be (k, n) with k >= 1, got {world_distance.shape}")
    return np.argmin(world_distance, axis=0).astype(np.int32)


def assemble_scene_result(points: np.ndarray, poses: list[Pose], eps: list[float],
                          fields: tuple[str, ...], answers: list,
                          only_colliding: bool) -> tuple[QueryResult, np.ndarray]:
    """A scene query's fields: per point, those of the nearest collider (:func:`nearest_collider`).

    points : (n, 3) world frame; poses, eps : per collider (eps in world units)
    answers : per collider, ``(distance, normal or None)`` in its frame from
        :meth:`Collider.query_local`
    Returns ``(result, nearest)``: world-frame fields (as :func:`assemble_result` gives for one
    collider) and the (n,) int32 index of the collider each point's fields come from.
    only_colliding : as in :func:`assemble_result` (a point collides when it does with its
        nearest collider, whose answer then holds its normal)
    """
    n = len(points)
    # (Both backends refuse an empty scene before this; np.stack would too.)
    nearest = nearest_collider(np.stack([d * pose.scale for (d, _), pose in zip(answers, poses)]))
    dtypes = {"distance": np.float32, "normal": np.float32, "contact": points.dtype,
              "collides": np.bool_}
    out = {f: np.empty((n, 3) if f in ("normal", "contact") else n, dtypes[f]) for f in fields}
    for i, ((distance, normal), pose) in enumerate(zip(answers, poses)):
        rows = np.flatnonzero(nearest == i)
        if not len(rows):
            continue
        part = assemble_result(points[rows], pose, eps[i], fields, distance[rows],
                               None if normal is None else normal[rows], only_colliding)
        for name, values in part.fields().items():
            out[name][rows] = values
    return QueryResult(**out), nearest
