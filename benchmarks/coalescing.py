"""Coalescing benchmark and transport overhead of ``collider serve``, in one run on one machine.

1. Coalescing: K concurrent clients (K = 1, 8, 32, 128), each sending 1,000-point
   ``distance + normal + contact`` msgpack queries back to back for ``--duration`` seconds, against
   a server with coalescing on and one with it off (``--no-coalesce``), for the voxel bunny and
   the neural bunny. Reported: points/s and p50/p99 latency; and, as the ceiling, one client
   sending the same K x 1,000 points in one request.
   Targets (voxel): K = 32: on >= 4x off, and on >= 70 % of the one-batch client; K = 128:
   on >= 80 % of the one-batch client.
2. Transport overhead: one 40,000-point ``distance + normal + contact`` query (the paper's cloth)
   through HTTP/msgpack on loopback (client encode + round trip + client decode) minus the same
   query in process (``Collider.query``), voxel bunny: the median of paired differences over
   interleaved repetitions, through the benchmark's lean client and through the shipped SDK
   (``collider_client.Client``).
   Target: the SDK's round trip at most 1.3x the in-process time.

Server and clients share the machine's cores (the clients are one asyncio process with a lean
HTTP/1.1 client, see ``service_common``). Run from the repository root:

    python benchmarks/coalescing.py                         # ~3 minutes
    python benchmarks/coalescing.py --duration 2 --kinds voxel --clients 1,32   # quick look

The models are made in ``--models`` (default ``out/bench-models``, not committed): the bunny
baked to a 128^3 voxel grid, and models/bunny.safetensors or, until it exists, an untrained
network of the paper's bunny architecture (identical compute per point).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from service_common import (
    REPO,
    LeanConnection,
    bunny_points,
    cpu_seconds,
    decode_response,
    machine_note,
    percentiles_ms,
    prepare_models,
    query_body,
    serve,
)

FIELDS = ("distance", "normal", "contact")


class Slices:
    """Latencies and points of one configuration, gathered over several time slices."""

    def __init__(self):
        self.latencies: list[float] = []
        self.points = 0
        self.seconds = 0.0
        self.cpu_s = 0.0  # the server process's CPU time
        self.errors: dict[int, int] = {}

    def result(self) -> dict:
        return {"points_per_s": self.points / self.seconds, "requests": len(self.latencies),
                "server_cpu_ms_per_1000_points": 1e6 * self.cpu_s / max(self.points, 1),
                "errors": self.errors, **percentiles_ms(self.latencies)}


async def run_clients(port: int, model: str, bodies: list[bytes], points_each: int,
                      duration_s: float, into: Slices) -> None:
    """len(bodies) clients, each posting its body back to back for ``duration_s``."""
    path = f"/v1/models/{model}/query"
    connections = [LeanConnection("127.0.0.1", port) for _ in bodies]
    # One request each first, so connections are open before the clock starts.
    await asyncio.gather(*(c.post(path, b) for c, b in zip(connections, bodies)))
    start = time.perf_counter()
    cpu_start = cpu_seconds(port)
    end = start + duration_s
    done = [0]

    async def client(connection: LeanConnection, body: bytes):
        while time.perf_counter() < end:
            sent = time.perf_counter()
            status, _ = await connection.post(path, body)
            if status == 200:
                into.latencies.append(time.perf_counter() - sent)
                done[0] += 1
            else:
                into.errors[status] = into.errors.get(status, 0) + 1

    await asyncio.gather(*(client(c, b) for c, b in zip(connections, bodies)))
    into.seconds += time.perf_counter() - start
    into.cpu_s += cpu_seconds(port) - cpu_start
    into.points += done[0] * points_each
    await asyncio.gather(*(c.close() for c in connections))


async def coalescing(models: Path, model: str, collider, clients: list[int], points_each: int,
                     duration_s: float, server_flags: tuple[str, ...] = (),
                     slices: int = 4) -> list[dict]:
    """Both servers (coalescing on and off) run side by side; each K is measured in ``slices``
    alternating slices of on / off / one-batch, so load drift on a shared machine hits all
    three alike."""
    rows = []
    max_k = max(clients)
    bodies = [query_body(bunny_points(collider, points_each, seed), FIELDS) for seed in range(max_k)]
    with serve(models, "--coalesce", *server_flags) as on_port, \
            serve(models, "--no-coalesce", *server_flags) as off_port:
        for k in clients:
            one_body = [query_body(bunny_points(collider, k * points_each, 10_000 + k), FIELDS)]
            runs = {"on": Slices(), "off": Slices(), "one-batch": Slices()}
            for _ in range(slices):
                await run_clients(on_port, model, bodies[:k], points_each, duration_s / slices,
                                  runs["on"])
                await run_clients(off_port, model, bodies[:k], points_each, duration_s / slices,
                                  runs["off"])
                await run_clients(on_port, model, one_body, k * points_each, duration_s / slices,
                                  runs["one-batch"])
            for mode, run in runs.items():
                result = run.result()
                rows.append({"model": model, "coalescing": mode, "clients": k, **result})
                label = (f"coalescing {mode:<3} K={k:<4}" if mode != "one-batch"
                         else f"one request of {k} x {points_each} points")
                print(f"  {model:<13} {label:<34} {result['points_per_s']:>12,.0f} points/s"
                      f"  p50 {result['p50_ms']:8.1f} ms  p99 {result['p99_ms']:8.1f} ms"
                      f"  server CPU {result['server_cpu_ms_per_1000_points']:.2f} ms/1000 pts"
                      f"  errors {result['errors'] or 0}", flush=True)
    return rows


async def transport(models: Path, collider, model: str, n: int, repetitions: int,
                    server_flags: tuple[str, ...] = ()) -> dict:
    """One query over HTTP/msgpack (client encode and decode included) against the same query
    in process (``Collider.query``): through the lean client and through the shipped SDK
    (``collider_client.Client``), interleaved so load drift hits all three alike."""
    from collider_client import Client

    points = bunny_points(collider, n, 123)
    expected = collider.query(points, FIELDS)
    in_process, over_http, over_sdk = [], [], []
    with serve(models, *server_flags) as port:
        connection = LeanConnection("127.0.0.1", port)
        sdk = Client(f"http://127.0.0.1:{port}")
        path = f"/v1/models/{model}/query"
        for i in range(repetitions + 2):
            t0 = time.perf_counter()
            collider.query(points, FIELDS)
            t1 = time.perf_counter()
            status, data = await connection.post(path, query_body(points, FIELDS))
            got = decode_response(data)
            t2 = time.perf_counter()
            via_sdk = sdk.query(model, points, FIELDS)
            t3 = time.perf_counter()
            assert status == 200, data[:300]
            if i >= 2:  # the first two warm every path up
                in_process.append(t1 - t0)
                over_http.append(t2 - t1)
                over_sdk.append(t3 - t2)
        await connection.close()
        sdk.close()
    for name in FIELDS:
        np.testing.assert_array_equal(got[name], getattr(expected, name))
        np.testing.assert_array_equal(getattr(via_sdk, name), getattr(expected, name))
    a = statistics.median(in_process) * 1e3
    b, c = statistics.median(over_http) * 1e3, statistics.median(over_sdk) * 1e3
    # The overhead is the median of paired differences: each HTTP call minus the in-process call
    # just before it, so slow drifts of a shared machine's load cancel out.
    paired = statistics.median(h - p for h, p in zip(over_http, in_process)) * 1e3
    paired_sdk = statistics.median(h - p for h, p in zip(over_sdk, in_process)) * 1e3
    return {"points": n, "fields": list(FIELDS), "in_process_ms": a, "http_msgpack_ms": b,
            "sdk_ms": c, "overhead_ms": paired, "sdk_overhead_ms": paired_sdk,
            "http_ratio": b / a, "sdk_ratio": c / a, "repetitions": repetitions}


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = sorted({r["model"] for r in rows}, reverse=True)
    fig, axes = plt.subplots(1, len(models), figsize=(5.5 * len(models), 4), squeeze=False)
    for ax, model in zip(axes[0], models):
        for mode, style in (("on", "o-"), ("off", "s--"), ("one-batch", "k:")):
            sel = [r for r in rows if r["model"] == model and r["coalescing"] == mode]
            label = {"on": "coalescing on", "off": "coalescing off",
                     "one-batch": "one client, K x 1000 points per request"}[mode]
            ax.plot([r["clients"] for r in sel], [r["points_per_s"] for r in sel], style, label=label)
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("K concurrent clients (1,000 points per request)")
        ax.set_ylabel("points / s")
        ax.set_title(model)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--models", type=Path, default=REPO / "out" / "bench-models")
    parser.add_argument("--kinds", default="voxel,neural")
    parser.add_argument("--clients", default="1,8,32,128")
    parser.add_argument("--points", type=int, default=1000, help="points per request")
    parser.add_argument("--duration", type=float, default=3.0, help="seconds per measurement")
    parser.add_argument("--transport-repetitions", type=int, default=40)
    parser.add_argument("--device", default="auto",
                        help="device of the server and of the in-process reference (cpu, cuda, auto)")
    parser.add_argument("--server-flags", default="",
                        help="extra `collider serve` flags, e.g. '--max-wait-ms 0'")
    parser.add_argument("--output", type=Path, default=REPO / "out" / "coalescing.json")
    parser.add_argument("--plot", type=Path, default=REPO / "out" / "service-coalescing.png")
    args = parser.parse_args()

    import torch

    from collider_server.engine.modelfile import load_collider
    from collider_server.service.settings import ServiceSettings

    # The in-process reference runs with the server's compute thread count, so the transport
    # figure compares like with like.
    torch.set_num_threads(ServiceSettings().resolved_compute_threads())
    flags = ("--device", args.device, *args.server_flags.split())

    print(f"machine: {machine_note()}", flush=True)
    notes = prepare_models(args.models)
    clients = [int(k) for k in args.clients.split(",")]
    results = {"machine": machine_note(), "models": notes, "server_flags": list(flags),
               "compute_threads": torch.get_num_threads(), "coalescing": []}
    for kind in args.kinds.split(","):
        model = f"bunny-{kind}"
        collider = load_collider(args.models / f"{model}.safetensors", args.device)
        print(f"{model}: {notes[model]}", flush=True)
        if kind == "voxel":
            # With the default batching (no wait), and with a 1 ms wait for more points.
            results["transport"] = []
            for extra in ((), ("--max-wait-ms", "1")):
                t = asyncio.run(transport(args.models, collider, model, 40_000,
                                          args.transport_repetitions, flags + extra))
                t["server_flags"] = list(flags + extra)
                results["transport"].append(t)
                print(f"  transport, 40,000 points distance+normal+contact {' '.join(extra)}: "
                      f"in process {t['in_process_ms']:.1f} ms, HTTP/msgpack lean client "
                      f"{t['http_msgpack_ms']:.1f} ms ({t['http_ratio']:.2f}x), shipped SDK "
                      f"Client {t['sdk_ms']:.1f} ms ({t['sdk_ratio']:.2f}x; target <= 1.3x)",
                      flush=True)
        results["coalescing"] += asyncio.run(
            coalescing(args.models, model, collider, clients, args.points, args.duration, flags))

    for model in {r["model"] for r in results["coalescing"]}:
        by = {(r["coalescing"], r["clients"]): r["points_per_s"]
              for r in results["coalescing"] if r["model"] == model}
        for k in clients:
            if ("off", k) in by and ("one-batch", k) in by:
                cpu = {(r["coalescing"], r["clients"]): r["server_cpu_ms_per_1000_points"]
                       for r in results["coalescing"] if r["model"] == model}
                print(f"{model} K={k}: on/off {by['on', k] / by['off', k]:.2f}x, "
                      f"on/one-batch {100 * by['on', k] / by['one-batch', k]:.0f} %; server CPU "
                      f"per point: off/on {cpu['off', k] / cpu['on', k]:.2f}x, one-batch/on "
                      f"{100 * cpu['one-batch', k] / cpu['on', k]:.0f} %")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(results, indent=2))
    plot(results["coalescing"], args.plot)
    print(f"wrote {args.output} and {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
