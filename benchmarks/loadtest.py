"""Load test of ``collider serve``: many cloth simulators, each sending its cloth's vertices every
step, for a bounded time; reports throughput and latency percentiles. Headless.

Each simulator owns a square cloth of ``--cloth`` x ``--cloth`` vertices (float32, metres, world
frame) that falls onto the collider and drapes (a height field sinking step by step, with a
per-simulator offset and a small wave so consecutive steps differ), and its own pose of the
collider (a rotation about z and a translation). Every step it asks for ``distance``, ``normal``
and ``contact`` (msgpack) and waits for the answer before the next step, as a simulator does;
``--step-ms`` adds the simulator's own compute time between steps.

Why an asyncio script and not locust: locust is not a dependency of this project, and one asyncio
process with a lean HTTP/1.1 client (``service_common.LeanConnection``) drives hundreds of
simulators while leaving the CPU to the server, which matters on a small machine where client and
server share the cores. Every answer is decoded and checked for shape and finiteness.

    python benchmarks/loadtest.py --simulators 16 --duration 20             # spawns a server
    python benchmarks/loadtest.py --url http://10.0.0.5:8000 --model bunny --token $T
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import sys
import time
from pathlib import Path
from urllib.parse import urlparse

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from service_common import (
    REPO,
    HTTPError,
    LeanConnection,
    decode_response,
    machine_note,
    percentiles_ms,
    prepare_models,
    query_body,
    serve,
)

FIELDS = ("distance", "normal", "contact")


class Simulator:
    """One cloth: an (m*m, 3) float32 grid over the collider's domain, sinking every step."""

    def __init__(self, index: int, side: int, lo: np.ndarray, hi: np.ndarray, steps_to_floor: int):
        rng = np.random.default_rng(index)
        centre, size = 0.5 * (lo + hi), float((hi - lo).max())
        u = np.linspace(-0.6, 0.6, side) * size
        x, y = np.meshgrid(u, u, indexing="ij")
        self.grid = np.stack([x.ravel(), y.ravel()], axis=1) + centre[:2] + rng.normal(0, 0.02 * size, 2)
        self.top, self.bottom = hi[2] + 0.1 * size, lo[2]
        self.phase = rng.uniform(0, 2 * math.pi)
        self.steps_to_floor = steps_to_floor
        angle = rng.uniform(0, 2 * math.pi)
        pose = np.eye(4)
        pose[:2, :2] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
        self.pose = pose
        self.step = 0

    def vertices(self) -> np.ndarray:
        t = (self.step % self.steps_to_floor) / self.steps_to_floor
        z = self.top + (self.bottom - self.top) * t
        wave = 0.01 * np.sin(self.grid[:, 0] * 40 + self.phase + self.step * 0.3)
        self.step += 1
        return np.column_stack([self.grid, z + wave]).astype(np.float32)


async def simulate(sim: Simulator, host: str, port: int, path: str, token: str | None,
                   end: float, step_s: float, stats: dict) -> None:
    connection = LeanConnection(host, port, token)
    pose = {"dtype": "<f8", "shape": [4, 4], "data": sim.pose.astype("<f8").tobytes()}
    try:
        while time.perf_counter() < end:
            vertices = sim.vertices()
            body = query_body(vertices, FIELDS, pose=pose)
            sent = time.perf_counter()
            try:
                status, data = await connection.post(path, body)
            except (ConnectionError, OSError) as exc:
                stats["transport_errors"] += 1
                stats["last_error"] = str(exc)
                await connection.close()
                connection = LeanConnection(host, port, token)
                continue
            latency = time.perf_counter() - sent
            stats["status"][status] = stats["status"].get(status, 0) + 1
            if status != 200:
                stats["last_error"] = str(HTTPError(status, data))
                await asyncio.sleep(0.05)
                continue
            answer = decode_response(data)
            if answer["normal"].shape != vertices.shape or not np.isfinite(answer["distance"]).all():
                raise AssertionError("malformed answer")
            stats["latencies"].append(latency)
            stats["points"] += len(vertices)
            stats["collisions"] += int((answer["distance"] < 1e-3).sum())
            if step_s:
                await asyncio.sleep(step_s)
    finally:
        await connection.close()


async def run(url: str, model: str, token: str | None, simulators: int, side: int,
              duration_s: float, step_ms: float, lo, hi) -> dict:
    parsed = urlparse(url)
    path = f"/v1/models/{model}/query"
    stats = {"latencies": [], "points": 0, "collisions": 0, "status": {}, "transport_errors": 0}
    sims = [Simulator(i, side, lo, hi, steps_to_floor=200) for i in range(simulators)]
    start = time.perf_counter()
    end = start + duration_s
    progress = asyncio.create_task(report_progress(stats, start, end))
    await asyncio.gather(*(simulate(s, parsed.hostname, parsed.port or 80, path, token, end,
                                    step_ms / 1000, stats) for s in sims))
    progress.cancel()
    elapsed = time.perf_counter() - start
    return {
        "simulators": simulators, "vertices_per_cloth": side * side, "seconds": elapsed,
        "steps": len(stats["latencies"]), "steps_per_s": len(stats["latencies"]) / elapsed,
        "points_per_s": stats["points"] / elapsed, **percentiles_ms(stats["latencies"]),
        "max_ms": 1e3 * max(stats["latencies"], default=float("nan")),
        "status": stats["status"], "transport_errors": stats["transport_errors"],
        "last_error": stats.get("last_error"),
    }


async def report_progress(stats: dict, start: float, end: float) -> None:
    from tqdm import tqdm

    with tqdm(total=round(end - start), unit="s", desc="load test", leave=False) as bar:
        while True:
            await asyncio.sleep(1)
            bar.update(1)
            bar.set_postfix(steps=len(stats["latencies"]), points=f"{stats['points']:,}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--url", default=None, help="a running server; default: spawn one")
    parser.add_argument("--model", default=None, help="model to query (default: bunny-voxel "
                                                      "of the spawned server)")
    parser.add_argument("--token", default=None, help="bearer token of the server")
    parser.add_argument("--models", type=Path, default=REPO / "out" / "bench-models",
                        help="repository for the spawned server (made if absent)")
    parser.add_argument("--simulators", type=int, default=16)
    parser.add_argument("--cloth", type=int, default=64, help="cloth side, vertices (64: 4,096)")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds")
    parser.add_argument("--step-ms", type=float, default=0.0, help="simulator time per step")
    parser.add_argument("--server-flags", default="", help="extra `collider serve` flags")
    parser.add_argument("--output", type=Path, default=None, help="also write the report as JSON")
    args = parser.parse_args()
    for name in ("simulators", "cloth"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1")
    if not args.duration > 0:
        parser.error("--duration must be > 0")

    import httpx

    print(f"machine: {machine_note()}", flush=True)
    with contextlib.ExitStack() as stack:
        if args.url is None:
            prepare_models(args.models)
            port = stack.enter_context(serve(args.models, *args.server_flags.split()))
            url, model = f"http://127.0.0.1:{port}", args.model or "bunny-voxel"
        else:
            url, model = args.url.rstrip("/"), args.model
            if model is None:
                parser.error("--model is required with --url")
        headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
        info = httpx.get(f"{url}/v1/models/{model}", headers=headers, timeout=10)
        if info.status_code != 200:
            print(f"loadtest: {url}/v1/models/{model}: {info.status_code} {info.text[:200]}",
                  file=sys.stderr)
            return 2
        lo, hi = np.asarray(info.json()["domain_min"]), np.asarray(info.json()["domain_max"])
        report = asyncio.run(run(url, model, args.token, args.simulators, args.cloth,
                                 args.duration, args.step_ms, lo, hi))
    report = {"url": url, "model": model, "fields": list(FIELDS), **report}
    print(f"{report['simulators']} simulators x {report['vertices_per_cloth']:,} vertices, "
          f"{report['seconds']:.1f} s: {report['steps_per_s']:.1f} steps/s, "
          f"{report['points_per_s']:,.0f} points/s; latency p50 {report['p50_ms']:.1f} ms, "
          f"p90 {report['p90_ms']:.1f} ms, p99 {report['p99_ms']:.1f} ms, max {report['max_ms']:.1f} ms; "
          f"status {report['status']}, transport errors {report['transport_errors']}")
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(report, indent=2))
    ok = set(report["status"]) <= {200} and not report["transport_errors"]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
