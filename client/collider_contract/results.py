"""What a query answers and what a model is: :class:`QueryResult` and :class:`ModelInfo`
(plain numpy, no torch), the same types from the engine, the service and both SDK backends."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import wire
from .animation import Timeline
from .pose import box_corners
from .queries import FIELDS


@dataclass
class QueryResult:
    """The fields asked for (the others are ``None``), world frame, world units (metres).

    distance : (n,) float32, signed, negative inside
    normal : (n, 3) float32, unit outward normal
    contact : (n, 3), ``p + (eps - distance) * normal``, dtype of the query points
    collides : (n,) bool, ``distance < eps``
    velocity : (n, 3) float32, world units per second: the surface's velocity at the contact
    collider : (n,) int32, scene queries only: index of the nearest collider in the request's list
    model : the model name (single-model queries), ``None`` for scene queries

    Arrays from the remote backend are read-only views on the response body (no copy).
    """

    distance: np.ndarray | None = None
    normal: np.ndarray | None = None
    contact: np.ndarray | None = None
    collides: np.ndarray | None = None
    velocity: np.ndarray | None = None
    collider: np.ndarray | None = None
    model: str | None = None

    def fields(self) -> dict[str, np.ndarray]:
        """The present fields (``distance``, ``normal``, ``contact``, ``collides``,
        ``velocity``) by name."""
        return {name: getattr(self, name) for name in FIELDS if getattr(self, name) is not None}

    def to_body(self) -> dict[str, Any]:
        """The response body: the fields, and ``model`` or ``collider`` (numpy arrays as values;
        :func:`~.wire.dumps` encodes them)."""
        body: dict[str, Any] = dict(self.fields())
        if self.collider is not None:
            body["collider"] = self.collider
        if self.model is not None:
            body["model"] = self.model
        return body

    @classmethod
    def from_body(cls, body: dict[str, Any], fields, scene: bool) -> QueryResult:
        """The result in a decoded response body that answered ``fields`` (a scene query's
        when ``scene``); :class:`~.wire.WireError` when a field is missing or malformed.
        msgpack arrays stay read-only views on the body; JSON lists get the promised dtypes."""
        result = cls(model=None if scene else body.get("model"))
        for name in (*fields, *(("collider",) if scene else ())):
            if name not in body:
                raise wire.WireError(f"the response lacks {name!r}, which was asked for")
            setattr(result, name, wire.decode_array(body[name], name))
        for name, dtype in (("distance", np.float32), ("normal", np.float32), ("collides", np.bool_),
                            ("velocity", np.float32), ("collider", np.int32)):
            value = getattr(result, name)
            if value is not None and value.dtype != dtype:
                setattr(result, name, value.astype(dtype))
        return result


@dataclass
class ModelInfo:
    """A model the service (or the embedded repository) holds.

    domain_min, domain_max : (3,) float64, collider frame and units: the box where the model is
        defined (outside it distances are a conservative extension)
    meters_per_unit : metres in one collider unit; bytes : size of the model file
    animation : empty for a static model; an animated one's ``frames``, ``frame_rate_hz``,
        ``duration_s``, ``loop`` and ``max_surface_speed`` (:mod:`.animation`; its queries must
        give a time)
    skeleton : empty for a model without one; a skinned model's ``joints`` (names), ``parents``
        (indices, -1 for a root), ``clips`` (each ``name``, ``duration_s`` and
        ``max_surface_speed``, collider units per second) and ``loop``
        (:mod:`.skeleton`; its queries give a clip and a time, or joint transforms)
    """

    name: str
    kind: str
    units: str = "m"
    meters_per_unit: float = 1.0
    domain_min: np.ndarray = field(default_factory=lambda: np.zeros(3))
    domain_max: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bytes: int = 0
    approximate: bool = False
    accuracy: dict = field(default_factory=dict)
    source: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    device: str = "cpu"
    animation: dict = field(default_factory=dict)
    skeleton: dict = field(default_factory=dict)
    #: keys a newer server sent that this client does not know (kept, not dropped)
    extra: dict = field(default_factory=dict)

    @property
    def animated(self) -> bool:
        """Whether the model changes in time: its queries must give a time."""
        return bool(self.animation)

    @property
    def skinned(self) -> bool:
        """Whether the model has a skeleton: its queries give a clip and a time, or joint
        transforms."""
        return bool(self.skeleton)

    @property
    def timeline(self) -> Timeline | None:
        """The animation's :class:`~.animation.Timeline`, or None for a static model."""
        return Timeline.from_dict(self.animation) if self.animation else None

    def clip_timeline(self, clip: str | None) -> Timeline:
        """A skinned model's clip ``clip`` (None: its first) as a :class:`~.animation.Timeline`
        (:meth:`~.animation.Timeline.of_clip`: its duration, the model's ``loop`` and the clip's
        ``max_surface_speed``). ValueError, one line, for a model without a skeleton, an unknown
        clip, a clip of no duration, or one without ``max_surface_speed`` (a model made before
        it was recorded: remake it)."""
        if not self.skinned:
            raise ValueError(f"model {self.name!r} has no skeleton: clip applies to skinned models")
        clips = self.skeleton.get("clips", [])
        names = [c.get("name") for c in clips]
        if not clips or (clip is not None and clip not in names):
            raise ValueError(f"model {self.name!r} has no clip {clip!r}; its clips: {names}")
        entry = clips[0 if clip is None else names.index(clip)]
        if "max_surface_speed" not in entry:
            raise ValueError(f"model {self.name!r}'s clip {entry['name']!r} does not record "
                             "max_surface_speed (made by an older version): make the model again")
        try:
            return Timeline.of_clip(entry.get("duration_s"), bool(self.skeleton.get("loop", True)),
                                    entry["max_surface_speed"])
        except ValueError as error:
            raise ValueError(f"model {self.name!r}'s clip {entry['name']!r}: {error}") from None

    def domain_corners(self) -> np.ndarray:
        """(8, 3) float64: the corners of the domain box, collider frame and units."""
        return box_corners(self.domain_min, self.domain_max)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, the keys :meth:`from_dict` reads (``extra`` merged back in)."""
        data = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "extra"}
        data["domain_min"] = np.asarray(self.domain_min, dtype=np.float64).tolist()
        data["domain_max"] = np.asarray(self.domain_max, dtype=np.float64).tolist()
        return {**self.extra, **data}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ModelInfo:
        known = {f.name for f in dataclasses.fields(cls)} - {"extra"}
        values = {k: v for k, v in data.items() if k in known}
        for key in ("domain_min", "domain_max"):
            if key in values:
                values[key] = np.asarray(values[key], dtype=np.float64).reshape(3)
        return cls(**values, extra={k: v for k, v in data.items() if k not in known})
