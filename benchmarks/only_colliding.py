"""Collide-only benchmark: time per step of the paper's drape on the neural bunny, embedded, with
the cloth hook asking for contacts at every point it sends (``only_colliding=False``) against
contacts of the colliding points only (``only_colliding=True``, the hook's default), and against
distance alone (the floor: no gradient work at all).

    python benchmarks/only_colliding.py --models models --steps 20 --plot only_colliding.png

Two cloth placements, both 200 x 200 vertices (the paper's), all inside the bunny's box:
``above`` is the scene's start (13 mm above the bunny: nothing collides, the case where every
gradient was wasted) and ``touching`` lowers the cloth 30 mm so a patch of it rests on the
bunny. Prints one table (ms per step: total, and the query part of it) and the ratios measured
in this one run; the figures depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from collider_client import Client
from collider_client.response import world_box
from collider_client.sim.scene import SCENES_DIR, load_scene
from collider_client.sim.simulator import Simulator

#: name -> (fields the hook asks for, only_colliding). "distance only" steps like "only
#: colliding" (a touching cloth needs contacts) and times, per step, one more query of the same
#: points for distance + collides alone: the floor, with no gradient work; its total is not shown.
MODES = {
    "every point": (["distance", "contact", "collides"], False),
    "only colliding": (["distance", "contact", "collides"], True),
    "distance only": (["distance", "contact", "collides"], True),
}
PLACEMENTS = {"above": 0.0, "touching": -0.030}  # metres added to the cloth's z


def run(client, placement: str, mode: str, steps: int, cloth: int | None) -> dict:
    scene = load_scene(SCENES_DIR / "drape_bunny.toml")
    scene.cloth.origin_m = np.asarray(scene.cloth.origin_m, dtype=np.float64) + [0, 0, PLACEMENTS[placement]]
    if cloth is not None:  # a coarser cloth of the same physical size
        scene.cloth.spacing_m *= scene.cloth.width / cloth
        scene.cloth.width = scene.cloth.height = cloth
    sim = Simulator(scene, client, {m.name: m for m in client.list_models()})
    sim.hook.fields, sim.hook.only_colliding = MODES[mode]
    sim.step()  # warm-up: loads the model; a touching cloth is pushed out once
    sim.timings.__init__()
    stats = sim.hook.stats
    sent, colliding, floor_s = stats.points_sent, [], 0.0
    placement_ = sim.hook.colliders[0]
    lo, hi = world_box(sim.hook.infos[placement_.model], placement_.pose(0.0), sim.hook.eps + 1e-9)
    started = time.perf_counter()
    from tqdm import tqdm

    for _ in tqdm(range(steps), desc=f"{placement}, {mode}", unit="step", leave=False):
        sim.step()
        colliding.append(stats.colliding_last)
        if mode == "distance only":  # the same points the hook sends (static collider: one box)
            points = sim.vertices[np.all((sim.vertices >= lo) & (sim.vertices <= hi), axis=1)]
            q0 = time.perf_counter()
            client.query(placement_.model, points, ["distance", "collides"],
                         pose=placement_.pose(sim.t), eps=sim.hook.eps)
            floor_s += time.perf_counter() - q0
    wall = time.perf_counter() - started
    query_s = floor_s if mode == "distance only" else sim.timings.query_s
    return {"placement": placement, "mode": mode,
            "total": float("nan") if mode == "distance only" else 1e3 * wall / steps,
            "query": 1e3 * query_s / steps, "sent": (stats.points_sent - sent) / steps,
            "colliding": float(np.mean(colliding)), "vertices": scene.cloth.width * scene.cloth.height}


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    width = 0.8 / len(MODES)
    for k, mode in enumerate(MODES):
        values = [r["query"] for p in PLACEMENTS for r in rows if r["placement"] == p and r["mode"] == mode]
        ax.bar(np.arange(len(PLACEMENTS)) + (k - 1) * width, values, width, label=mode)
    ax.set_xticks(range(len(PLACEMENTS)), [f"cloth {p}" for p in PLACEMENTS])
    ax.set_ylabel("query ms per step (embedded)")
    ax.set_title(f"neural bunny drape, {rows[0]['vertices']} vertices: contacts for which points")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", type=Path, default=Path("models"),
                        help="model repository holding `bunny` (neural, Y-up, metres)")
    parser.add_argument("--steps", type=int, default=20, help="timed steps per run")
    parser.add_argument("--cloth", type=int, default=None, help="vertices per side (default 200)")
    parser.add_argument("--threads", type=int, default=max(1, (os.cpu_count() or 2) - 1))
    parser.add_argument("--plot", type=Path, default=None, help="write a PNG bar chart here")
    args = parser.parse_args(argv)
    rows = []
    with Client(models=args.models, threads=args.threads) as client:
        for placement in PLACEMENTS:
            for mode in MODES:
                rows.append(run(client, placement, mode, args.steps, args.cloth))
    print(f"{'cloth':<9} {'mode':<15} {'total ms':>9} {'query ms':>9} {'sent/step':>10} {'colliding':>10}")
    for r in rows:
        print(f"{r['placement']:<9} {r['mode']:<15} {r['total']:>9.1f} {r['query']:>9.1f} "
              f"{r['sent']:>10.0f} {r['colliding']:>10.0f}")
    by = {(r["placement"], r["mode"]): r for r in rows}
    for placement in PLACEMENTS:
        every, only, floor = (by[placement, m] for m in MODES)
        print(f"{placement}: every point / only colliding = {every['total'] / only['total']:.2f}x "
              f"per step ({every['query'] / only['query']:.2f}x query); only colliding / distance "
              f"only = {only['query'] / floor['query']:.2f}x query")
    if args.plot:
        plot(rows, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
