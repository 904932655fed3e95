"""What a bench report looks like to people: the paper-layout time table, the accuracy table,
ratios to the exact ``mesh`` collider, the Pareto front and the error-vs-time picture.

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

import json
from pathlib import Path

import numpy as np

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


def served_faster(report: dict) -> list[str]:
    """Cells where the served call measured faster than the embedded one by more than the
    spread (after the retiming of :mod:`.timing`): never a figure to trust."""
    from .timing import Timing, served_beats_embedded

    out = []
    for r in report["colliders"]:
        for t in r["timings"]:
            if t["path"] != "served":
                continue
            e = timing(r, path="embedded", device=t["device"], mode=t["mode"], points=t["points"])
            if e is None:
                continue
            if served_beats_embedded(Timing("embedded", "", "", 1, times_s=e["times_s"]),
                                     Timing("served", "", "", 1, times_s=t["times_s"])):
                out.append(f"{r['label']} {t['mode']} {size_label(t['points'])} {t['device']} "
                           f"(served {1e3 * t['median_s']:.3g} ms, embedded {1e3 * e['median_s']:.3g} ms)")
    return out


# -- text tables (Markdown) -------------------------------------------------------------------


def size_label(n: int) -> str:
    return f"{n // 1_000_000}M" if n % 1_000_000 == 0 else (f"{n // 1000}k" if n % 1000 == 0 else str(n))


def time_tables(report: dict) -> str:
    """One paper-layout table per (path, device, mode): rows = call sizes, a column per
    collider, median milliseconds per call and the spread of the calls; ``!`` marks an
    unstable figure, ``(r)`` a cell with only r calls."""
    rows = report["colliders"]
    policy = report["config"]["timing"]
    out = []
    combos = sorted({(t["path"], t["device"], t["mode"]) for r in rows for t in r["timings"]},
                    key=lambda c: (c[1], ["embedded", "served"].index(c[0]), c[2] != "distance"))
    for path, device, mode in combos:
        present = [r for r in rows if any((t["path"], t["device"], t["mode"]) == (path, device, mode)
                                          for t in r["timings"])]
        out.append(f"**{mode}, {path}, {device}**: median ms per call, +- spread")
        out.append("")
        out.append("| points | " + " | ".join(r["label"] for r in present) + " |")
        out.append("|---|" + "---|" * len(present))
        for size in report["config"]["sizes"]:
            cells = []
            for r in present:
                t = timing(r, path=path, device=device, mode=mode, points=size)
                cells.append("-" if t is None else timing_text(t, policy))
            out.append(f"| {size_label(size)} | " + " | ".join(cells) + " |")
        out.append("")
    out.append(f"Each cell: a warm-up call, then one call per round, the colliders interleaved in "
               f"rounds (up to {policy['repeats']}); the median and, after +-, its spread (how far the median "
               f"may be off: 1.57 x the calls' interquartile range / sqrt(calls)). A cell leaves the rounds once "
               f"its calls add up to "
               f"{policy['cell_budget_s']:g} s ((r): its r calls), the reference cells after "
               f"{policy['min_repeats']} calls at least; ! marks a spread above "
               f"{100 * policy['max_spread']:.0f} % left after up to {policy['retime_rounds']} extra rounds.")
    return "\n".join(out)


def timing_text(t: dict, policy: dict) -> str:
    """``"12.3 +-4%"``, ``"531 +-41%!"`` (unstable), ``"30466 (1)"`` (one call)."""
    ms = 1e3 * t["median_s"]
    text = f"{ms:.{_digits(ms)}f}"
    if t.get("spread") is not None:
        text += f" +-{100 * t['spread']:.0f}%"
    if t["repeats"] >= 3 and not t.get("stable", True):
        text += "!"
    if t["repeats"] < policy["repeats"]:
        text += f" ({t['repeats']})"
    return text


def _digits(value: float) -> int:
    return 0 if value >= 100 else (1 if value >= 10 else 2)


def accuracy_table(report: dict) -> str:
    """Errors against the exact SDF in the +-1 mm and +-10 mm bands, build cost and memory."""
    n = report["config"]["accuracy_points"]
    animation = report.get("animation")
    against = ("the exact SDF" if animation is None else
               f"the exact interpolated mesh at {len(animation['times_s'])} random times (above), pooled,")
    out = [(f"Errors against {against} on {n:,} points per band (mm, deg); sign errors among "
           "points with abs(d) > 0.2 mm; memory: what the collider holds."), "",
           ("| collider | +-1 mm: distance mean / p99 / max | sign | normal mean / p99 | "
           "+-10 mm: distance mean / p99 / max | normal mean | build | file | memory |"),
           "|---|---|---|---|---|---|---|---|---|"]
    for r in report["colliders"]:
        a, b = r["accuracy"]["band_1mm"], r["accuracy"]["band_10mm"]
        out.append(
            f"| {r['label']} | {a['distance_mean_mm']:.4f} / {a['distance_p99_mm']:.3f} / {a['distance_max_mm']:.3f} "
            f"| {a['sign_errors_percent']:.3f} % | {a['normal_mean_deg']:.2f} / {a['normal_p99_deg']:.1f} "
            f"| {b['distance_mean_mm']:.4f} / {b['distance_p99_mm']:.3f} / {b['distance_max_mm']:.3f} "
            f"| {b['normal_mean_deg']:.2f} | {_build(r)} | {_mb(r['file_bytes'])} | {_mb(r['memory_bytes'])} |")
    return "\n".join(out)


def _build(row: dict) -> str:
    seconds = row.get("build_seconds")
    what = {"bake": "bake", "train": "training", "trained": "training"}[row["build"]]
    if seconds is None:
        return f"{what} ?"
    return f"{what} {seconds:.1f} s" if seconds < 120 else f"{what} {seconds / 60:.1f} min"


def _mb(n: int) -> str:
    return f"{n / 1e6:.2f} MB"


def ratio_table(report: dict, device: str = "cpu") -> str:
    """Per collider, relative to ``mesh`` (exact): reference time (wall and process CPU), and
    the +-1 mm band's errors."""
    rows = {r["name"]: r for r in report["colliders"]}
    base = reference_seconds_per_point(rows["mesh"], report, device) if "mesh" in rows else None
    size = max(report["config"]["sizes"])
    out = [(f"Reference time: {reference_mode(report)} on {size_label(size)} points per call, embedded, {device}: "
           "median wall seconds per 1M points (+- spread), the process CPU seconds it cost, the time "
           "relative to `mesh` (exact; below 1 = faster), and the +-1 mm band mean errors."), "",
           "| collider | s per 1M points | CPU s per 1M points | time / mesh | distance mean (mm) | normal mean (deg) |",
           "|---|---|---|---|---|---|"]
    for r in report["colliders"]:
        t = reference_timing(r, report, device)
        if t is None:
            continue
        a = r["accuracy"]["band_1mm"]
        per = t["median_s"] / t["points"]
        spread = "" if t.get("spread") is None else f" +-{100 * t['spread']:.0f}%" + ("!" if not t.get("stable", True) else "")
        cpu = "-" if t.get("cpu_seconds_per_million") is None else f"{t['cpu_seconds_per_million']:.2f}"
        ratio = "-" if base is None else f"{per / base:.2f}x"
        out.append(f"| {r['label']} | {per * 1e6:.2f}{spread} | {cpu} | {ratio} | {a['distance_mean_mm']:.4f} | "
                   f"{a['normal_mean_deg']:.2f} |")
    return "\n".join(out)


def summary(report: dict) -> str:
    """Everything a person reads after a run, as Markdown."""
    m = report["machine"]
    timing_info = report.get("timing") or {}
    parts = [
        (f"# collider bench: {report['mesh']['name']} ({report['mesh']['faces']:,} faces, "
        f"{report['mesh']['units']})"), "",
    ]
    if report.get("interrupted"):
        parts += ["**Interrupted** (Ctrl-C or SIGTERM): what follows is what was measured until then.", ""]
    parts += [
        f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['versions'].get('torch')} with "
        f"{m['torch_threads']} threads, GPU {m['gpu'] or 'none'}; load average "
        f"{_load(m['load_average_start'])} at start, {_load(m['load_average_end'])} at the end; "
        f"{report['seconds'] / 60:.1f} min in all"
        + (f"; {timing_info['rounds']} timing rounds" if timing_info.get("rounds") else "") + ".", "",
        *_mesh_lines(report), *_animation_lines(report), time_tables(report), "", accuracy_table(report), "",
        ratio_table(report), "",
    ]
    for device in report["config"]["devices"]:
        parts.append(front_text(report, device))
    faster = served_faster(report)
    if faster:
        parts += ["", ("Served measured faster than embedded by more than the spread, even after retiming "
                  "(the same query plus HTTP should not be: the load of the machine most likely changed "
                  "between the two; rerun on a quieter machine):")] + [f"- {f}" for f in faster]
    if report["skipped"]:
        parts += ["", "Not measured:"] + [f"- {s['name']}: {s['reason']}" for s in report["skipped"]]
    return "\n".join(parts) + "\n"


def _animation_lines(report: dict) -> list[str]:
    """An animated bench's animation, its random times and the time its queries were timed at."""
    a = report.get("animation")
    if not a:
        return []
    times = ", ".join(f"{t:.4f}" for t in a["times_s"])
    return [(f"Animated: {a['frames']} frames at {a['frame_rate_hz']:g} fps ({a['cache']}), {a['duration_s']:g} s, "
            f"{'looping' if a['loop'] else 'clamped'}. Errors at {len(a['times_s'])} random times drawn uniformly "
            f"over [0, {a['duration_s']:g}) s (between frames): {times} s; every query timed at "
            f"t = {a['timing_time_s']:.4f} s."), ""]


def _mesh_lines(report: dict) -> list[str]:
    from collider_server.making.mesh_check import MeshCheck

    check = report["mesh"].get("check")
    return [] if not check else [*MeshCheck.from_dict(check).lines(), ""]


def _load(value) -> str:
    return "?" if value is None else f"{value:.1f}"


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


def front_text(report: dict, device: str) -> str:
    labels = {r["name"]: r["label"] for r in report["colliders"]}
    basis = ranking_basis(report, device)
    limit = 100 * report["config"]["timing"]["max_spread"]
    if basis is None:
        return (f"Pareto front ({device}): not called: the reference time of "
                f"{', '.join(unstable_references(report, device))} is not a stable figure (spread above "
                f"{limit:.0f} % after retiming, or not measured), nor is its process CPU time "
                f"({', '.join(unstable_references(report, device, 'cpu'))}); a front drawn from them could change "
                "from run to run. Rerun on a quieter machine (the load average is in the header).")
    lines = []
    if basis == "cpu":
        unstable = unstable_references(report, device)
        why = (f"the wall times of {', '.join(unstable)} stayed unstable (spread above {limit:.0f} %)" if unstable
               else "wall and CPU times call different fronts: the load of the moment changed the ranking")
        lines.append(f"The front ranks by process CPU time per point, which other processes' load inflates "
                     f"least: {why}.")
    for error in ERROR_KEYS:
        names = front(report, device, error)
        if names:
            lines.append(f"Pareto front ({device}, {'CPU ' if basis == 'cpu' else ''}time vs {error} error): "
                         + ", ".join(labels[n] for n in names))
    lines.append(f"(Reference times within {100 * TIE:.0f} % or within their spread of each other count as equal.)")
    return "\n".join(lines)


#: Where a label may go around its marker, tried in this order at growing distances: (x, y)
#: direction of the offset, and the label's alignment there.
LABEL_SPOTS = ((0, -1, "center", "top"), (0, 1, "center", "bottom"), (1, 0, "left", "center"),
               (-1, 0, "right", "center"), (0.7, 0.7, "left", "bottom"), (0.7, -0.7, "left", "top"),
               (-0.7, 0.7, "right", "bottom"), (-0.7, -0.7, "right", "top"))


def place_labels(ax, labels: list[tuple[str, float, float, float]],
                 obstacles: list[tuple[float, float, float, str]] = ()) -> list:
    """Annotate each ``(text, x, y, marker diameter in points)`` near its marker: the first
    spot of :data:`LABEL_SPOTS`, on growing rings around the marker, where the label's rendered
    box lies inside the axes and overlaps no marker (``obstacles`` too: ``(x, y, diameter, text)``,
    a second marker of the label ``text`` names) and no label placed before; with a thin leader
    line when it had to move off the first ring or when the marker nearest it is another
    label's (clustered colliders would otherwise print over each other, or beside another marker).
    Call it once the figure's layout is final: it works in display coordinates. Returns the
    annotations."""
    fig = ax.figure
    renderer = fig.canvas.get_renderer()
    pixels_per_point = fig.dpi / 72.0

    def box(x, y, diameter):
        cx, cy = ax.transData.transform((x, y))
        r = diameter * pixels_per_point / 2
        return (cx - r, cy - r, cx + r, cy + r)

    taken = [box(x, y, d) for _, x, y, d in labels] + [box(x, y, d) for x, y, d, _ in obstacles]
    owners = [(ax.transData.transform((x, y)), text) for text, x, y, _ in labels]
    owners += [(ax.transData.transform((x, y)), text) for x, y, _, text in obstacles]

    def nearest_is_own(b, text) -> bool:
        """Whether the marker nearest the label's centre is one of its own (a reader pairs them so)."""
        centre = np.array([(b.x0 + b.x1) / 2, (b.y0 + b.y1) / 2])
        return min(owners, key=lambda o: np.hypot(*(centre - o[0])))[1] == text
    frame = ax.get_window_extent(renderer)
    annotations = []
    for text, x, y, diameter in sorted(labels, key=lambda item: item[1]):
        chosen = None
        for ring in range(6):
            gap = diameter / 2 + 3 + 12 * ring
            for ux, uy, ha, va in LABEL_SPOTS:
                arrow = {"arrowstyle": "-", "color": "grey", "linewidth": 0.6} if ring else None
                note = ax.annotate(text, (x, y), textcoords="offset points", xytext=(ux * gap, uy * gap),
                                   ha=ha, va=va, fontsize=8, arrowprops=arrow, zorder=5)
                b = text_box(note, renderer)
                inside = frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1
                if inside and not any(b.x0 < t[2] and t[0] < b.x1 and b.y0 < t[3] and t[1] < b.y1 for t in taken):
                    chosen = note
                    break
                note.remove()
            if chosen is not None:
                break
        if chosen is None:  # nowhere free: below the marker anyway
            chosen = ax.annotate(text, (x, y), textcoords="offset points", xytext=(0, -diameter / 2 - 3),
                                 ha="center", va="top", fontsize=8, zorder=5)
        b = text_box(chosen, renderer)
        if chosen.arrow_patch is None and not nearest_is_own(b, text):  # beside another marker: tie it
            chosen.remove()
            chosen = ax.annotate(text, (x, y), textcoords="offset points", xytext=chosen.xyann,
                                 ha=chosen.get_ha(), va=chosen.get_va(), fontsize=8, zorder=5,
                                 arrowprops={"arrowstyle": "-", "color": "grey", "linewidth": 0.6})
            b = text_box(chosen, renderer)
        taken.append((b.x0, b.y0, b.x1, b.y1))
        annotations.append(chosen)
    return annotations


def text_box(note, renderer):
    """The display box of an annotation's text alone (its leader line runs to the marker)."""
    from matplotlib.text import Text

    note.update_positions(renderer)
    return Text.get_window_extent(note, renderer)


# -- files ------------------------------------------------------------------------------------


def write_outputs(report: dict, directory: Path) -> dict[str, Path]:
    """``bench.json`` (every raw figure), ``bench.md`` (the tables) and one PNG per device."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = {"json": directory / "bench.json", "markdown": directory / "bench.md"}
    paths["json"].write_text(json.dumps(report, indent=1))
    paths["markdown"].write_text(summary(report))
    for device in report["config"]["devices"]:
        paths[f"png-{device}"] = plot(report, directory / f"bench-{device}.png", device)
    return paths


def interrupted_line(paths: dict[str, Path]) -> str:
    """What an interrupted run's report holds and where it is (``paths``: :func:`write_outputs`')."""
    return (f"interrupted: {paths['markdown']} and {paths['json']} hold what was measured until "
            "then")


def plot(report: dict, output: Path, device: str = "cpu") -> Path:
    """Save :func:`figure` as a PNG at ``output``."""
    import matplotlib.pyplot as plt

    fig = figure(report, device)
    output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(output, dpi=fig.dpi)
    plt.close(fig)
    return output


def figure(report: dict, device: str = "cpu"):
    """Two panels, distance and normal error (+-1 mm band, log) against the reference time per
    point (log); marker area ~ memory; the Pareto front as a dashed staircase (or a note saying
    why it is not called); embedded as filled markers and served (same query through
    ``collider serve``) as open ones. Returns the matplotlib figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    basis = ranking_basis(report, device) or "wall"
    rows = [r for r in report["colliders"]
            if reference_seconds_per_point(r, report, device, basis=basis) is not None]
    size = max(report["config"]["sizes"])
    colours = plt.get_cmap("tab10")
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.4), dpi=110)
    floor = {"distance": 1e-4, "normal": 1e-2}  # exact colliders (error 0) drawn on this floor
    biggest = max([r["memory_bytes"] for r in rows] or [1])
    panels = []
    for ax, (error, key) in zip(axes, ERROR_KEYS.items()):
        points, labels, served_markers = {}, [], []
        for i, r in enumerate(rows):
            t = reference_seconds_per_point(r, report, device, basis=basis) * 1e6
            e = max(r["accuracy"]["band_1mm"][key], floor[error])
            points[r["name"]] = (t, e)
            area = 30 + 600 * np.sqrt(r["memory_bytes"] / biggest)
            ax.scatter(t, e, s=area, color=colours(i % 10), alpha=0.8, edgecolors="black", linewidths=0.6,
                       zorder=3)
            exact = " (error 0, drawn on the floor)" if r["accuracy"]["band_1mm"][key] < floor[error] else ""
            text = f"{r['label']}{exact}"
            served = reference_seconds_per_point(r, report, device, "served", basis)
            if served is not None:
                ax.scatter(served * 1e6, e, s=area, facecolors="none", edgecolors=colours(i % 10),
                           linewidths=1.2, zorder=3)
                ax.plot([t, served * 1e6], [e, e], color=colours(i % 10), linewidth=0.8, alpha=0.6)
                served_markers.append((served * 1e6, e, np.sqrt(area), text))
            labels.append((text, t, e, np.sqrt(area)))
        names = front(report, device, error)
        if names:
            xs, ys = zip(*(points[n] for n in names))
            ax.step(xs, ys, where="post", color="crimson", linestyle="--", linewidth=1.5, zorder=2)
            ax.scatter(xs, ys, s=12, color="crimson", zorder=4)
        elif names is None:
            ax.set_title("Pareto front not called: unstable timings (see bench.md)", fontsize=9, color="crimson")
        ax.set_xscale("log")
        ax.set_yscale("log")
        # Times at 1, 2, 5 of each decade as plain numbers: matplotlib's own labels for a span of
        # one or two decades (2x10^-1, 3x10^-1, ... at every minor tick) run into each other.
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.xaxis.set_minor_locator(LogLocator(base=10, subs=tuple(range(2, 10))))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(f"{reference_mode(report).replace('+', ' + ')}: {'CPU ' if basis == 'cpu' else ''}µs per point "
                      f"({size_label(size)} points per call, {device})")
        ax.set_ylabel("mean distance error, +-1 mm band (mm)" if error == "distance"
                      else "mean normal angle error, +-1 mm band (degrees)")
        ax.grid(True, which="both", alpha=0.3)
        xlo, xhi = ax.get_xlim()
        ax.set_xlim(xlo / 1.5, xhi * 1.5)
        ylo, yhi = ax.get_ylim()
        ax.set_ylim(ylo / 2, yhi * 1.5)
        panels.append((ax, labels, served_markers))
    handles = [Line2D([], [], marker="o", linestyle="", color=colours(i % 10), markersize=8, label=r["label"])
               for i, r in enumerate(rows)]
    handles += [Line2D([], [], color="crimson", linestyle="--", label="Pareto front (embedded)"),
                Line2D([], [], marker="o", linestyle="", color="grey", markersize=8, label="embedded"),
                Line2D([], [], marker="o", linestyle="", markerfacecolor="none", color="grey", markersize=8,
                       label="served (HTTP + msgpack)")]
    fig.legend(handles=handles, loc="lower center", ncol=min(6, len(handles)), fontsize=8, frameon=False)
    m = report["machine"]
    where = m["gpu"] if device.startswith("cuda") else f"{m['cpu']}, {m['cores']} cores"
    animated = ("" if not report.get("animation") else
                f", animated: errors at {len(report['animation']['times_s'])} random times")
    fig.suptitle(f"{report['mesh']['name']}: what accuracy costs in time on {where}{animated} "
                 f"(marker area ~ memory, largest {biggest / 1e6:.1f} MB)", fontsize=11)
    fig.tight_layout(rect=(0, 0.08, 1, 0.95))
    fig.canvas.draw()  # the final layout: labels are placed in display coordinates
    for ax, labels, served_markers in panels:
        place_labels(ax, labels, served_markers)
    return fig
