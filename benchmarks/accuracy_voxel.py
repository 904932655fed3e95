"""Accuracy of the voxel and mesh colliders against the exact SDF in the +-1 mm band, and the
query time per 1M points of every kind, on this machine's CPU.

Truth: surface samples of the Stanford bunny (metres, its own frame) offset along the face normal
by U(-1 mm, 1 mm) (:func:`collider_server.sampling.surface_band_points`); the exact signed
distance of those points (libigl, fast winding number sign) and the direction to the exact
closest point (:meth:`ExactSDF.gradient`) are the reference.

Prints a markdown table (copied into ``docs/accuracy.md``). Run from the repository root:

    python benchmarks/accuracy_voxel.py                # bakes 256^3 (a few minutes on 2 cores)
    python benchmarks/accuracy_voxel.py --resolution 128 --timing-points 200000   # quick look

The baked voxel model is cached in ``--cache`` (default ``out/bunny-voxel-256.safetensors``) so
a second run skips the bake; pass ``--rebake`` to bake again.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MESHES = REPO.parent / "shared" / "data" / "meshes"


def band_errors(distance, normal, truth_distance, truth_normal, sign_threshold):
    """Error figures of one collider: distances in metres, angles in degrees."""
    error = np.abs(distance.astype(np.float64) - truth_distance)
    far = np.abs(truth_distance) > sign_threshold
    sign_errors = np.sign(distance[far]) != np.sign(truth_distance[far])
    cos = np.clip(np.einsum("ij,ij->i", normal.astype(np.float64), truth_normal), -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    return {
        "mean_mm": 1e3 * error.mean(),
        "p99_mm": 1e3 * np.percentile(error, 99),
        "max_mm": 1e3 * error.max(),
        "sign_error_pct": 100.0 * sign_errors.mean(),
        "sign_points": int(far.sum()),
        "normal_mean_deg": angle.mean(),
        "normal_p99_deg": np.percentile(angle, 99),
    }


def time_query(collider, points, fields, repeats=1):
    """Best wall time in seconds of ``collider.query(points, fields)``."""
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        collider.query(points, fields)
        best = min(best, time.perf_counter() - start)
    return best


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mesh", type=Path, default=MESHES / "stanford-bunny.obj")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--points", type=int, default=100_000, help="band points for accuracy")
    parser.add_argument("--band-mm", type=float, default=1.0)
    parser.add_argument("--timing-points", type=int, default=1_000_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=None,
                        help="voxel model file to reuse (default out/bunny-voxel-R.safetensors)")
    parser.add_argument("--rebake", action="store_true")
    args = parser.parse_args(argv)

    import torch

    from collider_server.bake import bake_collider
    from collider_server.collider import ColliderInfo
    from collider_server.kinds.neural import PRESETS, NeuralCollider, build_network
    from collider_server.meshes import ExactSDF, load_mesh
    from collider_server.modelfile import load_collider, save_collider
    from collider_server.sampling import surface_band_points

    if not args.mesh.is_file():
        print(f"error: {args.mesh}: mesh not found (the shared meshes folder is absent)", file=sys.stderr)
        return 2
    torch.manual_seed(args.seed)
    mesh = load_mesh(args.mesh)
    band = args.band_mm * 1e-3
    print(f"mesh {args.mesh.name}: {len(mesh.faces):,} faces, extent "
          f"{np.round(1e3 * np.ptp(mesh.vertices, axis=0), 1).tolist()} mm", file=sys.stderr)

    cache = args.cache or REPO / "out" / f"bunny-voxel-{args.resolution}.safetensors"
    start = time.perf_counter()
    if cache.is_file() and not args.rebake:
        voxel = load_collider(cache, "cpu")
        if voxel.info.source.get("sha256") != mesh.sha256 or voxel.resolution[0] != args.resolution:
            print(f"{cache} does not match the mesh/resolution; pass --rebake", file=sys.stderr)
            return 2
        bake_seconds = None
    else:
        voxel = bake_collider(mesh, "voxel", "bunny-voxel", resolution=args.resolution, device="cpu")
        bake_seconds = time.perf_counter() - start
        save_collider(voxel, cache)
    mesh_collider = bake_collider(mesh, "mesh", "bunny-mesh", device="cpu")
    kdtree = bake_collider(mesh, "kdtree", "bunny-kdtree", device="cpu")
    lo, hi = voxel.domain_min, voxel.domain_max
    arch = PRESETS["paper-bunny"]
    info = ColliderInfo("bunny-untrained", "neural", lo.tolist(), hi.tolist(),
                        settings={"architecture": arch.__dict__.copy()})
    neural = NeuralCollider(info, build_network(arch, 0.5 * (lo + hi), 0.5 * float((hi - lo).max())), "cpu")

    # Accuracy in the band.
    points = surface_band_points(mesh, args.points, band, args.seed)
    exact = ExactSDF(mesh)
    truth_d, closest, face = exact.query(points)
    truth_n = exact.gradient(points, truth_d, closest, face)
    rows = []
    for name, collider in (("voxel", voxel), ("mesh", mesh_collider), ("kdtree", kdtree)):
        result = collider.query(points, ["distance", "normal"])
        rows.append((name, band_errors(result.distance, result.normal, truth_d, truth_n, 2e-4)))

    # Speed: distance + normal, then distance only, on points in a +-1 cm band (near the surface,
    # where a cloth simulator queries).
    timing_points = surface_band_points(mesh, args.timing_points, 1e-2, args.seed + 7)
    per_million = 1e6 / args.timing_points
    timings = []
    kinds = (("voxel", voxel), ("mesh", mesh_collider), ("kdtree", kdtree),
             ("neural (untrained paper-bunny)", neural))
    for name, collider in kinds:
        collider.query(timing_points[:2000], ["distance", "normal"])  # warm-up (allocations, threads)
        with_normal = time_query(collider, timing_points, ["distance", "normal"])
        distance_only = time_query(collider, timing_points, ["distance"])
        timings.append((name, with_normal * per_million, distance_only * per_million))
        print(f"timed {name}", file=sys.stderr)

    print(f"# Bunny ({len(mesh.faces):,} faces, metres), {args.points:,} points in the "
          f"+-{args.band_mm:g} mm band, seed {args.seed}")
    print(f"voxel {args.resolution}^3 over the padded box, cell {1e3 * float(voxel._spacing.max()):.3f} mm"
          + (f"; baked in {bake_seconds:.0f} s" if bake_seconds is not None else " (cached)"))
    print()
    print("| kind | distance error mean / p99 / max (mm) | sign errors, abs(d) > 0.2 mm | "
          "normal angle error mean / p99 (deg) |")
    print("|---|---|---|---|")
    for name, e in rows:
        print(f"| {name} | {e['mean_mm']:.4f} / {e['p99_mm']:.4f} / {e['max_mm']:.4f} | "
              f"{e['sign_error_pct']:.3f} % of {e['sign_points']:,} | "
              f"{e['normal_mean_deg']:.2f} / {e['normal_p99_deg']:.2f} |")
    print()
    print(f"Query time per 1M points, CPU ({platform.processor() or platform.machine()}, "
          f"torch threads {torch.get_num_threads()}), measured on {args.timing_points:,} points "
          "in the +-1 cm band:")
    print()
    print("| kind | distance + normal (s per 1M) | distance only (s per 1M) |")
    print("|---|---|---|")
    for name, both, only in timings:
        print(f"| {name} | {both:.2f} | {only:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
