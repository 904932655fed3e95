"""What a query answers and what a model is: :class:`QueryResult` and :class:`ModelInfo`
(plain numpy, no torch), the same types from the engine, the service and both SDK backends."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .wire import FIELDS


@dataclass
class QueryResult:
    """The fields asked for (the others are ``None``), world frame, world units (metres).

    distance : (n,) float32, signed, negative inside
    normal : (n, 3) float32, unit outward normal
    contact : (n, 3), ``p + (eps - distance) * normal``, dtype of the query points
    collides : (n,) bool, ``distance < eps``
    collider : (n,) int32, scene queries only: index of the nearest collider in the request's list
    model : the model name (single-model queries), ``None`` for scene queries

    Arrays from the remote backend are read-only views on the response body (no copy).
    """

    distance: np.ndarray | None = None
    normal: np.ndarray | None = None
    contact: np.ndarray | None = None
    collides: np.ndarray | None = None
    collider: np.ndarray | None = None
    model: str | None = None

    def fields(self) -> dict[str, np.ndarray]:
        """The present fields (``distance``, ``normal``, ``contact``, ``collides``) by name."""
        return {name: getattr(self, name) for name in FIELDS if getattr(self, name) is not None}


@dataclass
class ModelInfo:
    """A model the service (or the embedded repository) holds.

    domain_min, domain_max : (3,) float64, collider frame and units: the box where the model is
        defined (outside it distances are a conservative extension)
    meters_per_unit : metres in one collider unit; bytes : size of the model file
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
    #: keys a newer server sent that this client does not know (kept, not dropped)
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "ModelInfo":
        known = {f.name for f in dataclasses.fields(cls)} - {"extra"}
        values = {k: v for k, v in data.items() if k in known}
        for key in ("domain_min", "domain_max"):
            if key in values:
                values[key] = np.asarray(values[key], dtype=np.float64).reshape(3)
        return cls(**values, extra={k: v for k, v in data.items() if k not in known})
