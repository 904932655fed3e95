"""What a bench report looks like to people: the paper-layout time table, the accuracy table,
ratios to the exact ``mesh`` collider, the Pareto front and the error-vs-time picture.

The *reference time* of a collider (what the front, the plot and the budget picker rank by) is
the median seconds per point of a ``distance+normal+contact`` query of the largest measured size,
embedded, on the device asked for (``cpu`` unless told).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

REFERENCE_MODE = "distance+normal+contact"
ERROR_KEYS = {"distance": "distance_mean_mm", "normal": "normal_mean_deg"}


def timing(row: dict, *, path: str, device: str, mode: str, points: int) -> dict | None:
    for t in row["timings"]:
        if (t["path"], t["device"], t["mode"], t["points"]) == (path, device, mode, points):
            return t
    return None


def reference_seconds_per_point(row: dict, report: dict, device: str = "cpu",
                                path: str = "embedded") -> float | None:
    """Median seconds per point of the largest measured ``distance+normal+contact`` call."""
    size = max(report["config"]["sizes"])
    t = timing(row, path=path, device=device, mode=REFERENCE_MODE, points=size)
    return None if t is None else t["median_s"] / t["points"]


def pareto_front(items: list[tuple[str, float, float]]) -> list[str]:
    """Names of the ``(name, time, error)`` items no other item beats on both time and error
    (<= on both, < on one), ordered by time."""
    front = []
    for name, t, e in items:
        dominated = any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for n2, t2, e2 in items if n2 != name)
        if not dominated:
            front.append((t, name))
    return [name for _, name in sorted(front)]


# -- text tables (Markdown) -------------------------------------------------------------------


def _size_label(n: int) -> str:
    return f"{n // 1_000_000}M" if n % 1_000_000 == 0 else (f"{n // 1000}k" if n % 1000 == 0 else str(n))


def time_tables(report: dict) -> str:
    """One paper-layout table per (path, device, mode): rows = call sizes, a column per
    collider, median milliseconds per call; ``(r)`` after a figure = only r timed repeats."""
    rows = report["colliders"]
    policy = report["config"]["timing"]
    out = []
    combos = sorted({(t["path"], t["device"], t["mode"]) for r in rows for t in r["timings"]},
                    key=lambda c: (c[1], ["embedded", "served"].index(c[0]), c[2] != "distance"))
    for path, device, mode in combos:
        present = [r for r in rows if any((t["path"], t["device"], t["mode"]) == (path, device, mode)
                                          for t in r["timings"])]
        out.append(f"**{mode}, {path}, {device}**: median ms per call")
        out.append("")
        out.append("| points | " + " | ".join(r["label"] for r in present) + " |")
        out.append("|---|" + "---|" * len(present))
        for size in report["config"]["sizes"]:
            cells = []
            for r in present:
                t = timing(r, path=path, device=device, mode=mode, points=size)
                if t is None:
                    cells.append("-")
                    continue
                note = f" ({t['repeats']})" if t["repeats"] < policy["repeats"] else ""
                cells.append(f"{1e3 * t['median_s']:.{_digits(1e3 * t['median_s'])}f}{note}")
            out.append(f"| {_size_label(size)} | " + " | ".join(cells) + " |")
        out.append("")
    out.append(f"Warm-up call first, then the median of up to {policy['repeats']} calls; a cell "
               f"stops repeating once its calls add up to {policy['cell_budget_s']:g} s, and (r) "
               "gives the repeats of such cells.")
    return "\n".join(out)


def _digits(value: float) -> int:
    return 0 if value >= 100 else (1 if value >= 10 else 2)


def accuracy_table(report: dict) -> str:
    """Errors against the exact SDF in the +-1 mm and +-10 mm bands, build cost and memory."""
    n = report["config"]["accuracy_points"]
    out = [f"Errors against the exact SDF on {n:,} points per band (mm, deg); sign errors among "
           "points with abs(d) > 0.2 mm.", "",
           "| collider | +-1 mm: distance mean / p99 / max | sign | normal mean / p99 | "
           "+-10 mm: distance mean / p99 / max | normal mean | build | file | memory |",
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
    """Per collider, relative to ``mesh`` (exact): reference time, and memory."""
    rows = {r["name"]: r for r in report["colliders"]}
    if "mesh" not in rows:
        return ""
    base = reference_seconds_per_point(rows["mesh"], report, device)
    if base is None:
        return ""
    size = max(report["config"]["sizes"])
    out = [f"Relative to `mesh` (exact), {REFERENCE_MODE} on {_size_label(size)} points, embedded, "
           f"{device}: time ratio (below 1 = faster than exact), and the +-1 mm band mean error.", "",
           "| collider | s per 1M points | time / mesh | distance mean (mm) | normal mean (deg) |",
           "|---|---|---|---|---|"]
    for r in report["colliders"]:
        t = reference_seconds_per_point(r, report, device)
        if t is None:
            continue
        a = r["accuracy"]["band_1mm"]
        out.append(f"| {r['label']} | {t * 1e6:.2f} | {t / base:.2f}x | {a['distance_mean_mm']:.4f} | "
                   f"{a['normal_mean_deg']:.2f} |")
    return "\n".join(out)


def summary(report: dict) -> str:
    """Everything a person reads after a run, as Markdown."""
    m = report["machine"]
    parts = [
        f"# collider bench: {report['mesh']['name']} ({report['mesh']['faces']:,} faces, "
        f"{report['mesh']['units']})", "",
        f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['versions'].get('torch')} with "
        f"{m['torch_threads']} threads, GPU {m['gpu'] or 'none'}; load average "
        f"{_load(m['load_average_start'])} at start, {_load(m['load_average_end'])} at the end; "
        f"{report['seconds'] / 60:.1f} min in all.", "",
        time_tables(report), "", accuracy_table(report), "", ratio_table(report), "",
    ]
    for device in report["config"]["devices"]:
        parts.append(front_text(report, device))
    if report["skipped"]:
        parts += ["", "Not measured:"] + [f"- {s['name']}: {s['reason']}" for s in report["skipped"]]
    return "\n".join(parts) + "\n"


def _load(value) -> str:
    return "?" if value is None else f"{value:.1f}"


def front_items(report: dict, device: str, error: str) -> list[tuple[str, float, float]]:
    items = []
    for r in report["colliders"]:
        t = reference_seconds_per_point(r, report, device)
        if t is not None:
            items.append((r["name"], t, r["accuracy"]["band_1mm"][ERROR_KEYS[error]]))
    return items


def front_text(report: dict, device: str) -> str:
    labels = {r["name"]: r["label"] for r in report["colliders"]}
    lines = []
    for error in ERROR_KEYS:
        names = pareto_front(front_items(report, device, error))
        if names:
            lines.append(f"Pareto front ({device}, time vs {error} error): " + ", ".join(labels[n] for n in names))
    return "\n".join(lines)


def place_labels(ax, labels: list[tuple[str, float, float, float]],
                 obstacles: list[tuple[float, float, float]] = ()) -> None:
    """Annotate each ``(text, x, y, marker diameter in points)`` near its marker: the first of
    a few offsets (growing rings around the marker) whose box overlaps no marker and no label
    placed before, with a thin leader line when it had to move away (clustered colliders, e.g.
    voxel grids of similar speed, would otherwise print over each other)."""
    to_points = 72.0 / ax.figure.dpi
    centres = [tuple(ax.transData.transform((x, y)) * to_points) + (size,) for _, x, y, size in labels]
    others = [tuple(ax.transData.transform((x, y)) * to_points) + (size,) for x, y, size in obstacles]
    placed = [(cx - s / 2, cy - s / 2, cx + s / 2, cy + s / 2) for cx, cy, s in centres + others]
    for (text, x, y, size), (px, py, _) in sorted(zip(labels, centres), key=lambda item: item[0][1]):
        width, height = 5.0 * len(text), 10.0
        choice = None
        for ring in range(4):
            gap = size / 2 + 3 + 14 * ring
            for dx, dy, ha in ((0, -gap - height, "center"), (0, gap, "center"), (gap, -height / 2, "left"),
                               (-gap, -height / 2, "right"), (gap * 0.7, gap * 0.7, "left"),
                               (gap * 0.7, -gap * 0.7 - height, "left"), (-gap * 0.7, gap * 0.7, "right"),
                               (-gap * 0.7, -gap * 0.7 - height, "right")):
                left = px + dx - {"center": width / 2, "left": 0, "right": width}[ha]
                box = (left, py + dy, left + width, py + dy + height)
                if not any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3] for b in placed):
                    choice = (dx, dy, ha, box, ring)
                    break
            if choice:
                break
        if choice is None:  # nowhere free: below the marker anyway
            gap = size / 2 + 3
            choice = (0, -gap - height, "center", (px - width / 2, py - gap - height, px + width / 2, py - gap), 0)
        dx, dy, ha, box, ring = choice
        placed.append(box)
        arrow = {"arrowstyle": "-", "color": "grey", "linewidth": 0.6} if ring else None
        ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy), ha=ha, va="bottom", fontsize=8,
                    arrowprops=arrow)


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


def plot(report: dict, output: Path, device: str = "cpu") -> Path:
    """Two panels, distance and normal error (+-1 mm band, log) against the reference time per
    point (log); marker area ~ memory; the Pareto front as a dashed staircase; embedded as filled
    markers and served (same query through ``collider serve``) as open ones."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    rows = [r for r in report["colliders"] if reference_seconds_per_point(r, report, device) is not None]
    size = max(report["config"]["sizes"])
    colours = plt.get_cmap("tab10")
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.4))
    floor = {"distance": 1e-4, "normal": 1e-2}  # exact colliders (error 0) drawn on this floor
    biggest = max(r["memory_bytes"] for r in rows)
    for ax, (error, key) in zip(axes, ERROR_KEYS.items()):
        points, labels, served_markers = {}, [], []
        for i, r in enumerate(rows):
            t = reference_seconds_per_point(r, report, device) * 1e6
            e = max(r["accuracy"]["band_1mm"][key], floor[error])
            points[r["name"]] = (t, e)
            area = 30 + 600 * np.sqrt(r["memory_bytes"] / biggest)
            ax.scatter(t, e, s=area, color=colours(i % 10), alpha=0.8, edgecolors="black", linewidths=0.6,
                       zorder=3)
            served = reference_seconds_per_point(r, report, device, "served")
            if served is not None:
                ax.scatter(served * 1e6, e, s=area, facecolors="none", edgecolors=colours(i % 10),
                           linewidths=1.2, zorder=3)
                ax.plot([t, served * 1e6], [e, e], color=colours(i % 10), linewidth=0.8, alpha=0.6)
                served_markers.append((served * 1e6, e, np.sqrt(area)))
            exact = " (error 0, drawn on the floor)" if r["accuracy"]["band_1mm"][key] < floor[error] else ""
            labels.append((f"{r['label']}{exact}", t, e, np.sqrt(area)))
        front = pareto_front([(n, t, e) for n, (t, e) in points.items()])
        if front:
            xs, ys = zip(*(points[n] for n in front))
            ax.step(xs, ys, where="post", color="crimson", linestyle="--", linewidth=1.5, zorder=2)
            ax.scatter(xs, ys, s=12, color="crimson", zorder=4)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"distance + normal + contact: microseconds per point ({_size_label(size)} points "
                      f"per call, {device})")
        ax.set_ylabel("mean distance error, +-1 mm band (mm)" if error == "distance"
                      else "mean normal angle error, +-1 mm band (degrees)")
        ax.grid(True, which="both", alpha=0.3)
        xlo, xhi = ax.get_xlim()
        ax.set_xlim(xlo / 1.5, xhi * 1.5)
        ylo, yhi = ax.get_ylim()
        ax.set_ylim(ylo / 2, yhi * 1.5)
        place_labels(ax, labels, served_markers)
    handles = [Line2D([], [], marker="o", linestyle="", color=colours(i % 10), markersize=8, label=r["label"])
               for i, r in enumerate(rows)]
    handles += [Line2D([], [], color="crimson", linestyle="--", label="Pareto front (embedded)"),
                Line2D([], [], marker="o", linestyle="", color="grey", markersize=8, label="embedded"),
                Line2D([], [], marker="o", linestyle="", markerfacecolor="none", color="grey", markersize=8,
                       label="served (HTTP + msgpack)")]
    fig.legend(handles=handles, loc="lower center", ncol=min(6, len(handles)), fontsize=8, frameon=False)
    m = report["machine"]
    where = m["gpu"] if device.startswith("cuda") else f"{m['cpu']}, {m['cores']} cores"
    fig.suptitle(f"{report['mesh']['name']}: what accuracy costs in time on {where} "
                 f"(marker area ~ memory, largest {biggest / 1e6:.1f} MB)", fontsize=11)
    fig.tight_layout(rect=(0, 0.08, 1, 0.95))
    output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(output, dpi=110)
    plt.close(fig)
    return output
