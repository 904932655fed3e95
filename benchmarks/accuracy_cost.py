"""What accuracy costs in time: every collider kind of the Stanford bunny on one plot.

For each collider (voxel grids at several resolutions, the exact mesh, the kd-tree baseline, the
shipped neural bunny and, optionally, others given with --model), measured in ONE run on this
machine: the error against the exact SDF on points in the +-1 mm band (distance mean and p99, normal
angle mean) and the time of a distance + normal + contact query, scaled to 1M points; plus the
model's size. Prints a table and writes a PNG (time vs error, marker area ~ file size).

    python benchmarks/accuracy_cost.py                      # ~5 min on 2 cores
    python benchmarks/accuracy_cost.py --resolutions 64 128 --output out/accuracy_cost.png

Lengths in mm, times in seconds per 1M points, sizes in bytes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BUNNY = REPO.parent / "shared" / "data" / "meshes" / "stanford-bunny.obj"


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=BUNNY)
    parser.add_argument("--resolutions", type=int, nargs="*", default=[64, 128, 256])
    parser.add_argument("--model", action="append", default=None,
                        help="model names/paths to include (default: the shipped 'bunny')")
    parser.add_argument("--models", type=Path, default=REPO / "models")
    parser.add_argument("--points", type=int, default=20_000, help="accuracy points in the +-1 mm band")
    parser.add_argument("--timing-points", type=int, default=100_000)
    parser.add_argument("--cache", type=Path, default=REPO / "out", help="where baked grids are kept")
    parser.add_argument("--output", type=Path, default=REPO / "docs" / "accuracy_cost.png")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    return parser.parse_args(argv)


def colliders(args, mesh):
    """(label, collider, file bytes) for every collider of the comparison, baking grids as needed."""
    from collider_server.bake import bake_collider
    from collider_server.modelfile import load_collider, save_collider
    from collider_server.repository import ModelRepository

    for resolution in args.resolutions:
        path = args.cache / f"bunny-voxel-{resolution}.safetensors"
        if not path.is_file():
            save_collider(bake_collider(mesh, "voxel", f"bunny-voxel-{resolution}", resolution=resolution), path)
        yield f"voxel {resolution}^3", load_collider(path), path.stat().st_size
    for kind in ("mesh", "kdtree"):
        collider = bake_collider(mesh, kind, f"bunny-{kind}", show_progress=False)
        size = sum(a.nbytes for a in collider.tensors().values())
        yield kind + (" (approximate)" if kind == "kdtree" else " (exact)"), collider, size
    repo = ModelRepository(args.models)
    for name in args.model or ["bunny"]:
        try:
            path = repo.resolve(name)
        except FileNotFoundError as exc:
            print(f"skipping {name}: {exc}", file=sys.stderr)
            continue
        collider = load_collider(path)
        arch = collider.info.settings.get("architecture", {})
        label = f"neural {collider.info.name}"
        if arch:
            label += f" ({arch['hidden_layers']}x{arch['hidden_width']})"
        yield label, collider, path.stat().st_size


def measure(collider, sdf, band_points, timing_points) -> dict:
    from collider_server.evaluation import error_figures, query_seconds_per_million

    figures = error_figures(collider, sdf, band_points)
    collider.query(timing_points[:1000], ["distance", "normal", "contact"])  # warm-up
    figures["seconds_per_million"] = query_seconds_per_million(collider, timing_points)
    return figures


def plot(rows, output: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for ax, key, label in ((axes[0], "distance_mean_mm", "mean distance error, +-1 mm band (mm)"),
                           (axes[1], "normal_mean_deg", "mean normal angle error, +-1 mm band (deg)")):
        for row in rows:
            value = max(row[key], 1e-5)
            ax.scatter(row["seconds_per_million"], value, s=20 + 300 * np.sqrt(row["bytes"] / 7e7))
            ax.annotate(f"{row['label']}\n{row['bytes'] / 1e6:.2f} MB", (row["seconds_per_million"], value),
                        textcoords="offset points", xytext=(6, 4), fontsize=8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("distance + normal + contact, s per 1M points (this CPU)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle("Stanford bunny: what accuracy costs in time (marker area ~ model size)")
    fig.tight_layout()
    output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(output, dpi=110)


def main(argv=None) -> int:
    from collider_server.meshes import ExactSDF, load_mesh
    from collider_server.progress import progress
    from collider_server.sampling import surface_band_points

    args = parse_args(argv)
    mesh = load_mesh(args.mesh)
    sdf = ExactSDF(mesh)
    band = surface_band_points(mesh, args.points, 1e-3, seed=0)
    timing = surface_band_points(mesh, args.timing_points, 1e-2, seed=1)
    rows = []
    started = time.time()
    entries = list(colliders(args, mesh))
    with progress(len(entries), "measure", "collider") as bar:
        for label, collider, size in entries:
            rows.append({"label": label, "bytes": int(size), **measure(collider, sdf, band, timing)})
            bar.update(1)
    print(f"\nmeasured in one run, {time.time() - started:.0f} s; error on {args.points:,} points in the "
          f"+-1 mm band, time on {args.timing_points:,} points in the +-10 mm band")
    print(f"{'collider':<28} {'s/1M pts':>9} {'dist mean':>10} {'p99':>8} {'max':>8} {'sign %':>7} "
          f"{'normal':>7} {'p99':>7} {'MB':>8}")
    for r in rows:
        print(f"{r['label']:<28} {r['seconds_per_million']:>9.2f} {r['distance_mean_mm']:>10.4f} "
              f"{r['distance_p99_mm']:>8.4f} {r['distance_max_mm']:>8.4f} {r['sign_errors_percent']:>7.3f} "
              f"{r['normal_mean_deg']:>7.2f} {r['normal_p99_deg']:>7.2f} {r['bytes'] / 1e6:>8.2f}")
    plot(rows, args.output)
    print(f"plot: {args.output}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
