"""A Newton cloth (XPBD solver) dropped on one of our colliders, on the CPU.

    python examples/newton_cloth_drop.py --models models --model bunny --pose y-up
    python examples/newton_cloth_drop.py --server http://127.0.0.1:8000 --model bunny --pose y-up

Newton integrates the cloth (springs, gravity -z); between its substeps the adapter sends the
particles near the collider to the collider service and applies our response (projection to the
contact points, Coulomb friction). Writes the final particle positions to OUTPUT.npy (metres,
world frame; default out/newton_cloth_drop.npy, like the ``collider`` commands' outputs) and
prints how deep the deepest particle is inside (collider's own distance).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def y_up_to_z_up() -> np.ndarray:
    """Pose (4x4, collider -> world) turning a Y-up model Z-up: x stays, y -> z, z -> -y."""
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    return pose


def build(args):
    import newton
    import warp as wp

    builder = newton.ModelBuilder()
    size = (args.cells - 1) * args.cell_m
    builder.add_cloth_grid(
        pos=wp.vec3(args.centre[0] - size / 2, args.centre[1] - size / 2, args.height_m),
        rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
        dim_x=args.cells - 1, dim_y=args.cells - 1, cell_x=args.cell_m, cell_y=args.cell_m,
        mass=args.particle_mass_kg, add_springs=True, spring_ke=args.spring_ke, spring_kd=0.0,
        particle_radius=1e-3)
    model = builder.finalize(device="cpu")
    solver = newton.solvers.SolverXPBD(model=model, iterations=args.iterations)
    return model, solver


def run(client, args):
    from collider_client import ColliderPlacement, CollisionHook
    from collider_client.adapters.newton import NewtonCollider

    model, solver = build(args)
    state_0, state_1, control = model.state(), model.state(), model.control()
    pose = y_up_to_z_up() if args.pose == "y-up" else np.eye(4)
    hook = CollisionHook(client, [ColliderPlacement(args.model, pose)],
                         eps=args.eps_m, friction=args.friction)
    adapter = NewtonCollider(model, hook)
    dt, t = args.dt_s, 0.0
    start_size = float(np.ptp(state_0.particle_q.numpy(), axis=0).max())
    started = time.perf_counter()
    for _ in range(args.steps):
        state_0.clear_forces()
        solver.step(state_0, state_1, control, None, dt)
        state_0, state_1 = state_1, state_0
        t += dt
        adapter.apply(state_0, t, dt)
    wall = time.perf_counter() - started
    q = state_0.particle_q.numpy()
    size = float(np.ptp(q, axis=0).max()) if np.isfinite(q).all() else float("inf")
    if size > 10 * start_size:  # a blown-up cloth: its collider distances would mean nothing
        raise SystemExit(f"newton_cloth_drop: the cloth blew up (it spans {size:.3g} m, it "
                         f"started at {start_size:.3g} m); lower --dt-s or raise --iterations")
    final = client.query(args.model, q, fields=["distance"], pose=pose)
    return q, float(final.distance.min()), hook.stats, wall


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", default=None, help="collider serve URL (default: embedded)")
    parser.add_argument("--models", default=None, help="model repository (embedded)")
    parser.add_argument("--model", default="bunny")
    parser.add_argument("--pose", choices=["identity", "y-up"], default="y-up",
                        help="y-up: the model is Y-up and is turned Z-up (the shipped bunny)")
    parser.add_argument("--cells", type=int, default=40, help="particles per side")
    parser.add_argument("--cell-m", type=float, default=5e-3)
    parser.add_argument("--centre", type=float, nargs=2, default=[-0.017, 0.0])
    parser.add_argument("--height-m", type=float, default=0.20)
    parser.add_argument("--particle-mass-kg", type=float, default=1e-2,
                        help="Newton XPBD on CPU went unstable on contact below ~1e-2 kg here")
    parser.add_argument("--spring-ke", type=float, default=500.0)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--dt-s", type=float, default=1e-3)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--eps-m", type=float, default=1e-3)
    parser.add_argument("--friction", type=float, default=0.4)
    parser.add_argument("--output", type=Path, default=Path("out") / "newton_cloth_drop",
                        help="output path without .npy (default out/newton_cloth_drop; the folder is created)")
    args = parser.parse_args(argv)

    from collider_client import Client

    output = args.output.with_name(args.output.name + ".npy")
    output.parent.mkdir(parents=True, exist_ok=True)  # before the run, not after it
    client = Client(args.server) if args.server else Client(models=args.models)
    with client:
        q, deepest, stats, wall = run(client, args)
    np.save(output, q)
    print(f"{args.steps} Newton steps in {wall:.2f} s ({1e3 * wall / args.steps:.2f} ms/step, "
          f"query {1e3 * stats.query_s / args.steps:.2f} ms/step); contacts at the end "
          f"{stats.colliding_last}; deepest particle {1e3 * max(0.0, -deepest):.3f} mm inside; "
          f"wrote {output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
