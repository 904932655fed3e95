"""Query speed of neural colliders against the exact mesh, embedded, in ONE interleaved run.

For 1M points (default) near each model's source mesh (uniform in the +-10 mm band, collider
frame, metres; the mesh is ``--mesh``, else the file the model was made from, found where it was
or under examples/meshes or ../shared/data/meshes), the time of ``Collider.query`` for distance + normal + contact and for distance only, for
the exact ``mesh`` kind (libigl) and for each neural model given (default: the shipped ``bunny``);
optionally the same network through another grid query kernel (``--kernel-from``, e.g. the one
before a change) and, for grid networks, the pure-torch path (the reference, and what runs on
CUDA). Every round times every candidate once, in turn (each round starting one candidate
later), so that a shared machine's load falls on all of them alike; prints the median and the
spread (min - max) in seconds per 1M points, the load average before and after, and the ratios
the issue's targets name.

    python benchmarks/neural_query.py                      # shipped bunny vs mesh, 1M points
    python benchmarks/neural_query.py --model out/b.safetensors --points 200000 --threads 2
    git show 3853465^:server/collider_server/engine/kinds/grid_kernels.py > /tmp/kernel_before.py
    #   (since the kernels' split: git show REV:server/collider_server/engine/kinds/query_kernel.py)
    python benchmarks/neural_query.py --kernel-from /tmp/kernel_before.py --rounds 7
    python benchmarks/neural_query.py --device cuda        # the networks on a GPU, the mesh on the CPU
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import os
import statistics
import sys
import time
from functools import partial
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ALL = ["distance", "normal", "contact"]


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=None, help="the models' source mesh (default: each one's own)")
    parser.add_argument("--model", action="append", default=None, help="model name or path (default: bunny)")
    parser.add_argument("--models", type=Path, default=REPO / "models")
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (median and spread over them)")
    parser.add_argument("--threads", type=int, default=None, help="torch and kernel threads")
    parser.add_argument("--device", default="cpu",
                        help="where the neural models run: cpu (the fused kernel) or cuda (the torch path); "
                             "the exact mesh runs on the CPU either way")
    parser.add_argument("--kernel-from", type=Path, default=None,
                        help="a grid_kernels.py (e.g. an older commit's) whose network_query to time too")
    parser.add_argument("--torch-path", action="store_true", help="also time the slow pure-torch path (1 round)")
    return parser.parse_args(argv)


def load_kernel(path: Path):
    """``network_query`` of the module file at ``path`` (same signature as grid_kernels')."""
    spec = importlib.util.spec_from_file_location("kernel_under_comparison", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # numba's on-disk cache imports the module by name
    spec.loader.exec_module(module)
    return module.network_query


@contextlib.contextmanager
def kernel(grid_kernels, network_query):
    """Queries inside run ``network_query`` in place of the engine's own (None: the engine's)."""
    own = grid_kernels.network_query
    grid_kernels.network_query = network_query or own
    try:
        yield
    finally:
        grid_kernels.network_query = own


def _gpu(device: str) -> str:
    import torch

    return "" if device == "cpu" else f", neural models on {torch.cuda.get_device_name(torch.device(device))}"


def source_mesh(info, given: Path | None):
    """``given``, else the mesh the model ``info`` was made from: ``NAME.obj`` (its source's
    ``mesh``) in examples/meshes or ../shared/data/meshes, the same file (sha256)."""
    from collider_server.making.mesh_files import load_mesh

    if given is not None:
        return load_mesh(given)
    name = f"{info.source.get('mesh', info.name)}.obj"
    for folder in (REPO / "examples" / "meshes", REPO.parent / "shared" / "data" / "meshes"):
        if (folder / name).is_file():
            mesh = load_mesh(folder / name)
            if mesh.sha256 == info.source.get("sha256", mesh.sha256):
                return mesh
    raise SystemExit(f"neural_query.py: {info.name}'s source mesh {name} is not here: give --mesh")


def timed(call) -> float:
    started = time.perf_counter()
    call()
    return time.perf_counter() - started


def main(argv=None) -> int:
    import torch

    from collider_server.engine.devices import resolve_device
    from collider_server.engine.kinds import grid_kernels
    from collider_server.engine.modelfile import load_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.bake import bake_collider
    from collider_server.making.sampling import surface_band_points

    args = parse_args(argv)
    args.device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
        grid_kernels.set_threads(args.threads)
    other_kernel = load_kernel(args.kernel_from) if args.kernel_from else None
    repo = ModelRepository(args.models)
    # candidates: (label, collider, kernel or None, points)
    candidates = []
    for name in args.model or ["bunny"]:
        collider = load_collider(repo.resolve(name), args.device)
        mesh = source_mesh(collider.info, args.mesh)
        transform = collider.info.source.get("transform")
        placed = mesh.transformed(transform) if transform is not None else mesh
        points = surface_band_points(placed, args.points, 1e-2 / collider.info.meters_per_unit, seed=1)
        # Two models of one name (a file from an older commit beside the shipped one): the
        # second is shown by the name or path it was given.
        shown = name if any(c.info.name == collider.info.name for _, c, _, _ in candidates) else collider.info.name
        label = f"neural {shown}" + ("" if args.device == "cpu" else f" ({args.device})")
        candidates.append((label, collider, None, points))
        if other_kernel is not None:
            candidates.append((label + f" ({args.kernel_from.name})", collider, other_kernel, points))
        # the exact mesh in the model's frame, where the points are
        candidates.append((f"mesh (exact, libigl) for {shown}",
                           bake_collider(placed, "mesh", "exact", show_progress=False), None, points))
    for _, collider, query_kernel, points in candidates:  # warm-up: kernel compilation is cached on disk
        with kernel(grid_kernels, query_kernel):
            collider.query(points[:1000], ALL)

    load_before = os.getloadavg()
    times = {label: ([], []) for label, *_ in candidates}
    for round_ in range(args.rounds):
        # Each round starts one candidate later, so that none always follows the same one: a query
        # right after the exact mesh's pays the page faults of memory glibc gave back after it
        # (docs/neural.md: up to 1.5x, d+n+c of the grid network).
        turn = round_ % len(candidates)
        for label, collider, query_kernel, points in candidates[turn:] + candidates[:turn]:
            with kernel(grid_kernels, query_kernel):
                times[label][0].append(timed(partial(collider.query, points, ALL)))
                times[label][1].append(timed(partial(collider.query, points, ["distance"])))
    load_after = os.getloadavg()
    if args.torch_path:
        for label, collider, query_kernel, points in candidates:
            if query_kernel is None and getattr(collider, "network", None) is not None \
                    and hasattr(collider.network, "fused"):
                collider.network.fused = False
                times[label + " (pure torch, 1 round)"] = ([timed(partial(collider.query, points, ALL))],
                                                          [timed(partial(collider.query, points, ["distance"]))])
                collider.network.fused = True

    scale = 1e6 / args.points
    print(f"{args.points:,} points in the +-10 mm band, embedded Collider.query, {args.rounds} interleaved "
          f"rounds, torch threads {torch.get_num_threads()}{_gpu(args.device)}; load average (1, 5, 15 min) "
          f"{'/'.join(f'{v:.2f}' for v in load_before)} before, {'/'.join(f'{v:.2f}' for v in load_after)} after")
    print("seconds per 1M points: median (min - max)")
    print(f"{'collider':<52} {'d+n+c':>22} {'d only':>22}")

    def cell(values):
        return f"{statistics.median(values) * scale:.3f} ({min(values) * scale:.3f}-{max(values) * scale:.3f})"

    for label, (full, only) in times.items():
        print(f"{label:<52} {cell(full):>22} {cell(only):>22}")
    medians = {label: statistics.median(full) for label, (full, _) in times.items()}
    for label, _, query_kernel, _ in candidates:
        if label.startswith("neural") and query_kernel is None:
            name = label.split(" ")[1]
            exact = medians[f"mesh (exact, libigl) for {name}"]
            print(f"{label}: exact mesh / neural (d+n+c, medians) = {exact / medians[label]:.2f}x")
            if other_kernel is not None:
                before = medians[label + f" ({args.kernel_from.name})"]
                print(f"{label}: {args.kernel_from.name} / engine kernel (d+n+c, medians) = {before / medians[label]:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
