"""Effects benchmark: time per step of the paper's drape with only the effects it needs, against
the same scene with every effect on and every field requested (and without box culling),
embedded and through a real `collider serve`.

    python benchmarks/simulate.py --models models --steps 100 --serve --plot simulate.png

Prints one table (ms per step: total = integration + collision (client side) + query (engine in
process, or HTTP round trip + server)) and the ratios measured in this one run. Units: ms/step.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from collider_client import FIELDS, Client
from collider_client.sim.scene import SCENES_DIR, load_scene
from collider_client.sim.simulator import Simulator

VARIANTS = {
    "needed": ("drape_bunny.toml", "the paper's effects; distance + contact; culled"),
    "all": ("drape_bunny_all_effects.toml", "+ wind, friction; every field; culled"),
    "all-nocull": ("drape_bunny_all_effects.toml", "+ wind, friction; every field; every point"),
}


def run_variant(variant: str, client, steps: int, cloth: int | None,
                start: np.ndarray | None = None) -> dict:
    scene = load_scene(SCENES_DIR / VARIANTS[variant][0])
    if cloth is not None:  # a coarser cloth of the same physical size
        scale = scene.cloth.width / cloth
        scene.cloth.width = scene.cloth.height = cloth
        scene.cloth.spacing_m *= scale
    infos = {m.name: m for m in client.list_models()}
    sim = Simulator(scene, client, infos)
    if start is not None:  # resume from a saved frame (e.g. the draped cloth), at rest
        sim.x = start.reshape(sim.x.shape).astype(np.float64)
        sim.x_prev = sim.x.copy()
    if variant != "needed":
        sim.hook.fields = list(FIELDS)
    if variant == "all-nocull":
        sim.hook.cull = False
    sim.step()  # warm-up: loads the model, opens the connection
    sim.timings.__init__()
    sent_before = sim.hook.stats.points_sent
    started = time.perf_counter()
    from tqdm import tqdm

    for _ in tqdm(range(steps), desc=variant, unit="step", leave=False):
        sim.step()
    wall = time.perf_counter() - started
    t = sim.timings
    return {"variant": variant, "vertices": scene.cloth.width * scene.cloth.height,
            "total": 1e3 * wall / steps, "integration": 1e3 * t.integration_s / steps,
            "collision": 1e3 * t.collision_s / steps, "query": 1e3 * t.query_s / steps,
            "sent": (sim.hook.stats.points_sent - sent_before) / steps,
            "colliding": sim.hook.stats.colliding_last,
            "fields": ",".join(sim.hook.fields), "effects": ",".join(sim.effects)}


def start_server(models: Path):
    """A ready ``collider serve`` over ``models``: ``(process, url)``."""
    from collider_cli.launch import ServerProcess

    server = ServerProcess(models, "--log-level", "warning").wait_ready(120)
    return server.process, server.url


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['variant']}\n{r['backend']}" for r in rows]
    bottom = np.zeros(len(rows))
    fig, ax = plt.subplots(figsize=(1.6 * len(rows) + 2, 4.5))
    for part, colour in (("integration", "#4a90d9"), ("collision", "#f5a623"),
                         ("query", "#c0392b")):
        values = np.array([r[part] for r in rows])
        ax.bar(labels, values, bottom=bottom, color=colour, label=part)
        bottom += values
    ax.set_ylabel("ms per step")
    ax.set_title(f"drape, {rows[0]['vertices']} vertices: time per step by part")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", type=Path, default=Path("models"),
                        help="model repository holding `bunny` (Y-up, metres)")
    parser.add_argument("--steps", type=int, default=100, help="timed steps per variant")
    parser.add_argument("--cloth", type=int, default=None,
                        help="vertices per side (default: the paper's 200)")
    parser.add_argument("--serve", action="store_true",
                        help="also time through a `collider serve` started on loopback")
    parser.add_argument("--server", default=None, help="also time through this running server")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--start", type=Path, default=None,
                        help="start from the last frame of this PC2 (e.g. out/drape_bunny.pc2 "
                             "of a full run), so the timed steps are in contact")
    parser.add_argument("--plot", type=Path, default=None, help="write a PNG bar chart here")
    args = parser.parse_args(argv)

    backends = [("embedded", None)]
    process = None
    if args.serve:
        process, url = start_server(args.models)
        backends.append(("remote", url))
    elif args.server:
        backends.append(("remote", args.server))
    start = None
    if args.start is not None:
        from collider_contract.point_cache import read_pc2

        start = np.array(read_pc2(args.start)[-1])
    rows = []
    try:
        for backend, url in backends:
            client = Client(url, timeout_s=120) if url else Client(
                models=args.models, threads=max(1, (os.cpu_count() or 2) - 1))
            with client:
                for variant in args.variants.split(","):
                    row = run_variant(variant, client, args.steps, args.cloth, start)
                    row["backend"] = backend
                    rows.append(row)
    finally:
        if process is not None:
            process.terminate()
            process.wait(timeout=30)

    print(f"{'variant':<11} {'backend':<9} {'verts':>6} {'total':>8} {'integr':>8} {'collis':>8} "
          f"{'query':>8} {'sent/step':>10} {'contacts':>8}  fields")
    for r in rows:
        print(f"{r['variant']:<11} {r['backend']:<9} {r['vertices']:>6} {r['total']:>8.2f} "
              f"{r['integration']:>8.2f} {r['collision']:>8.2f} {r['query']:>8.2f} "
              f"{r['sent']:>10.0f} {r['colliding']:>8}  {r['fields']}")
    by = {(r["variant"], r["backend"]): r for r in rows}
    for backend, _ in backends:
        base = by.get(("needed", backend))
        for variant in ("all", "all-nocull"):
            other = by.get((variant, backend))
            if base and other:
                print(f"{backend}: {variant} / needed = {other['total'] / base['total']:.2f}x "
                      "time per step")
    if ("needed", "remote") in by and ("needed", "embedded") in by:
        print(f"needed: remote / embedded = "
              f"{by['needed', 'remote']['total'] / by['needed', 'embedded']['total']:.2f}x")
    if args.plot:
        plot(rows, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
