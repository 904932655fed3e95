"""Query timings: a warm-up call, then the median of repeated calls, fewer repeats for slow
cells (a cell stops repeating once its timed calls have taken ``cell_budget_s``).

A *cell* is one (path, device, mode, size): path "embedded" (the engine in this process) or
"served" (the same collider behind a real ``collider serve``, HTTP + msgpack, through the client
SDK); mode "distance" or "distance+normal+contact"; size the number of points in one call.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

#: Query modes and the fields each one asks for.
MODES: dict[str, tuple[str, ...]] = {
    "distance": ("distance",),
    "distance+normal+contact": ("distance", "normal", "contact"),
}


@dataclass(frozen=True)
class TimingPolicy:
    """repeats : most timed calls per cell; cell_budget_s : a cell stops repeating once its
    timed calls add up to this (at least one call is always timed); warmup_points : size of the
    untimed warm-up call before each (collider, path, device, mode)."""

    repeats: int = 5
    cell_budget_s: float = 10.0
    warmup_points: int = 10_000

    def check(self) -> None:
        if not isinstance(self.repeats, int) or self.repeats < 1:
            raise ValueError(f"--repeats must be an integer >= 1, got {self.repeats!r}")
        if not (np.isfinite(self.cell_budget_s) and self.cell_budget_s > 0):
            raise ValueError(f"cell budget must be a finite number of seconds > 0, got {self.cell_budget_s}")


@dataclass
class Timing:
    """One cell's figures: seconds per call (median and every timed call), seconds per point."""

    path: str
    device: str
    mode: str
    points: int
    median_s: float
    repeats: int
    times_s: list[float]

    @property
    def seconds_per_point(self) -> float:
        return self.median_s / self.points

    def to_dict(self) -> dict:
        return {**asdict(self), "seconds_per_million": self.median_s * 1e6 / self.points}


def time_calls(call: Callable[[], object], policy: TimingPolicy,
               clock: Callable[[], float] = time.perf_counter) -> list[float]:
    """Wall seconds of up to ``policy.repeats`` calls of ``call``, stopping early once they add
    up to ``policy.cell_budget_s``; ``clock`` is injectable for tests."""
    times: list[float] = []
    while len(times) < policy.repeats:
        started = clock()
        call()
        times.append(clock() - started)
        if sum(times) >= policy.cell_budget_s:
            break
    return times


def time_cells(query: Callable[[np.ndarray, tuple[str, ...]], object], points: np.ndarray,
               sizes: tuple[int, ...], path: str, device: str, policy: TimingPolicy,
               on_cell: Callable[[], None] = lambda: None) -> list[Timing]:
    """Every (mode, size) cell of one collider on one path and device.

    query : ``query(points (n, 3) float32, fields)``, the call being timed
    points : (max(sizes), 3) float32 query points; a size-n cell uses the first n
    """
    timings = []
    for mode, fields in MODES.items():
        query(points[: min(policy.warmup_points, len(points))], fields)  # warm-up, untimed
        for size in sizes:
            chunk = points[:size]
            times = time_calls(lambda: query(chunk, fields), policy)
            timings.append(Timing(path, device, mode, size, statistics.median(times), len(times), times))
            on_cell()
    return timings
