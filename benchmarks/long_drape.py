"""The paper's full drape (5 s, 50,000 steps of 1e-4 s, 200 x 200 vertices) on a voxel bunny,
checked for the long-run guarantees of the hard-case suite (README, "Hard cases"):

- no position ever becomes NaN or infinite (the simulator stops at the first one);
- the cloth's mechanical energy stays bounded (it may only fall below its start: gravity, springs
  and kinetic energy; damping and inelastic contact dissipate);
- at every written frame, no vertex is deeper than 0.1 mm inside the exact mesh (eps is 1 mm).

    python benchmarks/long_drape.py                      # full 5 s (about 16 min on a quiet 2-core CPU)
    python benchmarks/long_drape.py --steps 5000 --json out/long_drape.json

The voxel bunny (128^3 by default) is baked from the Stanford bunny (Y-up, metres; the scene's pose
turns it Z-up) into a temporary model folder. Prints one summary; writes JSON with per-frame
figures when asked. Units: metres, joules, seconds.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from collider_client import Client
from collider_client.sim.motion import pose_function
from collider_client.sim.scene import SCENES_DIR, load_scene
from collider_client.sim.simulator import Simulator

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MESH = REPO.parent / "shared" / "data" / "meshes" / "stanford-bunny.obj"


def bake_voxel_bunny(mesh_path: Path, resolution: int, folder: Path) -> None:
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider
    from collider_server.making.mesh_files import load_mesh

    collider = bake_collider(load_mesh(mesh_path), "voxel", "bunny", resolution=resolution)
    save_collider(collider, folder / "bunny.safetensors")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--steps", type=int, default=None, help="default: the scene's 50,000")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from tqdm import tqdm

    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.mesh_files import load_mesh

    scene = load_scene(SCENES_DIR / "drape_bunny.toml")
    steps = scene.steps if args.steps is None else args.steps
    exact = ExactSDF(load_mesh(args.mesh))
    pose_at = pose_function(scene.colliders[0])
    with tempfile.TemporaryDirectory() as folder:
        bake_voxel_bunny(args.mesh, args.resolution, Path(folder))
        with Client(models=folder, device="cpu") as client:
            sim = Simulator(scene, client, {m.name: m for m in client.list_models()})
            start_energy = sim.energy()["total"]
            frames = []
            started = time.perf_counter()
            for i in tqdm(range(1, steps + 1), desc="drape", unit="step", smoothing=0.05):
                sim.step()  # raises SimulationError at the first non-finite or runaway state
                if i % scene.frame_every == 0 or i == steps:
                    pose = pose_at(sim.t)
                    local = (sim.vertices - pose[:3, 3]) @ pose[:3, :3]
                    distance = exact.signed_distance(local)
                    energy = sim.energy()
                    frames.append({"step": i, "t_s": sim.t, "finite": bool(np.isfinite(sim.x).all()),
                                   "deepest_inside_m": float(max(0.0, -distance.min())),
                                   "closest_m": float(distance.min()), "energy_j": energy,
                                   "colliding": sim.hook.stats.colliding_last})
                    if args.json:  # after every frame: a run stopped early keeps its figures
                        write_json(args.json, summarise(frames, start_energy, scene, args,
                                                        time.perf_counter() - started), frames)
            wall = time.perf_counter() - started
    summary = summarise(frames, start_energy, scene, args, wall)
    for key, value in summary.items():
        print(f"{key:26s} {value}")
    ok = summary["all_finite"] and summary["energy_rise_j"] <= 0.0 and summary["deepest_inside_exact_mm"] <= 0.1
    print("guarantees (finite, energy not above its start, deepest <= 0.1 mm):", "met" if ok else "NOT met")
    if args.json:
        write_json(args.json, summary, frames)


def write_json(path: Path, summary: dict, frames: list) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"summary": summary, "frames": frames}, indent=1))


def summarise(frames: list, start_energy: float, scene, args, wall: float) -> dict:
    """The run's figures over the frames so far."""
    steps = frames[-1]["step"]
    worst = max(frames, key=lambda f: f["deepest_inside_m"])
    energies = np.array([f["energy_j"]["total"] for f in frames])
    return {
        "steps": steps, "dt_s": scene.dt_s, "simulated_s": steps * scene.dt_s, "frames": len(frames),
        "wall_s": round(wall, 1), "ms_per_step": round(1e3 * wall / steps, 2),
        "voxel_resolution": args.resolution, "all_finite": all(f["finite"] for f in frames),
        "energy_start_j": start_energy, "energy_max_j": float(energies.max()),
        "energy_end_j": float(energies[-1]),
        "energy_rise_j": float(energies.max() - start_energy),
        "deepest_inside_exact_mm": 1e3 * worst["deepest_inside_m"], "deepest_at_step": worst["step"],
        "closest_mm": 1e3 * min(f["closest_m"] for f in frames),
        "colliding_max": max(f["colliding"] for f in frames),
    }


if __name__ == "__main__":
    main()
