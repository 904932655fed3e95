"""Round-robin vs by-model routing in front of two ``collider serve`` replicas: how large do the
batches stay? Headless; prints a table and writes JSON.

Each replica coalesces only the queries it receives. With round-robin, one model's queries are
split over both replicas, so each replica's batches of that model are about half as large; routed
by model (docker/nginx/collider.conf.template: consistent hash of the model name), every model's
queries meet in one batcher. This script runs the same load both ways through a real nginx and the
same template (round-robin = the template with its ``hash`` line removed), in front of the same two
replicas (started once), and reads each replica's ``/metrics`` before and after each policy's load:
mean batch points = sum / count of ``collider_batch_points`` over that load.

The load: ``--models`` copies of one collider under different names (same compute per point, so
the routing is the only difference), ``--simulators`` cloth simulators per model (loadtest.py's:
closed loop, distance + normal + contact, msgpack), for ``--duration`` seconds per policy.

    python benchmarks/routing.py                       # the shipped neural bunny, 4 models x 4 sims
    python benchmarks/routing.py --collider out/bench-models/bunny-voxel.safetensors --cloth 64
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from loadtest import Simulator, simulate
from service_common import REPO, free_port, machine_note, nginx, nginx_config, percentiles_ms, serve

POLICIES = ("round-robin", "by-model")


def batch_metrics(port: int) -> dict[str, dict[str, float]]:
    """Per model: batches, points in them, compute seconds, from one replica's /metrics."""
    import httpx

    text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10).text
    found: dict[str, dict[str, float]] = {}
    for metric, key in (("collider_batch_points_count", "batches"),
                        ("collider_batch_points_sum", "points"),
                        ("collider_compute_seconds_sum", "compute_s")):
        for model, value in re.findall(rf'^{metric}\{{model="([^"]+)"\}} (\S+)$', text, re.MULTILINE):
            found.setdefault(model, {})[key] = float(value)
    return found


async def load(port: int, models: list[str], per_model: int, side: int, duration_s: float,
               lo: np.ndarray, hi: np.ndarray) -> dict:
    stats = {"latencies": [], "points": 0, "collisions": 0, "status": {}, "transport_errors": 0}
    start = time.perf_counter()
    end = start + duration_s
    tasks = []
    for m, model in enumerate(models):
        for s in range(per_model):
            sim = Simulator(m * per_model + s, side, lo, hi, steps_to_floor=200)
            tasks.append(simulate(sim, "127.0.0.1", port, f"/v1/models/{model}/query", None, end,
                                  0.0, stats))
    await asyncio.gather(*tasks)
    elapsed = time.perf_counter() - start
    return {"seconds": elapsed, "queries": len(stats["latencies"]),
            "points_per_s": stats["points"] / elapsed, **percentiles_ms(stats["latencies"]),
            "status": stats["status"], "transport_errors": stats["transport_errors"]}


def since(after: dict[str, dict[str, float]], before: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """Per model, what :func:`batch_metrics` counted between ``before`` and ``after`` (models with
    no batch in between left out)."""
    found = {}
    for model, figures in after.items():
        was = before.get(model, {})
        delta = {key: value - was.get(key, 0.0) for key, value in figures.items()}
        if delta.get("batches"):
            found[model] = delta
    return found


def run_policy(policy: str, replicas: list[int], models: list[str], args, lo, hi) -> dict:
    """The load through nginx routing by ``policy`` to the replicas on ports ``replicas``."""
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        before = [batch_metrics(p) for p in replicas]
        with nginx(nginx_config(policy, port, replicas, Path(tmp)), port):
            print(f"{policy}: replicas on ports {replicas}, nginx on {port}; "
                  f"{args.duration:.0f} s of load", flush=True)
            traffic = asyncio.run(load(port, models, args.simulators, args.cloth, args.duration, lo, hi))
        per_replica = [since(batch_metrics(p), b) for p, b in zip(replicas, before)]
    batches = sum(m.get("batches", 0) for r in per_replica for m in r.values())
    points = sum(m.get("points", 0) for r in per_replica for m in r.values())
    placement = {model: [i for i, r in enumerate(per_replica) if r.get(model, {}).get("batches")]
                 for model in models}
    return {"policy": policy, **traffic, "batches": batches,
            "mean_batch_points": points / batches if batches else float("nan"),
            "points_per_replica": [sum(m.get("points", 0) for m in r.values()) for r in per_replica],
            "replicas_of_model": placement, "per_replica": per_replica}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--collider", type=Path, default=REPO / "models" / "bunny.safetensors",
                        help="the model file served under every name (default: the neural bunny)")
    parser.add_argument("--models", type=int, default=4, help="how many model names")
    parser.add_argument("--simulators", type=int, default=4, help="simulators per model")
    parser.add_argument("--cloth", type=int, default=32, help="cloth side, vertices (32: 1,024)")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds per policy")
    parser.add_argument("--compute-threads", type=int, default=1, help="per replica")
    parser.add_argument("--by-model-first", action="store_true",
                        help="run by-model before round-robin (to see the machine's drift)")
    parser.add_argument("--output", type=Path, default=REPO / "out" / "routing.json")
    args = parser.parse_args()
    if not args.collider.is_file():
        parser.error(f"--collider {args.collider}: no such file")
    if min(args.models, args.simulators, args.cloth) < 1 or not args.duration > 0:
        parser.error("--models, --simulators, --cloth must be >= 1 and --duration > 0")

    from collider_server.engine.modelfile import read_info

    info = read_info(args.collider)
    lo, hi = np.asarray(info.domain_min), np.asarray(info.domain_max)
    names = [f"model-{chr(ord('a') + i)}" for i in range(args.models)]
    print(f"machine: {machine_note()}", flush=True)
    flags = ("--device", "cpu", "--compute-threads", str(args.compute_threads))
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        repo = Path(tmp)
        for name in names:
            shutil.copy(args.collider, repo / f"{name}.safetensors")
        replicas = [stack.enter_context(serve(repo, *flags)) for _ in range(2)]
        order = POLICIES[::-1] if args.by_model_first else POLICIES
        results = sorted((run_policy(p, replicas, names, args, lo, hi) for p in order),
                         key=lambda r: POLICIES.index(r["policy"]))

    print(f"\n{args.models} models x {args.simulators} simulators x {args.cloth ** 2:,} points, "
          f"{args.collider.name}, 2 replicas x {args.compute_threads} compute thread(s)")
    print("| routing | mean batch points | queries/s | points/s | p50 ms | p99 ms | points per replica |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['policy']} | {r['mean_batch_points']:,.0f} | {r['queries'] / r['seconds']:.1f} | "
              f"{r['points_per_s']:,.0f} | {r['p50_ms']:.1f} | {r['p99_ms']:.1f} | "
              f"{' / '.join(f'{p:,.0f}' for p in r['points_per_replica'])} |")
    by_model, round_robin = results[1], results[0]
    ratio = by_model["mean_batch_points"] / round_robin["mean_batch_points"]
    print(f"by-model / round-robin mean batch points: {ratio:.2f}x; "
          f"by-model placement: {by_model['replicas_of_model']}")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"machine": machine_note(), "args": {
        k: str(v) for k, v in vars(args).items()}, "results": results, "ratio": ratio}, indent=2))
    failed = any(set(r["status"]) - {200} or r["transport_errors"] for r in results)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
