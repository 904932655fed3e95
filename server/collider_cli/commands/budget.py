"""``collider bake MESH --max-error ...``: an error budget in, the fastest collider that meets it
out (the candidates measured as ``collider bench`` measures them, :mod:`collider_cli.bench`)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from .diagnostics import print_mesh_check
from .options import cache_dir, cache_size_line, load_placed_mesh

#: Seed of the check after a pick (``collider eval``'s default; the bench uses 0 and 1).
FRESH_SEED = 1234
#: Points per set of that check (``collider eval``'s default).
FRESH_POINTS = 100_000
#: How the bake measures the candidates itself (no --bench): points per call of their timing,
#: points per band of their accuracy, and the timing policy's rounds and seconds per cell
#: (:class:`~collider_cli.bench.TimingPolicy`; ``collider bench``'s interleaved rounds).
BUDGET_POINTS = 100_000
BUDGET_ACCURACY_POINTS = 40_000
BUDGET_TIMING = {"repeats": 5, "cell_budget_s": 10.0}


def add_budget_arguments(bake) -> None:
    """The error-budget options of ``collider bake`` (with them, bake picks the kind itself)."""
    group = bake.add_argument_group(
        "error budget", "with --max-error, bake measures the candidates (or reads --bench) and builds "
        "the fastest collider whose mean errors in the +-1 mm band meet every limit; --kind and "
        "--resolution are then chosen, not taken")
    group.add_argument("--max-error", default=None, help="mean distance error, e.g. 0.05mm (bare number: mm)")
    group.add_argument("--max-normal-error", default=None, help="mean normal angle error, e.g. 3deg")
    group.add_argument("--max-memory", default=None,
                       help="memory of the collider's arrays, e.g. 8MB (default for the candidates: 128MiB)")
    group.add_argument("--train-minutes", type=float, default=None,
                       help="also train each neural preset that has no trained model of this mesh in --models "
                            "for this many minutes, and consider it (default: only trained models)")
    group.add_argument("--bench", type=Path, default=None,
                       help="pick from this bench.json of `collider bench` (same mesh and placement) "
                            "instead of measuring now")


def budget_from_args(args):
    from ..bench.budget import Budget, angle_deg, length_mm, size_bytes

    if args.max_error is None:
        if any(v is not None for v in (args.max_normal_error, args.max_memory, args.bench, args.train_minutes)):
            raise ValueError("--max-normal-error, --max-memory, --train-minutes and --bench need --max-error")
        return None
    if args.train_minutes is not None and args.bench is not None:
        raise ValueError("--train-minutes trains candidates to measure them now; --bench reads figures "
                         "measured before: give one of them")
    return Budget(length_mm(args.max_error),
                  None if args.max_normal_error is None else angle_deg(args.max_normal_error),
                  None if args.max_memory is None else size_bytes(args.max_memory))


def run_budget_bake(args, budget) -> int:
    """``collider bake MESH --max-error ...``: measure (or read) the candidates, build the fastest
    collider that meets the budget, check it with a fresh evaluation (another seed), save it."""
    from collider_server.engine.repository import ModelRepository, check_name

    from ..bench import NothingMeetsBudget, rank

    check_name(args.name)
    ModelRepository(args.models).check_writable()  # before the measuring, not after
    mesh, transform, units, meters_per_unit = load_placed_mesh(args)
    check = print_mesh_check(mesh)
    device = _bake_device(args.device)
    report = _budget_report(args, budget, mesh, transform, units, meters_per_unit, device)
    if report.get("interrupted"):
        raise KeyboardInterrupt  # its measured figures are written; nothing was picked
    try:
        ranked = rank(report, budget, device)
    except NothingMeetsBudget as exc:
        print(f"collider bake: {exc}", file=sys.stderr)
        return 1
    print_ranking(report, ranked, budget, device)
    for row in ranked:
        if _build_and_check(args, row, report, budget, mesh, transform, units, meters_per_unit, device, check):
            return 0
    print(f"collider bake: every collider that met {budget.describe()} in the measurement missed it in the "
          "fresh evaluation; nothing was saved", file=sys.stderr)
    return 1


def print_ranking(report: dict, ranked: list[dict], budget, device: str) -> None:
    """Every measured collider: its reference time (+- spread) and whether it meets the budget
    (and why not); then which colliders were equally fast as the pick, and unstable figures."""
    from ..bench.budget import equally_fast, format_bytes
    from ..bench.report import (
        ranking_basis,
        reference_seconds_per_point,
        reference_spread,
        unstable_references,
    )

    basis = ranking_basis(report, device)
    meeting = {r["name"] for r in ranked}
    print(f"measured colliders ({device}, distance+normal+contact, {'CPU ' if basis == 'cpu' else ''}s per 1M "
          f"points +- spread; +-1 mm band mean errors), for {budget.describe()}:")

    def seconds(row):
        t = reference_seconds_per_point(row, report, device, basis=basis or "wall")
        return float("inf") if t is None else t

    for r in sorted(report["colliders"], key=seconds):
        if seconds(r) == float("inf"):
            continue
        a = r["accuracy"]["band_1mm"]
        spread = f" +-{100 * reference_spread(r, report, device, basis or 'wall'):3.0f}%"
        verdict = "meets" if r["name"] in meeting else "misses: " + "; ".join(budget.misses(r))
        print(f"  {r['label']:<34} {seconds(r) * 1e6:8.2f}{spread}  {a['distance_mean_mm']:.4f} mm  "
              f"{a['normal_mean_deg']:5.2f} deg  {format_bytes(r['memory_bytes']):>9}  {verdict}")
    for skipped in report.get("skipped", []):
        print(f"  not measured: {skipped['name']}: {skipped['reason']}")
    tied = equally_fast(report, ranked, device)
    if tied:
        print(f"{ranked[0]['label']} and {', '.join(r['label'] for r in tied)} are equally fast within the "
              "measurement; the pick is the one with the least memory")
    if basis == "cpu":
        print("ranked by process CPU time per point: the wall times were unstable or ranked otherwise (the load of "
              "the moment)")
    elif basis is None:
        print(f"warning: unstable timings ({', '.join(unstable_references(report, device))}), wall and CPU: the "
              "ranking by speed may differ in another run; the budget itself is checked afresh below",
              file=sys.stderr)


def _bake_device(device: str | None) -> str:
    from collider_server.engine.devices import resolve_device

    resolved = resolve_device(device)
    return "cuda" if resolved.startswith("cuda") else "cpu"


def _budget_report(args, budget, mesh, transform, units, meters_per_unit, device) -> dict:
    """The bench report the pick is made from: ``--bench``'s file, or measured now (embedded,
    :data:`BUDGET_POINTS` points per call, the same interleaved timing as ``collider bench``),
    its figures written to the cache (``budget-NAME/``)."""
    from ..bench import BenchConfig, PlanConfig, TimingPolicy, run_bench
    from ..bench.report import interrupted_line, write_outputs
    from .bench import add_hints

    if args.bench is not None:
        try:
            report = json.loads(args.bench.read_text())
            source = report["mesh"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{args.bench}: not a bench.json of `collider bench` ({exc})") from None
        if source.get("sha256") != mesh.sha256 or not np.allclose(source.get("transform"), transform):
            from .hints import command, placement_options

            raise ValueError(f"{args.bench} measured another mesh or placement ({source.get('path')}, "
                             f"transform {source.get('transform')}); measure this one with "
                             f"`{command('bench', args.mesh, *placement_options(args))}`")
        return report
    plan = PlanConfig(padding=args.padding, train_minutes=args.train_minutes or 0.0,
                      max_memory_bytes=budget.max_memory_bytes or PlanConfig().max_memory_bytes)
    config = BenchConfig(sizes=(BUDGET_POINTS,), accuracy_points=BUDGET_ACCURACY_POINTS, paths=("embedded",),
                         devices=(device,), plan=plan, timing=TimingPolicy(**BUDGET_TIMING))
    cache = cache_dir(args)
    print(f"measuring the candidates of {args.mesh} ({device}, embedded, {BUDGET_POINTS:,} points per call) ...",
          file=sys.stderr)
    report = run_bench(mesh, transform, config, units=units, meters_per_unit=meters_per_unit,
                       models_root=args.models, cache=cache, mesh_path=str(args.mesh),
                       show_progress=not args.quiet)
    add_hints(report, args)
    paths = write_outputs(report, cache / f"budget-{args.name}")
    print(f"measured figures: {paths['markdown']}, {paths['json']}")
    if report.get("interrupted"):
        print(interrupted_line(paths), file=sys.stderr)
    print(cache_size_line(cache))
    return report


def _build_and_check(args, row, report, budget, mesh, transform, units, meters_per_unit, device,
                     check) -> bool:
    """Build ``row``'s collider, evaluate it afresh (seed :data:`FRESH_SEED`), save it if it
    meets the budget. Prints what it measured either way, naming every limit it checked."""
    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.evaluation import evaluate_collider, format_report

    from ..bench.budget import format_bytes
    from ..bench.plan import Candidate, build_candidate
    from ..bench.report import ranking_basis, reference_seconds_per_point

    repo = ModelRepository(args.models)
    candidate = Candidate(row["name"], row["label"], row["kind"], row["settings"], build=row["build"])
    if candidate.build == "trained":  # an existing model: the very file the bench measured
        candidate.path = Path(row["settings"]["model_file"])
    collider = build_candidate(candidate, mesh, transform, units=units, meters_per_unit=meters_per_unit,
                               cache=cache_dir(args), show_progress=not args.quiet)
    basis = ranking_basis(report, device) or "wall"
    seconds = reference_seconds_per_point(row, report, device, basis=basis)
    bench = row["accuracy"]["band_1mm"]
    print(f"picked {row['label']}: the fastest measured collider meeting {budget.describe()}: "
          f"{seconds * 1e6:.2f} {'CPU ' if basis == 'cpu' else ''}s per 1M points ({device}), mean distance error "
          f"{bench['distance_mean_mm']:.4f} mm, normal {bench['normal_mean_deg']:.2f} deg, "
          f"{format_bytes(row['memory_bytes'])} (measured with seed {report['config']['seed']})")
    fresh = evaluate_collider(collider, mesh, points=FRESH_POINTS, seed=FRESH_SEED, reconstruction=False,
                              show_progress=not args.quiet)
    checks = budget.checks(fresh["band_1mm"], collider.nbytes())
    print(format_report(args.name, collider.info.kind, fresh))
    verdict = "; ".join(text for _, text in checks)
    if not all(met for met, _ in checks):
        print(f"fresh evaluation (seed {FRESH_SEED}, {FRESH_POINTS:,} points per band) misses the budget: {verdict}; "
              "trying the next candidate", file=sys.stderr)
        return False
    collider.info.name = args.name
    collider.info.accuracy = fresh
    collider.info.source["check"] = check.to_dict()
    collider.info.source["path"] = str(Path(args.mesh).resolve())
    collider.info.settings["picked_for_budget"] = {
        "max_error_mm": budget.max_error_mm, "max_normal_error_deg": budget.max_normal_error_deg,
        "max_memory_bytes": budget.max_memory_bytes, "candidate": row["name"],
        "bench_seconds_per_million": seconds * 1e6}
    path = save_collider(collider, repo.path(args.name))
    print(f"fresh evaluation (seed {FRESH_SEED}, {FRESH_POINTS:,} points per band) meets the budget: {verdict}")
    print(f"sign errors: {fresh['band_1mm']['sign_errors_percent']:.2f} % of the +-1 mm band points farther than "
          "0.2 mm from the surface (fresh evaluation, against the exact winding-number sign)"
          + ("" if check.watertight else "; the mesh is not watertight: sign errors gather near its holes"))
    print(f"wrote {path} ({path.stat().st_size:,} bytes, kind {collider.info.kind}"
          + (f", resolution {row['settings']['resolution']}" if row["kind"] == "voxel" else "") + ")")
    return True
