"""An error budget in, the cheapest collider out.

A budget is a most-allowed mean distance error (and optionally mean normal angle error and
memory); errors are the means in the +-1 mm band around the surface (where collisions are
decided), as ``collider eval`` reports them. Among the measured colliders that meet every limit
the picker takes the one with the smallest reference time (see
:mod:`collider_cli.bench.report`): it is on the measured Pareto front by construction, and no
other measured collider meeting the budget is faster.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from .report import reference_seconds_per_point

LENGTH_MM = {"mm": 1.0, "um": 1e-3, "µm": 1e-3, "cm": 10.0, "m": 1000.0}
ANGLE_DEG = {"deg": 1.0, "°": 1.0, "rad": 180.0 / math.pi}
SIZE_BYTES = {"b": 1, "kb": 1e3, "mb": 1e6, "gb": 1e9, "kib": 2**10, "mib": 2**20, "gib": 2**30}


def _quantity(text: str, units: dict, default_unit: str, what: str) -> float:
    match = re.fullmatch(r"\s*([-+0-9.eE]+)\s*([^\s0-9.]*)\s*", str(text))
    unit = (match.group(2) if match else "") or default_unit
    key = unit if unit in units else unit.lower()
    try:
        value = float(match.group(1)) if match else float("nan")
    except ValueError:
        value = float("nan")
    if not match or key not in units or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{what} must be a finite number > 0 with a unit ({', '.join(units)}), "
                         f"e.g. 0.05{default_unit}; got {text!r}")
    return value * units[key]


def length_mm(text: str) -> float:
    """``"0.05mm"``, ``"50um"``, ``"0.05"`` (mm) -> millimetres."""
    return _quantity(text, LENGTH_MM, "mm", "--max-error")


def angle_deg(text: str) -> float:
    """``"3deg"``, ``"3"`` (degrees), ``"0.05rad"`` -> degrees."""
    return _quantity(text, ANGLE_DEG, "deg", "--max-normal-error")


def size_bytes(text: str) -> int:
    """``"8MB"`` (10^6), ``"8MiB"`` (2^20), ``"500kB"``, ``"123"`` (bytes) -> bytes."""
    return int(_quantity(text, SIZE_BYTES, "b", "--max-memory"))


@dataclass(frozen=True)
class Budget:
    """max_error_mm : mean distance error, +-1 mm band; max_normal_error_deg : mean normal
    angle error, +-1 mm band (None: no limit); max_memory_bytes : the collider's arrays in
    memory (None: no limit)."""

    max_error_mm: float
    max_normal_error_deg: float | None = None
    max_memory_bytes: int | None = None

    def misses(self, row: dict) -> list[str]:
        """Why ``row`` (a bench collider) does not meet the budget; empty when it does."""
        a = row["accuracy"]["band_1mm"]
        return self.misses_figures(a, row["memory_bytes"])

    def misses_figures(self, band_1mm: dict, memory_bytes: int) -> list[str]:
        why = []
        if band_1mm["distance_mean_mm"] > self.max_error_mm:
            why.append(f"mean distance error {band_1mm['distance_mean_mm']:.4f} mm > {self.max_error_mm:g} mm")
        if self.max_normal_error_deg is not None and band_1mm["normal_mean_deg"] > self.max_normal_error_deg:
            why.append(f"mean normal error {band_1mm['normal_mean_deg']:.2f} deg > {self.max_normal_error_deg:g} deg")
        if self.max_memory_bytes is not None and memory_bytes > self.max_memory_bytes:
            why.append(f"memory {memory_bytes / 1e6:.2f} MB > {self.max_memory_bytes / 1e6:g} MB")
        return why

    def describe(self) -> str:
        parts = [f"mean distance error <= {self.max_error_mm:g} mm"]
        if self.max_normal_error_deg is not None:
            parts.append(f"mean normal error <= {self.max_normal_error_deg:g} deg")
        if self.max_memory_bytes is not None:
            parts.append(f"memory <= {self.max_memory_bytes / 1e6:g} MB")
        return ", ".join(parts) + " (+-1 mm band)"


class NothingMeetsBudget(Exception):
    """No measured collider meets the budget; the message says what came closest."""


def rank(report: dict, budget: Budget, device: str = "cpu") -> list[dict]:
    """The bench's colliders that meet ``budget``, fastest first (reference time on
    ``device``). Raises :class:`NothingMeetsBudget` saying, per collider, what it misses."""
    timed = [(reference_seconds_per_point(r, report, device), r) for r in report["colliders"]]
    timed = [(t, r) for t, r in timed if t is not None]
    if not timed:
        raise ValueError(f"the bench report has no embedded {device} timings to rank by")
    meeting = sorted(((t, r) for t, r in timed if not budget.misses(r)), key=lambda tr: tr[0])
    if meeting:
        return [r for _, r in meeting]
    lines = [f"no measured collider meets {budget.describe()}:"]
    for t, r in sorted(timed, key=lambda tr: tr[1]["accuracy"]["band_1mm"]["distance_mean_mm"]):
        lines.append(f"  {r['label']}: " + "; ".join(budget.misses(r)))
    if report.get("skipped"):
        lines.append("not measured: " + "; ".join(f"{s['name']} ({s['reason']})" for s in report["skipped"]))
    raise NothingMeetsBudget("\n".join(lines))
