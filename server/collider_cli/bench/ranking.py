"""How a bench report ranks its colliders: reference times, their basis (wall or CPU), when two
are equal, the Pareto fronts. (Where serving beat embedding is :func:`.tables.served_faster`.)

The *reference time* of a collider (what the front, the plot and the budget picker rank by) is
the median seconds per point of a ``distance+normal+contact`` query of the largest measured size,
embedded, on the device asked for (``cpu`` unless told), over interleaved rounds
(:mod:`.timing`): its wall time, or, when some collider's wall time stayed unstable, its process
CPU time if every collider's is stable (the *basis*, :func:`ranking_basis`; CPU time does not
grow with other processes' load, wall time does), else no front is called. Two reference times
count as *equal* when they differ by less than :data:`TIE` or than either one's spread: a front or
a pick never rests on a smaller difference.
"""

from __future__ import annotations

REFERENCE_MODE = "distance+normal+contact"


def reference_mode(report: dict) -> str:
    """The mode a report ranks by: :data:`REFERENCE_MODE`, or what the run says (an animated
    bench adds the velocity)."""
    return report.get("reference_mode", REFERENCE_MODE)
ERROR_KEYS = {"distance": "distance_mean_mm", "normal": "normal_mean_deg"}
#: Reference times closer than this (relative) are equal for the front and the budget picker: on
#: the shared 2-core machine the ratio of two colliders' CPU times moved by up to 30 % between
#: quick benches minutes apart (voxel 64^3 over 32^3: 0.97 to 1.30x) while each run's own spread
#: said 7 %: a front resting on a smaller difference would change from run to run.
TIE = 0.35


def timing(row: dict, *, path: str, device: str, mode: str, points: int) -> dict | None:
    for t in row["timings"]:
        if (t["path"], t["device"], t["mode"], t["points"]) == (path, device, mode, points):
            return t
    return None


def reference_timing(row: dict, report: dict, device: str = "cpu", path: str = "embedded") -> dict | None:
    """The cell of the largest measured ``distance+normal+contact`` call (None: not measured)."""
    size = max(report["config"]["sizes"])
    return timing(row, path=path, device=device, mode=reference_mode(report), points=size)


#: Where a basis reads a cell's figure, spread and stability.
BASES = {"wall": ("median_s", "spread", "stable"), "cpu": ("cpu_median_s", "cpu_spread", "cpu_stable")}


def reference_seconds_per_point(row: dict, report: dict, device: str = "cpu",
                                path: str = "embedded", basis: str = "wall") -> float | None:
    """Median seconds per point (wall, or process CPU) of the largest measured
    ``distance+normal+contact`` call."""
    t = reference_timing(row, report, device, path)
    value = None if t is None else t.get(BASES[basis][0])
    return None if value is None else value / t["points"]


def reference_spread(row: dict, report: dict, device: str = "cpu", basis: str = "wall") -> float:
    t = reference_timing(row, report, device)
    return (t or {}).get(BASES[basis][1]) or 0.0


def ranking_basis(report: dict, device: str = "cpu") -> str | None:
    """What the front and the picker rank by: ``"wall"`` when every collider's reference wall
    time is stable and, if the CPU times are stable too, they call the same fronts; ``"cpu"``
    when the CPU times are stable and the wall times are not, or call other fronts (then the
    load of the moment changed the ranking: on the shared machine a 1 MB voxel grid slowed
    against a 128 kB one under other processes' cache traffic, 1.56x in wall time, 1.2x in CPU
    time); None when neither is stable (no front is called)."""
    stable = [basis for basis in BASES if not unstable_references(report, device, basis)]
    if stable == ["wall", "cpu"]:
        same = all(pareto_front(front_items(report, device, error, "wall"))
                   == pareto_front(front_items(report, device, error, "cpu")) for error in ERROR_KEYS)
        return "wall" if same else "cpu"
    return stable[0] if stable else None


def equal_times(a: float, b: float, spread_a: float | None = 0.0, spread_b: float | None = 0.0) -> bool:
    """Times ``a`` and ``b`` (same unit) equal within :data:`TIE` or either one's spread."""
    tolerance = max(TIE, spread_a or 0.0, spread_b or 0.0)
    return max(a, b) <= min(a, b) * (1.0 + tolerance)


def pareto_front(items: list[tuple]) -> list[str]:
    """Names of the ``(name, time, error[, spread])`` items that no other item dominates,
    ordered by time. B dominates A when B is at least as accurate and not slower beyond the
    measurement (:func:`equal_times`), and strictly better in one: more accurate, or faster
    beyond the measurement."""
    full = [(n, t, e, (rest[0] if rest else 0.0)) for n, t, e, *rest in items]
    front = []
    for name, t, e, s in full:
        dominated = False
        for n2, t2, e2, s2 in full:
            if n2 == name or e2 > e:
                continue
            tied = equal_times(t, t2, s, s2)
            if (t2 < t or tied) and (e2 < e or (t2 < t and not tied)):
                dominated = True
                break
        if not dominated:
            front.append((t, name))
    return [name for _, name in sorted(front)]


def unstable_references(report: dict, device: str = "cpu", basis: str = "wall") -> list[str]:
    """Labels (with their spread) of colliders whose reference time on ``basis`` is missing or
    unstable."""
    key, spread_key, stable_key = BASES[basis]
    out = []
    for r in report["colliders"]:
        t = reference_timing(r, report, device)
        if t is None or t.get(key) is None:
            out.append(f"{r['label']} (not timed)")
        elif not t.get(stable_key, True):
            spread = t.get(spread_key)
            out.append(f"{r['label']} (spread {'?' if spread is None else f'{100 * spread:.0f} %'} over "
                       f"{t['repeats']} calls)")
    return out


def front_items(report: dict, device: str, error: str, basis: str = "wall") -> list[tuple[str, float, float, float]]:
    """``(name, reference seconds per point, +-1 mm band mean error, spread)`` per timed collider."""
    items = []
    for r in report["colliders"]:
        t = reference_seconds_per_point(r, report, device, basis=basis)
        if t is not None:
            items.append((r["name"], t, r["accuracy"]["band_1mm"][ERROR_KEYS[error]],
                          reference_spread(r, report, device, basis)))
    return items


def front(report: dict, device: str, error: str) -> list[str] | None:
    """The Pareto front's names on the :func:`ranking_basis`, or None when it is not called
    (some reference time is missing, an interrupted run, or unstable on both bases)."""
    basis = ranking_basis(report, device)
    if basis is None or not report["colliders"]:
        return None
    return pareto_front(front_items(report, device, error, basis))
