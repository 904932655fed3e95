"""Slow connections against a real ``collider serve`` (issue 21, item 1): thousands of connections
that send nothing, half a request, or their headers a byte a second, while a normal client keeps
querying.

Measured, in one run, in alternating slices without and with the attack:

- (a) every attacking connection is closed by the server within ``header_timeout_s`` (its
  lifetime, from the attacker's connect to the server's close; a closed one is opened again at
  once, so the attack holds its count for the whole slice), and the server's open descriptors
  (``/proc/PID/fd``) fall back to their quiet level after the attack;
- (b) the normal client's query latency (1,000 points, distance + normal + contact, msgpack, one
  keep-alive connection, back to back) during the attack against without it: the ratio of the
  medians per pair of slices, and its spread.

    python benchmarks/slow_connections.py                       # ~3 minutes; out/slow_connections.json
    python benchmarks/slow_connections.py --connections 3000 --header-timeout-s 5 --pairs 4
    python benchmarks/slow_connections.py --behind-nginx        # the attack and the client through nginx

``--behind-nginx`` puts a real nginx in front, configured with the deployment's own file
(docker/nginx/collider.conf.template, whose ``client_header_timeout`` then closes the slow
connections instead of the service), one worker with room for the attack; the normal client
goes through nginx in both slices, so the ratio compares like with like.

The attacker is a separate process (its own event loop and open-files limit, raised to fit),
neither niced nor pinned: it shares the cores with the server, and its CPU seconds are reported;
the model is a voxel sphere baked on the spot (no files needed).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import resource
import selectors
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_common import (
    LeanConnection,
    free_port,
    machine_note,
    nginx,
    nginx_config,
    percentiles_ms,
    query_body,
    serve,
)

KINDS = ("silent", "half-sent", "trickle")


# -- the attacker (a subprocess: python slow_connections.py --attack ...) ------------------------


def attack(port: int, count: int) -> dict:
    """Hold ``count`` slow connections to ``port``: a third send nothing, a third half a request
    line, a third a header byte a second. Each one the server closes is recorded and opened
    again, until a line comes on stdin; then none is opened again, and the open ones are held
    (never closed from here) until the server closes them, or for 60 s. Prints "ready" once all
    are open.

    One thread on ``selectors`` (epoll), not asyncio streams: the attacker's own event handling
    stays cheap, so a connection's lifetime (from its connect completing to the server's close
    being seen) is measured within milliseconds even with thousands open."""
    selector = selectors.DefaultSelector()
    selector.register(sys.stdin, selectors.EVENT_READ, "stdin")
    lifetimes: dict[str, list[float]] = {k: [] for k in KINDS}
    answers: dict[str, int] = {}
    state = {"open": 0, "connected": 0, "stopping": False, "stopped_at": None}

    def count_answer(key: str) -> None:
        answers[key] = answers.get(key, 0) + 1

    def start(kind: str) -> None:
        sock = socket.socket()
        sock.setblocking(False)
        sock.connect_ex(("127.0.0.1", port))
        selector.register(sock, selectors.EVENT_WRITE, {"kind": kind, "t0": None, "data": b""})
        state["open"] += 1

    def finish(sock, conn: dict, closed: bool) -> None:
        selector.unregister(sock)
        sock.close()
        state["open"] -= 1
        if closed and conn["t0"] is not None:
            lifetimes[conn["kind"]].append(time.monotonic() - conn["t0"])
            data = conn["data"]
            count_answer(data.split(b" ", 2)[1].decode() if data.startswith(b"HTTP/") else "none")
        elif conn["t0"] is None:
            count_answer("connect failed")
        if not state["stopping"]:
            start(conn["kind"])

    for i in range(count):
        start(KINDS[i % 3])
    next_trickle = time.monotonic() + 1.0
    while state["open"] and (state["stopped_at"] is None
                             or time.monotonic() - state["stopped_at"] < 60):
        for key, mask in selector.select(timeout=0.2):
            if key.data == "stdin":
                sys.stdin.readline()
                selector.unregister(sys.stdin)
                state["stopping"], state["stopped_at"] = True, time.monotonic()
                continue
            sock, conn = key.fileobj, key.data
            if conn["t0"] is None:  # the connect completed (or failed)
                if sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR):
                    finish(sock, conn, closed=False)
                    continue
                conn["t0"] = time.monotonic()
                state["connected"] += 1
                if state["connected"] == count:
                    print("ready", flush=True)
                if conn["kind"] == "half-sent":
                    sock.send(b"POST /v1/models/sphere/query HTTP/1.1\r\nHost: x\r\nContent-Le")
                elif conn["kind"] == "trickle":  # then one more byte of this header a second
                    sock.send(b"GET /livez HTTP/1.1\r\nHost: x\r\nX-Slow: ")
                selector.modify(sock, selectors.EVENT_READ, conn)
                continue
            try:
                chunk = sock.recv(4096)
            except OSError:
                chunk = b""
            if chunk:
                conn["data"] += chunk
            else:
                finish(sock, conn, closed=True)
        if time.monotonic() >= next_trickle:
            next_trickle += 1.0
            for key in list(selector.get_map().values()):
                if key.data != "stdin" and key.data["kind"] == "trickle" and key.data["t0"]:
                    try:
                        key.fileobj.send(b"a")
                    except OSError:
                        pass
    never = state["open"]
    every = sorted(x for v in lifetimes.values() for x in v)

    def quantile(q: float) -> float:
        return float(np.quantile(every, q)) if every else float("nan")

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {"connections": count, "closed_by_server": len(every),
            "attacker_cpu_s": usage.ru_utime + usage.ru_stime,
            "never_closed_within_60_s": never, "answers": answers,
            "lifetime_s": {k: {"n": len(v), "median": float(np.median(v)) if v else float("nan"),
                               "max": max(v, default=float("nan"))}
                           for k, v in lifetimes.items()},
            "lifetime_p50_s": quantile(0.5), "lifetime_p99_s": quantile(0.99),
            "max_lifetime_s": every[-1] if every else float("nan")}


def attacker_main(args) -> int:
    _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    result = attack(args.port, args.connections)
    print(json.dumps(result), flush=True)
    return 0


# -- the measurement ---------------------------------------------------------------------------


class FdSampler(threading.Thread):
    """The server's open descriptors every 0.1 s: (monotonic time, count)."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid, self.samples, self.stop = pid, [], threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                self.samples.append((time.monotonic(), len(os.listdir(f"/proc/{self.pid}/fd"))))
            except OSError:
                return
            time.sleep(0.1)


async def query_for(connection: LeanConnection, body: bytes, seconds: float) -> list[float]:
    """Latencies (s) of back-to-back queries on one keep-alive connection for ``seconds``."""
    latencies = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t0 = time.perf_counter()
        status, _ = await connection.post("/v1/models/sphere/query", body)
        latencies.append(time.perf_counter() - t0)
        assert status == 200, status
    return latencies


def measure(port: int, body: bytes, seconds: float, during=None) -> list[float]:
    """:func:`query_for` on a new connection, opened (and used once) before ``during()`` is
    called, as a simulator holds its keep-alive connection: with the server at max_connections
    a new connection would be refused, an open one keeps being served."""
    async def run():
        connection = LeanConnection("127.0.0.1", port)
        try:
            await connection.post("/v1/models/sphere/query", body)
            if during is not None:
                await asyncio.get_running_loop().run_in_executor(None, during)
            return await query_for(connection, body, seconds)
        finally:
            await connection.close()

    return asyncio.run(run())


def run_attack_slice(port: int, body: bytes, args, sampler: FdSampler) -> tuple[list[float], dict]:
    """Queries for ``args.slice_s`` under attack; then the attack stops opening connections and
    waits for the server to close the ones it holds. Also returns how long the server's
    descriptors took to come back to their level before the attack."""
    before = sampler.samples[-1][1]
    attacker = None

    def start_attack():
        nonlocal attacker
        attacker = subprocess.Popen(
            [sys.executable, __file__, "--attack", "--port", str(port), "--connections",
             str(args.connections)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert attacker.stdout.readline().strip() == "ready", "the attacker did not connect"

    latencies = measure(port, body, args.slice_s, during=start_attack)
    attacker.stdin.write("stop\n")
    attacker.stdin.close()
    stopped = time.monotonic()
    while sampler.samples[-1][1] > before + 5 and time.monotonic() - stopped < 60:
        time.sleep(0.05)
    fds_back_after_s = time.monotonic() - stopped
    result = json.loads(attacker.stdout.read())
    attacker.wait()
    return latencies, {**result, "fds_before": before, "fds_back_after_s": fds_back_after_s}


def nginx_header_timeout_s() -> float:
    """The deployment's nginx ``client_header_timeout`` (seconds)."""
    import re

    from service_common import NGINX_TEMPLATE

    return float(re.search(r"client_header_timeout (\d+)s;", NGINX_TEMPLATE.read_text()).group(1))


def make_models(root: Path) -> None:
    import trimesh

    from collider_server.engine.meshes import Mesh
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider

    tri = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    save_collider(bake_collider(Mesh(np.asarray(tri.vertices), np.asarray(tri.faces), "sphere"),
                                "voxel", "sphere", resolution=64, show_progress=False,
                                device="cpu"), root / "sphere.safetensors")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--connections", type=int, default=3000)
    parser.add_argument("--header-timeout-s", type=float, default=5.0)
    parser.add_argument("--max-connections", type=int, default=None,
                        help="the server's bound (default: the server's own, 4096)")
    parser.add_argument("--pairs", type=int, default=4, help="quiet/attack slice pairs")
    parser.add_argument("--slice-s", type=float, default=12.0, help="seconds of queries a slice")
    parser.add_argument("--behind-nginx", action="store_true",
                        help="attack and query through nginx with the deployment's configuration")
    parser.add_argument("--output", type=Path, default=None,
                        help="default out/slow_connections.json (out/slow_connections_nginx.json behind nginx)")
    parser.add_argument("--attack", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.attack:
        return attacker_main(args)

    print(f"machine: {machine_note()}; {args.pairs} pairs of {args.slice_s:g} s slices, "
          f"{args.connections} slow connections, header_timeout_s {args.header_timeout_s:g}; "
          f"about {args.pairs * 2 * (args.slice_s + 8) / 60:.0f} minutes", flush=True)
    load_start = os.getloadavg()
    body = query_body(np.random.default_rng(0).uniform(-0.15, 0.15, (1000, 3)).astype(np.float32),
                      ["distance", "normal", "contact"])
    flags = ["--header-timeout-s", str(args.header_timeout_s), "--compute-threads", "1",
             "--device", "cpu"]
    if args.max_connections:
        flags += ["--max-connections", str(args.max_connections)]
    report = {"machine": machine_note(), "connections": args.connections,
              "header_timeout_s": args.header_timeout_s, "slices": []}
    report["behind"] = "nginx" if args.behind_nginx else "the service alone"
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        make_models(Path(tmp))
        port = server_port = stack.enter_context(serve(Path(tmp), *flags))
        if args.behind_nginx:  # two descriptors per proxied connection, the attack's and the client's
            port = free_port()
            root = Path(tmp) / "nginx"
            root.mkdir()
            stack.enter_context(nginx(nginx_config("by-model", port, [server_port], root,
                                                   worker_connections=2 * args.connections + 256), port))
        from service_common import SERVER_PIDS

        sampler = FdSampler(SERVER_PIDS[server_port])
        front = "nginx" if args.behind_nginx else "the server"
        sampler.start()
        measure(port, body, 2.0)  # warm up
        for pair in range(args.pairs):
            # Alternate which goes first, so that a drift in the machine's load is shared.
            for mode in (("quiet", "attack") if pair % 2 == 0 else ("attack", "quiet")):
                started = time.monotonic()
                if mode == "quiet":
                    latencies, attacked = measure(port, body, args.slice_s), None
                else:
                    latencies, attacked = run_attack_slice(port, body, args, sampler)
                fds = [n for t, n in sampler.samples if t >= started]
                entry = {"pair": pair, "mode": mode, "queries": len(latencies),
                         **percentiles_ms(latencies),
                         "mean_ms": 1e3 * float(np.mean(latencies)),
                         "max_ms": 1e3 * max(latencies), "server_fds_max": max(fds),
                         "server_fds_min": min(fds)}
                if attacked:
                    entry["attack"] = attacked
                report["slices"].append(entry)
                print(f"pair {pair} {mode:6s}: {len(latencies)} queries, p50 "
                      f"{entry['p50_ms']:.2f} ms, p99 {entry['p99_ms']:.2f} ms, max "
                      f"{entry['max_ms']:.0f} ms, server fds "
                      f"{min(fds)}-{max(fds)}" + (
                          f"; attack: {attacked['closed_by_server']} closed by {front}, "
                          f"{attacked['never_closed_within_60_s']} never, longest lived "
                          f"{attacked['max_lifetime_s']:.2f} s, answers "
                          f"{attacked['answers']}, attacker's CPU "
                          f"{attacked['attacker_cpu_s']:.1f} s; fds back "
                          f"{attacked['fds_back_after_s']:.1f}"
                          " s after the attack stopped" if attacked else ""), flush=True)
        sampler.stop.set()
        quiet_fds = min(n for t, n in sampler.samples[:20])
    quiet = [s for s in report["slices"] if s["mode"] == "quiet"]
    attacked = [s for s in report["slices"] if s["mode"] == "attack"]
    ratios = [a["p50_ms"] / q["p50_ms"] for a, q in zip(attacked, quiet)]
    ratios99 = [a["p99_ms"] / q["p99_ms"] for a, q in zip(attacked, quiet)]
    ratios_mean = [a["mean_ms"] / q["mean_ms"] for a, q in zip(attacked, quiet)]
    longest = max(s["attack"]["max_lifetime_s"] for s in attacked)
    report["summary"] = {
        "p50_ratio_attack_over_quiet": {"median": float(np.median(ratios)), "min": min(ratios),
                                        "max": max(ratios), "each": ratios},
        "p99_ratio_attack_over_quiet": {"median": float(np.median(ratios99)),
                                        "min": min(ratios99), "max": max(ratios99)},
        "mean_ratio_attack_over_quiet": {"median": float(np.median(ratios_mean)),
                                         "min": min(ratios_mean), "max": max(ratios_mean)},
        "max_ms_quiet_attacked": [[q["max_ms"], a["max_ms"]] for q, a in zip(quiet, attacked)],
        "longest_attacking_connection_s": longest,
        "attacking_connection_lifetime_p99_s": max(s["attack"]["lifetime_p99_s"]
                                                   for s in attacked),
        "server_fds_quiet": quiet_fds,
        "server_fds_peak_under_attack": max(s["server_fds_max"] for s in attacked),
        "fds_back_after_s_max": max(s["attack"]["fds_back_after_s"] for s in attacked),
        "never_closed": sum(s["attack"]["never_closed_within_60_s"] for s in attacked),
        "load_average_start_end": [load_start[0], os.getloadavg()[0]],
    }
    summary = report["summary"]
    timeout = (f"nginx's client_header_timeout {nginx_header_timeout_s():g} s" if args.behind_nginx
               else f"header_timeout_s {args.header_timeout_s:g}")
    print(f"\nlongest-lived attacking connection {longest:.2f} s ({timeout}); server descriptors {quiet_fds} quiet, "
          f"{summary['server_fds_peak_under_attack']} at most under attack, back within "
          f"{summary['fds_back_after_s_max']:.1f} s after it")
    print(f"query p50 under attack / quiet: median {summary['p50_ratio_attack_over_quiet']['median']:.2f}x "
          f"(pairs {', '.join(f'{r:.2f}' for r in ratios)}); p99 median "
          f"{summary['p99_ratio_attack_over_quiet']['median']:.2f}x, mean "
          f"{summary['mean_ratio_attack_over_quiet']['median']:.2f}x; load average "
          f"{load_start[0]:.1f} -> {os.getloadavg()[0]:.1f}")
    if args.output is None:
        args.output = Path("out/slow_connections_nginx.json" if args.behind_nginx else "out/slow_connections.json")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(report, indent=1))
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
