"""Query speed of neural colliders against the exact mesh, embedded, in ONE run.

For 1M points (default) near the bunny's surface (uniform in the +-10 mm band, collider frame,
metres), the time of ``Collider.query`` for distance + normal + contact and for distance only, for
the exact ``mesh`` kind (libigl) and for each neural model given (default: the shipped ``bunny``);
for grid networks also the pure-torch path (the reference, and what runs on CUDA) beside the fused
CPU kernels. Prints seconds per 1M points and the ratios the issue's targets name.

    python benchmarks/neural_query.py                      # shipped bunny vs mesh, 1M points
    python benchmarks/neural_query.py --model out/b.safetensors --points 200000 --threads 2
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BUNNY = REPO.parent / "shared" / "data" / "meshes" / "stanford-bunny.obj"
ALL = ["distance", "normal", "contact"]


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=BUNNY)
    parser.add_argument("--model", action="append", default=None, help="model name or path (default: bunny)")
    parser.add_argument("--models", type=Path, default=REPO / "models")
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=2, help="best of this many runs")
    parser.add_argument("--threads", type=int, default=None, help="torch and kernel threads")
    parser.add_argument("--no-torch-path", action="store_true", help="skip the slow pure-torch timing")
    return parser.parse_args(argv)


def best_seconds(call, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        started = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - started)
    return best


def main(argv=None) -> int:
    import torch

    from collider_server.engine.kinds import grid_kernels
    from collider_server.engine.modelfile import load_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.bake import bake_collider
    from collider_server.making.mesh_files import load_mesh
    from collider_server.making.sampling import surface_band_points

    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
        grid_kernels.set_threads(args.threads)
    mesh = load_mesh(args.mesh)
    repo = ModelRepository(args.models)
    rows = []
    exact = bake_collider(mesh, "mesh", "exact", show_progress=False)
    for name in args.model or ["bunny"]:
        collider = load_collider(repo.resolve(name), "cpu")
        transform = collider.info.source.get("transform")
        placed = mesh.transformed(transform) if transform is not None else mesh
        points = surface_band_points(placed, args.points, 1e-2 / collider.info.meters_per_unit, seed=1)
        collider.query(points[:1000], ALL)  # warm-up (kernel compilation is cached on disk)
        label = f"neural {collider.info.name}"
        full = best_seconds(lambda: collider.query(points, ALL), args.repeat)
        only = best_seconds(lambda: collider.query(points, ["distance"]), args.repeat)
        rows.append((label, full, only))
        network = collider.network
        if hasattr(network, "fused") and not args.no_torch_path:
            network.fused = False
            rows.append((label + " (pure torch)", best_seconds(lambda: collider.query(points, ALL), 1),
                         best_seconds(lambda: collider.query(points, ["distance"]), 1)))
            network.fused = True
        if transform is not None:  # the exact mesh in the model's frame, where the points are
            exact = bake_collider(placed, "mesh", "exact", show_progress=False)
        rows.append(("mesh (exact, libigl)", best_seconds(lambda: exact.query(points, ALL), 1),
                     best_seconds(lambda: exact.query(points, ["distance"]), 1)))
    scale = 1e6 / args.points
    print(f"{args.points:,} points in the +-10 mm band, embedded Collider.query, torch threads "
          f"{torch.get_num_threads()}; seconds per 1M points")
    print(f"{'collider':<36} {'d+n+c':>8} {'d only':>8} {'d+n+c / d':>10}")
    for label, full, only in rows:
        print(f"{label:<36} {full * scale:>8.3f} {only * scale:>8.3f} {full / only:>10.2f}")
    neural = [r for r in rows if r[0].startswith("neural") and "torch" not in r[0]]
    exact_rows = [r for r in rows if r[0].startswith("mesh")]
    for (label, full, _), (_, mesh_full, _) in zip(neural, exact_rows):
        print(f"{label}: exact mesh / neural (d+n+c) = {mesh_full / full:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
