"""The latest few values a collider built for a pose or a time, kept for the queries that ask for
it again (a simulator asks the same few times over and over; a batch of requests at one pose, and
a query's chunks, build once). Thread-safe: the service evaluates in several threads."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

T = TypeVar("T")


class Kept(Generic[T]):
    """The latest ``keep`` values by key (the one asked for last is the newest)."""

    def __init__(self, keep: int):
        self.keep = keep
        self._values: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable, build: Callable[[], T]) -> T:
        """The value kept for ``key``, else ``build()``'s, then kept (built outside the lock: two
        threads asking for a new key at once may both build it; the later is kept)."""
        with self._lock:
            value = self._values.get(key)
            if value is not None:
                self._values.move_to_end(key)
                return value
        value = build()
        with self._lock:
            self._values[key] = value
            self._values.move_to_end(key)  # (another thread may have kept one meanwhile)
            while len(self._values) > self.keep:
                self._values.popitem(last=False)
        return value

    def clear(self) -> None:
        with self._lock:
            self._values.clear()

    def __len__(self) -> int:
        return len(self._values)
