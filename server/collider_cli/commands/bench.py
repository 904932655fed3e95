"""``collider bench MESH`` and ``collider bake MESH --max-error ...`` (the error budget)."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from .options import (
    add_device_argument,
    add_models_argument,
    add_placement_arguments,
    add_quiet_argument,
    placement_from_args,
)

SUFFIXES = {"k": 1_000, "M": 1_000_000}


def _ints(text: str) -> tuple[int, ...]:
    """``"10k,40k,1M"`` or ``"10000,40000"`` -> (10000, 40000, ...)."""
    values = []
    for item in (v.strip().replace("_", "") for v in text.split(",")):
        if not item:
            continue
        factor = SUFFIXES.get(item[-1], 1)
        try:
            values.append(int(item[:-1] if factor > 1 else item) * factor)
        except ValueError:
            raise ValueError(f"expected comma-separated integers (10k, 1M allowed), got {text!r}") from None
    return tuple(values)


def register(subparsers) -> None:
    bench = subparsers.add_parser(
        "bench", help="what accuracy costs in time: every collider kind of a mesh, measured here",
        description="Builds kdtree, mesh, voxel grids (up to --max-memory) and the neural presets "
                    "of MESH, measures their errors against the exact SDF (+-1 mm and +-10 mm "
                    "bands) and their query time (10k, 40k, 1M points; distance, and "
                    "distance+normal+contact; embedded and through a real `collider serve`; CPU, "
                    "and CUDA when present). Writes bench.json (every raw figure and the machine), "
                    "bench.md (tables) and bench-DEVICE.png (error vs time, Pareto front).")
    bench.add_argument("mesh", help="mesh file (OBJ, PLY, STL, OFF, GLB)")
    add_placement_arguments(bench)
    bench.add_argument("--quick", action="store_true",
                       help="a small run (under a minute): 10k and 40k points, voxel 32 and 64, 2 repeats")
    bench.add_argument("--kinds", default=None, help="comma-separated subset of kdtree,mesh,voxel,neural")
    bench.add_argument("--resolutions", default=None, help="voxel resolutions to try (default 64,128,256,512)")
    bench.add_argument("--max-memory", default=None,
                       help="largest collider memory, e.g. 128MiB (default); voxel grids stop before it")
    bench.add_argument("--train-minutes", type=float, default=None,
                       help="train each neural preset without a trained model of this mesh for this long "
                            "(default 0: list them as not measured)")
    bench.add_argument("--presets", default=None,
                       help="comma-separated neural presets to include (default: every preset)")
    bench.add_argument("--sizes", default=None, help="points per query call (default 10k,40k,1M)")
    bench.add_argument("--accuracy-points", type=int, default=None, help="points per band (default 40000)")
    bench.add_argument("--repeats", type=int, default=None, help="most timed calls per cell (default 5)")
    bench.add_argument("--cell-seconds", type=float, default=None,
                       help="a cell stops repeating once its calls took this long (default 10)")
    bench.add_argument("--no-served", action="store_true", help="skip the served (HTTP) half")
    add_device_argument(bench, "cpu or cuda (default: cpu, and cuda when present)")
    bench.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    bench.add_argument("--seed", type=int, default=0)
    add_models_argument(bench, "searched for trained neural models of MESH")
    bench.add_argument("--output", type=Path, default=None, help="folder of the results (default out/bench-MESH)")
    bench.add_argument("--cache", type=Path, default=Path("out/bench-cache"),
                       help="baked grids and bench-trained networks are kept here")
    add_quiet_argument(bench)
    bench.set_defaults(func=run_bench_command)


def placed_mesh(args):
    """(mesh in the collider frame, 4x4 transform applied, units, metres per unit)."""
    from collider_server.making.mesh_files import load_mesh

    placement = placement_from_args(args)
    mesh, transform = placement.apply(load_mesh(args.mesh))
    return mesh, transform, placement.units, placement.meters_per_unit


def bench_config(args):
    from ..bench import QUICK, BenchConfig
    from ..bench.budget import size_bytes

    base = QUICK if args.quick else BenchConfig()
    plan = base.plan
    if args.kinds is not None:
        plan = dataclasses.replace(plan, kinds=tuple(k.strip() for k in args.kinds.split(",") if k.strip()))
    if args.resolutions is not None:
        plan = dataclasses.replace(plan, resolutions=_ints(args.resolutions))
    if args.max_memory is not None:
        plan = dataclasses.replace(plan, max_memory_bytes=size_bytes(args.max_memory))
    if args.train_minutes is not None:
        plan = dataclasses.replace(plan, train_minutes=args.train_minutes)
    if args.presets is not None:
        plan = dataclasses.replace(plan, presets=tuple(p.strip() for p in args.presets.split(",") if p.strip()))
    timing = base.timing
    if args.repeats is not None:
        timing = dataclasses.replace(timing, repeats=args.repeats)
    if args.cell_seconds is not None:
        timing = dataclasses.replace(timing, cell_budget_s=args.cell_seconds)
    devices = None
    if args.device is not None:
        devices = (args.device,)
    return dataclasses.replace(
        base, plan=plan, timing=timing, devices=devices, seed=args.seed, threads=args.threads,
        sizes=_ints(args.sizes) if args.sizes else base.sizes,
        accuracy_points=args.accuracy_points if args.accuracy_points is not None else base.accuracy_points,
        paths=("embedded",) if args.no_served else base.paths)


def run_bench_command(args) -> int:
    from ..bench import run_bench
    from ..bench.report import summary, write_outputs

    config = bench_config(args)
    config.check()
    _check_device(config.devices)
    mesh, transform, units, meters_per_unit = placed_mesh(args)
    output = args.output or Path("out") / f"bench-{Path(args.mesh).stem}"
    report = run_bench(mesh, transform, config, units=units, meters_per_unit=meters_per_unit,
                       models_root=args.models, cache=args.cache, work_dir=output,
                       mesh_path=str(args.mesh), show_progress=not args.quiet)
    paths = write_outputs(report, output)
    print(summary(report))
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def _check_device(devices) -> None:
    if devices is None:
        return
    for device in devices:
        if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
            raise ValueError(f"--device must be cpu or cuda, got {device!r}")
        if device.startswith("cuda"):
            import torch

            if not torch.cuda.is_available():
                raise ValueError("--device cuda: no CUDA GPU on this machine")


# -- collider bake MESH --max-error ... ----------------------------------------------------------


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
    group.add_argument("--bench", type=Path, default=None,
                       help="pick from this bench.json of `collider bench` (same mesh and placement) "
                            "instead of measuring now")


def budget_from_args(args):
    from ..bench.budget import Budget, angle_deg, length_mm, size_bytes

    if args.max_error is None:
        if args.max_normal_error is not None or args.max_memory is not None or args.bench is not None:
            raise ValueError("--max-normal-error, --max-memory and --bench need --max-error")
        return None
    return Budget(length_mm(args.max_error),
                  None if args.max_normal_error is None else angle_deg(args.max_normal_error),
                  None if args.max_memory is None else size_bytes(args.max_memory))


def run_budget_bake(args, budget) -> int:
    """``collider bake MESH --max-error ...``: measure (or read) the front, build the fastest
    collider that meets the budget, check it with a fresh evaluation (another seed), save it."""
    from collider_server.engine.repository import check_name

    from ..bench import NothingMeetsBudget, rank

    check_name(args.name)
    mesh, transform, units, meters_per_unit = placed_mesh(args)
    device = _bake_device(args.device)
    report = _budget_report(args, budget, mesh, transform, units, meters_per_unit, device)
    try:
        ranked = rank(report, budget, device)
    except NothingMeetsBudget as exc:
        print(f"collider bake: {exc}", file=sys.stderr)
        return 1
    print_ranking(report, ranked, budget, device)
    for row in ranked:
        if _build_and_check(args, row, report, budget, mesh, transform, units, meters_per_unit, device):
            return 0
    print(f"collider bake: every collider that met {budget.describe()} in the bench missed it in the "
          "fresh evaluation; nothing was saved", file=sys.stderr)
    return 1


def print_ranking(report: dict, ranked: list[dict], budget, device: str) -> None:
    """Every measured collider: its reference time and whether it meets the budget (and why not)."""
    from ..bench.report import reference_seconds_per_point

    meeting = {r["name"] for r in ranked}
    print(f"measured colliders ({device}, distance+normal+contact, s per 1M points; "
          f"+-1 mm band mean errors), for {budget.describe()}:")
    rows = sorted(report["colliders"], key=lambda r: reference_seconds_per_point(r, report, device) or float("inf"))
    for r in rows:
        t = reference_seconds_per_point(r, report, device)
        if t is None:
            continue
        a = r["accuracy"]["band_1mm"]
        verdict = "meets" if r["name"] in meeting else "misses: " + "; ".join(budget.misses(r))
        print(f"  {r['label']:<34} {t * 1e6:8.2f}  {a['distance_mean_mm']:.4f} mm  {a['normal_mean_deg']:5.2f} deg  "
              f"{r['memory_bytes'] / 1e6:7.2f} MB  {verdict}")
    for skipped in report.get("skipped", []):
        print(f"  not measured: {skipped['name']}: {skipped['reason']}")


def _bake_device(device: str | None) -> str:
    from collider_server.engine.devices import resolve_device

    resolved = resolve_device(device)
    return "cuda" if resolved.startswith("cuda") else "cpu"


def _budget_report(args, budget, mesh, transform, units, meters_per_unit, device) -> dict:
    from ..bench import BenchConfig, PlanConfig, TimingPolicy, run_bench

    if args.bench is not None:
        try:
            report = json.loads(args.bench.read_text())
            source = report["mesh"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{args.bench}: not a bench.json of `collider bench` ({exc})") from None
        if source.get("sha256") != mesh.sha256 or not np.allclose(source.get("transform"), transform):
            raise ValueError(f"{args.bench} measured another mesh or placement ({source.get('path')}, "
                             f"transform {source.get('transform')}); run `collider bench` on this one")
        return report
    plan = PlanConfig(padding=args.padding, max_memory_bytes=budget.max_memory_bytes or PlanConfig().max_memory_bytes)
    config = BenchConfig(sizes=(100_000,), paths=("embedded",), devices=(device,), plan=plan,
                         timing=TimingPolicy(repeats=3, cell_budget_s=10.0))
    from ..bench.report import write_outputs

    work_dir = Path("out") / f"bake-{args.name}"
    print(f"measuring the candidates of {args.mesh} ({device}, embedded, 100k points per call) ...",
          file=sys.stderr)
    report = run_bench(mesh, transform, config, units=units, meters_per_unit=meters_per_unit,
                       models_root=args.models, work_dir=work_dir, mesh_path=str(args.mesh),
                       show_progress=not args.quiet)
    paths = write_outputs(report, work_dir)
    print(f"measured figures: {paths['markdown']}, {paths['json']}")
    return report


def _build_and_check(args, row, report, budget, mesh, transform, units, meters_per_unit, device) -> bool:
    """Build ``row``'s collider, evaluate it afresh (seed ``FRESH_SEED``), save it if it meets
    the budget. Prints what it measured either way."""
    import tempfile

    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.evaluation import evaluate_collider, format_report

    from ..bench.plan import Candidate, build_candidate
    from ..bench.report import reference_seconds_per_point

    repo = ModelRepository(args.models)
    candidate = Candidate(row["name"], row["label"], row["kind"], row["settings"], build=row["build"])
    if candidate.build == "trained":  # an existing model: the very file the bench measured
        candidate.path = Path(row["settings"]["model_file"])
    with tempfile.TemporaryDirectory() as scratch:
        collider = build_candidate(candidate, mesh, transform, units=units, meters_per_unit=meters_per_unit,
                                   cache=Path("out/bench-cache"), out_dir=Path(scratch),
                                   show_progress=not args.quiet)
    seconds = reference_seconds_per_point(row, report, device)
    bench = row["accuracy"]["band_1mm"]
    print(f"picked {row['label']}: the fastest measured collider meeting {budget.describe()}: "
          f"{seconds * 1e6:.2f} s per 1M points ({device}), mean distance error "
          f"{bench['distance_mean_mm']:.4f} mm, normal {bench['normal_mean_deg']:.2f} deg, "
          f"{row['memory_bytes'] / 1e6:.2f} MB (bench, seed {report['config']['seed']})")
    fresh = evaluate_collider(collider, mesh, points=100_000, seed=FRESH_SEED, reconstruction=False,
                              show_progress=not args.quiet)
    misses = budget.misses_figures(fresh["band_1mm"], collider.nbytes())
    print(format_report(args.name, collider.info.kind, fresh))
    if misses:
        print(f"fresh evaluation (seed {FRESH_SEED}) misses the budget: {'; '.join(misses)}; trying the "
              "next candidate", file=sys.stderr)
        return False
    collider.info.name = args.name
    collider.info.accuracy = fresh
    collider.info.settings["picked_for_budget"] = {
        "max_error_mm": budget.max_error_mm, "max_normal_error_deg": budget.max_normal_error_deg,
        "max_memory_bytes": budget.max_memory_bytes, "candidate": row["name"],
        "bench_seconds_per_million": seconds * 1e6}
    path = save_collider(collider, repo.path(args.name))
    print(f"fresh evaluation (seed {FRESH_SEED}, 100,000 points per band) meets the budget: mean "
          f"distance error {fresh['band_1mm']['distance_mean_mm']:.4f} mm <= {budget.max_error_mm:g} mm")
    print(f"wrote {path} ({path.stat().st_size:,} bytes, kind {collider.info.kind}"
          + (f", resolution {row['settings']['resolution']}" if row["kind"] == "voxel" else "") + ")")
    return True


#: Seed of the check after a pick (``collider eval``'s default; the bench uses 0 and 1).
FRESH_SEED = 1234
