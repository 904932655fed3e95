"""How a collider's block size (``Collider.chunk_points``: the points evaluated per call inside
one query) changes the time of a large query, embedded.

    python benchmarks/chunk_points.py --kind voxel --resolution 128 --threads 1
    python benchmarks/chunk_points.py --kind neural --threads 2

Builds the collider of the shipped bunny's mesh (``voxel``: baked at ``--resolution``; ``neural``:
the shipped ``bunny`` model), then times ``query`` of ``--points`` points in its +-10 mm band
(world frame = collider frame, metres) for distance alone and for distance, normal and contact,
once per block size and round, the block sizes interleaved in every round. Prints per block size
the median seconds, the range over the rounds, and the ratio to the kind's own block size; the
answers are checked to be the same whatever the block size. The figures depend on the machine and
its load: the load average is printed.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

BUNNY = Path(__file__).resolve().parents[1] / "examples" / "meshes" / "stanford-bunny.obj"
FIELDS = {"distance": ["distance"], "d+n+c": ["distance", "normal", "contact"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kind", choices=("voxel", "neural"), default="voxel")
    parser.add_argument("--resolution", type=int, default=128, help="voxel samples per axis")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch and kernel threads (default: torch's)")
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--chunks", default="16384,65536,262144,1048576", help="block sizes, comma-separated")
    parser.add_argument("--hold-freed-memory", action="store_true",
                        help="keep freed arrays in the heap, as `collider serve` and `collider bench` do "
                             "(engine/memory.py): large blocks then page-fault less")
    args = parser.parse_args()

    import torch

    from collider_server.engine.repository import ModelRepository
    from collider_server.making.bake import bake_collider
    from collider_server.making.mesh_files import load_mesh
    from collider_server.making.sampling import surface_band_points

    if args.threads:
        torch.set_num_threads(args.threads)
    held = 0
    if args.hold_freed_memory:
        from collider_server.engine.memory import hold_freed_memory

        held = hold_freed_memory()
    mesh = load_mesh(BUNNY)
    collider = (bake_collider(mesh, "voxel", "voxel", resolution=args.resolution, show_progress=False)
                if args.kind == "voxel" else ModelRepository(None).load("bunny"))
    own = collider.chunk_points
    chunks = sorted({int(c) for c in args.chunks.split(",")} | {own})
    points = surface_band_points(mesh, args.points, 1e-2, seed=0).astype(np.float32)  # as a client sends
    times: dict[tuple, list[float]] = {}
    answers: dict[str, object] = {}
    for round_ in range(args.rounds + 1):  # round 0: warm-up, and the answers compared
        for chunk in chunks:
            collider.chunk_points = chunk
            for label, fields in FIELDS.items():
                started = time.perf_counter()
                result = collider.query(points, fields)
                elapsed = time.perf_counter() - started
                if round_ == 0:
                    first = answers.setdefault(label, result)
                    for name in fields:
                        if not np.array_equal(getattr(result, name), getattr(first, name)):
                            raise SystemExit(f"{name} differs with blocks of {chunk} points")
                else:
                    times.setdefault((label, chunk), []).append(elapsed)
    print(f"{args.kind} ({f'{args.resolution}^3' if args.kind == 'voxel' else 'bunny'}), "
          f"{args.points:,} points, {torch.get_num_threads()} threads, {args.rounds} rounds; "
          f"{f'freed memory held up to {held >> 20} MiB' if held else 'freed memory not held'}; "
          f"load average {', '.join(f'{x:.1f}' for x in os.getloadavg())}; the kind's own block: {own:,}")
    for label in FIELDS:
        base = np.median(times[label, own])
        for chunk in chunks:
            t = times[label, chunk]
            print(f"  {label:9s} blocks of {chunk:>9,}: median {np.median(t):.4f} s "
                  f"({min(t):.4f}-{max(t):.4f}), {np.median(t) / base:.2f}x the kind's own")


if __name__ == "__main__":
    main()
