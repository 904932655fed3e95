"""A bench report as text: the paper-layout time table, the accuracy table, ratios to the exact
``mesh`` collider, the Pareto front's lines and the whole Markdown summary (``bench.md``). The
ranking they show is :mod:`.ranking`'s."""

from __future__ import annotations

from .ranking import (
    ERROR_KEYS,
    TIE,
    front,
    ranking_basis,
    reference_mode,
    reference_seconds_per_point,
    reference_timing,
    timing,
    unstable_references,
)


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
    animation, skinned = report.get("animation"), report.get("skinned")
    against = ("the exact SDF" if animation is None else
               f"the exact interpolated mesh at {len(animation['times_s'])} random times (above), pooled,")
    if skinned:
        against = (f"the exact skin (its union) at {report['config']['plan']['poses']} random poses (above; "
                   "the clip times in the table below), pooled,")
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
        *_mesh_lines(report), *_animation_lines(report), *_skinned_lines(report), time_tables(report), "",
        accuracy_table(report), "", *_pose_set_table(report),
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


def _skinned_lines(report: dict) -> list[str]:
    """A skinned bench's character, its pose sets and the poses its queries were timed at."""
    s = report.get("skinned")
    if not s:
        return []
    plan, at = report["config"]["plan"], s["timed_at"]
    return [(f"Skinned: {s['joints']} joints, clips {', '.join(str(c) for c in s['clips']) or 'none'}. Errors at "
             f"{plan['times']} random clip times (asked by clip and time) and at {plan['poses']} random poses "
             f"(random clip times, every joint's local rotation then turned by up to {s['perturb_deg']:g} deg; asked "
             f"by joint transforms), apart; queries timed at clip {at['clip_times']['clip']} "
             f"t = {at['clip_times']['time_s']:.4f} s (clip time) and at one more random pose (random pose)."), ""]


def _pose_set_table(report: dict) -> list[str]:
    """A skinned bench's +-1 mm band errors in each pose set, side by side."""
    from collider_server.making.evaluation import SKINNED_POSE_SETS

    if not report.get("skinned"):
        return []
    out = ["+-1 mm band per pose set (mm, deg): distance mean / p99 / max, sign errors, normal mean.", "",
           "| collider | " + " | ".join(n.replace("_", " ") for n in SKINNED_POSE_SETS) + " |",
           "|---|" + "---|" * len(SKINNED_POSE_SETS)]
    for r in report["colliders"]:
        cells = []
        for name in SKINNED_POSE_SETS:
            a = r["accuracy"][name]["band_1mm"]
            cells.append(f"{a['distance_mean_mm']:.4f} / {a['distance_p99_mm']:.3f} / {a['distance_max_mm']:.3f}, "
                         f"{a['sign_errors_percent']:.3f} %, {a['normal_mean_deg']:.2f}")
        out.append(f"| {r['label']} | " + " | ".join(cells) + " |")
    return [*out, ""]


def _mesh_lines(report: dict) -> list[str]:
    from collider_server.making.mesh_check import MeshCheck

    check = report["mesh"].get("check")
    return [] if not check else [*MeshCheck.from_dict(check).lines(), ""]


def _load(value) -> str:
    return "?" if value is None else f"{value:.1f}"


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
