"""Query timings that hold on a busy machine: every cell timed in interleaved rounds, the
median and the spread of its calls, process CPU time beside wall time, unstable figures retimed.

A *cell* is one (collider, path, device, mode, size): path "embedded" (the engine in this
process) or "served" (the same collider behind a real ``collider serve``, HTTP + msgpack,
through the client SDK); mode "distance" or "distance+normal+contact"; size the number of points
in one call.

Why rounds: a shared machine's load comes and goes over seconds. Timing one collider after the
other gives each the load of its own moment (a grid measured during a burst looked 50x slower
than the same grid through HTTP a minute later). A round times one call of every cell, one after
the other, so every collider sees the same moments of load; a cell's figure is the median of its
rounds and its *spread* the interquartile range over the median. A figure whose spread exceeds
``max_spread`` is *unstable*: it is retimed in extra rounds (up to ``retime_rounds``), and the
report refuses to rank colliders by figures that stay unstable (:mod:`.report`).

CPU time: for each call, the process CPU seconds it cost (this process's for embedded calls;
the server's plus this process's for served ones): steadier than wall time when other processes
take the cores, and reported beside it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

#: Query modes and the fields each one asks for.
MODES: dict[str, tuple[str, ...]] = {
    "distance": ("distance",),
    "distance+normal+contact": ("distance", "normal", "contact"),
}
#: The same for animated colliders: the surface's velocity beside the contact, at one time.
ANIMATED_MODES: dict[str, tuple[str, ...]] = {
    "distance": ("distance",),
    "distance+normal+contact+velocity": ("distance", "normal", "contact", "velocity"),
}
#: A skinned collider's: the animated modes at a clip time (asked by clip and time) and at a random
#: pose (asked by joint transforms, the joints still).
SKINNED_MODES: dict[str, tuple[str, ...]] = {
    f"{mode}, {where}": fields for where in ("clip time", "random pose") for mode, fields in ANIMATED_MODES.items()}


@dataclass(frozen=True)
class TimingPolicy:
    """How cells are timed.

    repeats : rounds: timed calls per cell
    cell_budget_s : a cell leaves the rounds once its timed calls add up to this (seconds), and
        has at least ``min_repeats`` calls when it is a reference cell (at least one otherwise)
    warmup_points : size of the untimed warm-up call of each (collider, path, device, mode)
    min_repeats : calls of a reference cell (what the front and the budget picker rank by),
        whatever its budget: a spread needs three
    max_spread : a figure whose spread (:func:`spread`, relative) exceeds this is unstable
    retime_rounds : most extra rounds for unstable figures
    """

    repeats: int = 5
    cell_budget_s: float = 10.0
    warmup_points: int = 10_000
    min_repeats: int = 3
    max_spread: float = 0.25
    retime_rounds: int = 10

    def check(self) -> None:
        if not isinstance(self.repeats, int) or self.repeats < 1:
            raise ValueError(f"--repeats must be an integer >= 1, got {self.repeats!r}")
        if not (np.isfinite(self.cell_budget_s) and self.cell_budget_s > 0):
            raise ValueError(f"--cell-seconds must be a finite number of seconds > 0, got {self.cell_budget_s}")
        if not isinstance(self.min_repeats, int) or self.min_repeats < 1:
            raise ValueError(f"min_repeats must be an integer >= 1, got {self.min_repeats!r}")
        if not (np.isfinite(self.max_spread) and self.max_spread > 0):
            raise ValueError(f"max_spread must be a finite number > 0, got {self.max_spread}")
        if not isinstance(self.retime_rounds, int) or self.retime_rounds < 0:
            raise ValueError(f"retime_rounds must be an integer >= 0, got {self.retime_rounds!r}")


def median(values: list[float]) -> float:
    return float(np.median(values))


#: The notch factor: median +- 1.57 IQR / sqrt(n) holds the median of the distribution with about
#: 95 % confidence (McGill, Tukey and Larsen 1978).
NOTCH = 1.57


def spread(values: list[float]) -> float | None:
    """How far the median of ``values`` may be off, relative to it: 1.57 IQR / (median sqrt(n))
    (0.1: the median is known within 10 %). None below two values (nothing to judge by)."""
    if len(values) < 2:
        return None
    q1, mid, q3 = np.percentile(values, [25, 50, 75])
    return float(NOTCH * (q3 - q1) / (mid * np.sqrt(len(values)))) if mid > 0 else 0.0


@dataclass
class Timing:
    """One cell's figures: wall and process CPU seconds of every timed call (the order of the
    rounds), their medians and spreads.

    path, device, mode, points : the cell; reference : a figure the front and the picker rank by
    times_s : wall seconds per call; cpu_s : process CPU seconds per call (see the module)
    """

    path: str
    device: str
    mode: str
    points: int
    reference: bool = False
    times_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)
    retimed: int = 0

    @property
    def median_s(self) -> float:
        return median(self.times_s)

    @property
    def spread(self) -> float | None:
        return spread(self.times_s)

    def stable(self, max_spread: float) -> bool:
        """A spread at most ``max_spread`` over at least three calls."""
        s = self.spread
        return s is not None and len(self.times_s) >= 3 and s <= max_spread

    def cpu_stable(self, max_spread: float) -> bool:
        """The same for the process CPU times of the calls."""
        s = spread(self.cpu_s)
        return s is not None and len(self.cpu_s) >= 3 and s <= max_spread

    def to_dict(self, max_spread: float) -> dict:
        cpu = median(self.cpu_s) if self.cpu_s else None
        cpu_spread = spread(self.cpu_s)
        return {"path": self.path, "device": self.device, "mode": self.mode, "points": self.points,
                "reference": self.reference, "median_s": self.median_s, "spread": self.spread,
                "repeats": len(self.times_s), "retimed": self.retimed, "stable": self.stable(max_spread),
                "times_s": self.times_s, "seconds_per_million": self.median_s * 1e6 / self.points,
                "cpu_median_s": cpu, "cpu_spread": cpu_spread, "cpu_s": self.cpu_s,
                "cpu_stable": self.cpu_stable(max_spread),
                "cpu_seconds_per_million": None if cpu is None else cpu * 1e6 / self.points}


def process_cpu_clock(pid: int | None = None) -> Callable[[], float]:
    """Process CPU seconds (user + system, every thread) of this process, or of process ``pid``
    (Linux: its CPU-time clock id, nanosecond resolution), as a function."""
    if pid is None:
        return time.process_time
    clock_id = ((~pid) << 3) | 2  # Linux's CPUCLOCK_SCHED clock of a whole process (posix-cpu-timers)
    try:
        time.clock_gettime(clock_id)
    except (OSError, AttributeError):  # not Linux, or the process is gone: no figure, not a crash
        return lambda: math.nan
    return lambda: time.clock_gettime(clock_id)


@dataclass
class Cell:
    """One cell being timed: ``call()`` runs one query; ``cpu_clocks`` read the processes whose
    CPU time the call spends (summed)."""

    name: str
    timing: Timing
    call: Callable[[], object]
    cpu_clocks: tuple[Callable[[], float], ...] = (time.process_time,)

    def measure(self, clock: Callable[[], float] = time.perf_counter) -> float:
        cpu0 = sum(c() for c in self.cpu_clocks)
        started = clock()
        self.call()
        wall = clock() - started
        self.timing.times_s.append(wall)
        self.timing.cpu_s.append(sum(c() for c in self.cpu_clocks) - cpu0)
        return wall

    def wants_more(self, policy: TimingPolicy) -> bool:
        """In the regular rounds: fewer than ``repeats`` calls and, past ``min_repeats`` (a
        reference cell) or one call (others), still under the cell budget."""
        n = len(self.timing.times_s)
        if n >= policy.repeats:
            return False
        floor = min(policy.min_repeats, policy.repeats) if self.timing.reference else 1
        return n < floor or sum(self.timing.times_s) < policy.cell_budget_s


def time_rounds(cells: list[Cell], policy: TimingPolicy, on_call: Callable[[Cell], None] = lambda c: None,
                clock: Callable[[], float] = time.perf_counter) -> int:
    """Time ``cells`` in interleaved rounds (one call of every cell still wanting more per round,
    in the list's order), then retime, in up to ``retime_rounds`` extra rounds, the cells
    :func:`retime_due` names: unstable ones (more calls narrow a median's spread) and served
    cells measured faster than their embedded twin (:func:`served_beats_embedded`) with that
    twin. Returns the rounds run."""
    rounds = 0
    while True:
        due = [c for c in cells if c.wants_more(policy)]
        if not due:
            break
        for cell in due:
            cell.measure(clock)
            on_call(cell)
        rounds += 1
    for _ in range(policy.retime_rounds):
        due = retime_due(cells, policy)
        if not due:
            break
        for cell in due:
            cell.measure(clock)
            cell.timing.retimed += 1
            on_call(cell)
        rounds += 1
    return rounds


def retime_due(cells: list[Cell], policy: TimingPolicy) -> list[Cell]:
    """Cells to time once more (see :func:`time_rounds`), in the list's order: unstable ones (wall
    or CPU time) while their calls stay under twice the cell budget, and both twins of a served call faster
    than its embedded one until each has three calls (a spread to judge by), then as unstable
    ones."""
    def under_budget(cell):
        return sum(cell.timing.times_s) < 2 * policy.cell_budget_s

    def unstable(t):  # on either basis: the report may rank by wall or by CPU time
        return not (t.stable(policy.max_spread) and t.cpu_stable(policy.max_spread))

    due = {id(c) for c in cells if len(c.timing.times_s) >= 3 and unstable(c.timing) and under_budget(c)}
    twins: dict[tuple, dict[str, Cell]] = {}
    for cell in cells:
        t = cell.timing
        twins.setdefault((cell.name, t.device, t.mode, t.points), {})[t.path] = cell
    for pair in twins.values():
        if "served" in pair and "embedded" in pair and served_beats_embedded(pair["embedded"].timing,
                                                                            pair["served"].timing):
            due.update(id(c) for c in pair.values() if len(c.timing.times_s) < 3 or under_budget(c))
    return [c for c in cells if id(c) in due]


def interval(values: list[float]) -> tuple[float, float]:
    """The median of ``values`` minus and plus its :func:`spread` (seconds)."""
    mid, s = median(values), spread(values) or 0.0
    return mid * (1 - s), mid * (1 + s)


def served_beats_embedded(embedded: Timing, served: Timing) -> bool:
    """Served faster than embedded by more than the measured spread: the served median's
    interval wholly below the embedded one's. The same query plus HTTP should not be faster (the
    engine computes an embedded query in the blocks a server batches: ``Collider.chunk_points``
    and ``max_batch_points``, 65,536 for the grid kinds), so this is a measurement to redo, never
    a figure to report as is."""
    if not embedded.times_s or not served.times_s:
        return False
    return interval(served.times_s)[1] < interval(embedded.times_s)[0]


def warm_up(call: Callable[[], object], clock: Callable[[], float] = time.perf_counter) -> float:
    """One untimed-for-the-figures call; returns its wall seconds (for the duration estimate)."""
    started = clock()
    call()
    return clock() - started

