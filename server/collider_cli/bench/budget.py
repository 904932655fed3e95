"""An error budget in, the cheapest collider out.

A budget is a most-allowed mean distance error (and optionally mean normal angle error and
memory); errors are the means in the +-1 mm band around the surface (where collisions are
decided), as ``collider eval`` reports them; a figure equal to its limit meets it. Among the
measured colliders that meet every limit the picker takes the one with the smallest reference
time (see :mod:`collider_cli.bench.report`); colliders whose times are equal within the
measurement (:func:`~collider_cli.bench.report.equal_times`) count as equally fast, and of those
it takes the one with the least memory (then the most accurate): no other measured collider
meeting the budget is faster by more than the measurement can tell.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from .report import equal_times, ranking_basis, reference_seconds_per_point, reference_spread

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
        return self.misses_figures(row["accuracy"]["band_1mm"], row["memory_bytes"])

    def checks(self, band_1mm: dict, memory_bytes: int) -> list[tuple[bool, str]]:
        """Every limit of the budget against the figures: ``(met, "figure <= limit")``, one per
        limit given. A figure equal to its limit meets it."""
        out = [(band_1mm["distance_mean_mm"] <= self.max_error_mm,
                (f"mean distance error {band_1mm['distance_mean_mm']:.4f} mm "
                f"{'<=' if band_1mm['distance_mean_mm'] <= self.max_error_mm else '>'} {self.max_error_mm:g} mm"))]
        if self.max_normal_error_deg is not None:
            met = band_1mm["normal_mean_deg"] <= self.max_normal_error_deg
            out.append((met, (f"mean normal error {band_1mm['normal_mean_deg']:.2f} deg "
                             f"{'<=' if met else '>'} {self.max_normal_error_deg:g} deg")))
        if self.max_memory_bytes is not None:
            met = memory_bytes <= self.max_memory_bytes
            out.append((met, (f"memory {format_bytes(memory_bytes)} {'<=' if met else '>'} "
                             f"{format_bytes(self.max_memory_bytes)}")))
        return out

    def misses_figures(self, band_1mm: dict, memory_bytes: int) -> list[str]:
        return [text for met, text in self.checks(band_1mm, memory_bytes) if not met]

    def describe(self) -> str:
        parts = [f"mean distance error <= {self.max_error_mm:g} mm"]
        if self.max_normal_error_deg is not None:
            parts.append(f"mean normal error <= {self.max_normal_error_deg:g} deg")
        if self.max_memory_bytes is not None:
            parts.append(f"memory <= {format_bytes(self.max_memory_bytes)}")
        return ", ".join(parts) + " (+-1 mm band)"


def format_bytes(n: float) -> str:
    """``"512 bytes"``, ``"1 kB"``, ``"8.39 MB"``, ``"1.5 GB"`` (powers of 1000, as --max-memory's
    kB, MB, GB), with enough digits to tell a limit from a figure near it."""
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} bytes"


class NothingMeetsBudget(Exception):
    """No measured collider meets the budget; the message says what came closest."""


def rank(report: dict, budget: Budget, device: str = "cpu") -> list[dict]:
    """The bench's colliders that meet ``budget``, the pick first (the fastest; among those
    equally fast within the measurement, the least memory, then the most accurate), then the
    others fastest first (reference time on ``device``, on the report's ranking basis: wall
    time, or process CPU time when wall times were unstable). Raises :class:`NothingMeetsBudget`
    saying, per collider, what it misses."""
    basis = ranking_basis(report, device) or "wall"
    timed = [(reference_seconds_per_point(r, report, device, basis=basis), reference_spread(r, report, device, basis), r)
             for r in report["colliders"]]
    timed = [(t, s, r) for t, s, r in timed if t is not None]
    if not timed:
        raise ValueError(f"the bench report has no embedded {device} timings to rank by")
    meeting = sorted(((t, s, r) for t, s, r in timed if not budget.misses(r)), key=lambda tsr: tsr[0])
    if meeting:
        fastest, spread, _ = meeting[0]
        tied = [m for m in meeting if equal_times(fastest, m[0], spread, m[1])]
        pick = min(tied, key=lambda m: (m[2]["memory_bytes"], m[2]["accuracy"]["band_1mm"]["distance_mean_mm"]))
        return [pick[2]] + [r for _, _, r in meeting if r is not pick[2]]
    lines = [f"no measured collider meets {budget.describe()}:"]
    for _, _, r in sorted(timed, key=lambda tsr: tsr[2]["accuracy"]["band_1mm"]["distance_mean_mm"]):
        lines.append(f"  {r['label']}: " + "; ".join(budget.misses(r)))
    if report.get("skipped"):
        lines.append("not measured: " + "; ".join(f"{s['name']} ({s['reason']})" for s in report["skipped"]))
    raise NothingMeetsBudget("\n".join(lines))


def equally_fast(report: dict, ranked: list[dict], device: str = "cpu") -> list[dict]:
    """The meeting colliders whose reference time equals the pick's within the measurement."""
    basis = ranking_basis(report, device) or "wall"

    def figure(row):
        return (reference_seconds_per_point(row, report, device, basis=basis),
                reference_spread(row, report, device, basis))

    first, first_spread = figure(ranked[0])
    return [r for r in ranked[1:] if equal_times(first, figure(r)[0], first_spread, figure(r)[1])]
