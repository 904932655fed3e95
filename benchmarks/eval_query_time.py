"""``collider eval``'s query time against the SDK's on the same points, interleaved in one process
(issue 35, item 10): the eval's own timing function (``making.evaluation``) and
``collider_client.Client(models=...).query`` over the eval's points (the +-1 mm band) and over
points in the domain box, in alternating rounds, so that the machine's load falls on both alike.

    python benchmarks/eval_query_time.py MODELS NAME MESH [--rounds 5] [--points 50000]

MODELS is a model repository, NAME a static model in it (e.g. ``collider bake
examples/meshes/spot.obj --name spot --kind mesh --models out/eval-time``), MESH its source mesh.
Prints the medians (s per 1M distance + normal + contact points), the eval / SDK ratios and the
load average during the rounds.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

FIELDS = ["distance", "normal", "contact"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models")
    parser.add_argument("name")
    parser.add_argument("mesh")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--points", type=int, default=50_000, help="points per set (the eval times 50,000)")
    args = parser.parse_args()

    import torch

    from collider_client import Client
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.evaluation import point_sets, query_seconds_per_million
    from collider_server.making.mesh_files import load_mesh

    collider = ModelRepository(args.models).load(args.name, "cpu")
    sets = point_sets(collider, load_mesh(args.mesh), args.points, 1234)
    client = Client(models=args.models, device="cpu")
    client.query(args.name, sets["box"][:1000], FIELDS)  # untimed: both share the built trees
    print(f"torch threads {torch.get_num_threads()}, {os.cpu_count()} CPUs")
    times: dict[tuple[str, str], list[float]] = {}
    loads = []
    for _ in range(args.rounds):
        for set_name in ("band_1mm", "box"):
            points = sets[set_name]
            times.setdefault(("eval", set_name), []).append(
                query_seconds_per_million(collider, points, repeats=1))
            started = time.perf_counter()
            client.query(args.name, points, FIELDS)
            times.setdefault(("sdk", set_name), []).append(
                (time.perf_counter() - started) * 1e6 / len(points))
        loads.append(os.getloadavg()[0])
    median = {key: statistics.median(values) for key, values in times.items()}
    for (path, set_name), values in times.items():
        print(f"{path:4} {set_name:8} median {median[path, set_name]:.2f} s per 1M points "
              f"(rounds: {', '.join(f'{v:.1f}' for v in values)})")
    for set_name in ("band_1mm", "box"):
        print(f"{set_name}: eval / SDK {median['eval', set_name] / median['sdk', set_name]:.2f}x")
    print(f"SDK band / box {median['sdk', 'band_1mm'] / median['sdk', 'box']:.2f}x; "
          f"load average during the rounds {min(loads):.1f}-{max(loads):.1f}")


if __name__ == "__main__":
    main()
