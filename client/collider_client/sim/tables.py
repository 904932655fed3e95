"""Reading TOML tables so that every error names the file and the key (``colliders[0].motion.kind:
must be one of ...``), and refusing keys nobody read."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Literal, NoReturn, overload

import numpy as np


class SceneError(ValueError):
    """A scene file that cannot be simulated; the message names the file and the key."""


class Table:
    """A TOML table that remembers where it is, so each error names file and key."""

    def __init__(self, data: dict, where: str, path: Path):
        if not isinstance(data, dict):
            raise SceneError(f"{path}: [{where}] must be a table, got {type(data).__name__}")
        self.data, self.where, self.path = data, where, path
        self.used: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def fail(self, name: str, message: str) -> NoReturn:
        raise SceneError(f"{self.path}: {self.key(name)}: {message}")

    def get(self, name: str, default=None, required: bool = False):
        self.used.add(name)
        if name not in self.data:
            if required:
                self.fail(name, "missing (required)")
            return default
        return self.data[name]

    def number(self, name, default=None, required=False, minimum=None, positive=False,
               integer=False, maximum=None):
        value = self.get(name, default, required)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                integer and not isinstance(value, int)):
            self.fail(name, f"must be {'an integer' if integer else 'a number'}, "
                            f"got {type(value).__name__} {value!r}")
        if not math.isfinite(value):
            self.fail(name, f"must be finite, got {value}")
        if positive and not value > 0:
            self.fail(name, f"must be > 0, got {value}")
        if minimum is not None and value < minimum:
            self.fail(name, f"must be >= {minimum}, got {value}")
        if maximum is not None and value > maximum:
            self.fail(name, f"must be <= {maximum}, got {value}")
        return value

    @overload
    def vector(self, name: str, default: Sequence[float], required: bool = ..., length: int = ...) -> np.ndarray:
        ...

    @overload
    def vector(self, name: str, default: None = ..., required: bool = ..., length: int = ...
               ) -> np.ndarray | None:
        ...

    def vector(self, name, default=None, required=False, length=3) -> np.ndarray | None:
        value = self.get(name, default, required)
        if value is None:
            return None
        if (not isinstance(value, list) or len(value) != length or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) for v in value)):
            self.fail(name, f"must be a list of {length} numbers, got {value!r}")
        array = np.asarray(value, dtype=np.float64)
        if not np.isfinite(array).all():
            self.fail(name, f"must be finite, got {value!r}")
        return array

    def string(self, name, default=None, required=False, choices=None):
        value = self.get(name, default, required)
        if value is None:
            return None
        if not isinstance(value, str):
            self.fail(name, f"must be a string, got {type(value).__name__} {value!r}")
        if choices is not None and value not in choices:
            self.fail(name, f"must be one of {list(choices)}, got {value!r}")
        return value

    def boolean(self, name, default=None, required=False):
        value = self.get(name, default, required)
        if value is None:
            return None
        if not isinstance(value, bool):
            self.fail(name, f"must be true or false, got {type(value).__name__} {value!r}")
        return value

    @overload
    def table(self, name: str, required: Literal[True]) -> Table:
        ...

    @overload
    def table(self, name: str, required: bool = ...) -> Table | None:
        ...

    def table(self, name, required=False) -> Table | None:
        value = self.get(name, None, required)
        if value is None:
            return None
        return Table(value, self.key(name), self.path)

    def done(self):
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            raise SceneError(f"{self.path}: unknown key(s) {[self.key(u) for u in unknown]}"
                             f"; known here: {sorted(self.used)}")
