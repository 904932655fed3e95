"""A bench report's files: ``bench.json``, ``bench.md`` and the error-vs-time picture per device
(:func:`figure`, matplotlib)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .labels import place_labels
from .ranking import ERROR_KEYS, front, ranking_basis, reference_mode, reference_seconds_per_point
from .tables import size_label, summary


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
