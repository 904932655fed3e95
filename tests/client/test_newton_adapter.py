"""The Newton adapter: a small Newton cloth (XPBD, CPU) dropped on a real (voxel) sphere ends with
no particle inside it; on an animated sphere, asked at Newton's time, none is ever inside the
sphere of that time. Skips when Newton (the ``newton`` extra) is not installed."""

from __future__ import annotations

import numpy as np
import pytest

from .conftest import SPHERE_RADIUS_M

newton = pytest.importorskip("newton", reason="Newton is not installed (pip install '.[newton]')")
wp = pytest.importorskip("warp")


def test_newton_cloth_drop_on_sphere_ends_outside(models_dir):
    import collider_client as cc
    from collider_client.adapters.newton import NewtonCollider

    wp.config.quiet = True
    builder = newton.ModelBuilder()  # z up, gravity -9.81 z, metres
    cells, cell_m = 15, 0.01
    builder.add_cloth_grid(
        pos=wp.vec3(-cells * cell_m / 2, -cells * cell_m / 2, SPHERE_RADIUS_M + 0.01),
        rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0), dim_x=cells, dim_y=cells,
        cell_x=cell_m, cell_y=cell_m, mass=1e-2, add_springs=True, spring_ke=500.0,
        spring_kd=0.0, particle_radius=1e-3)
    model = builder.finalize(device="cpu")
    solver = newton.solvers.SolverXPBD(model=model, iterations=10)
    state_0, state_1, control = model.state(), model.state(), model.control()
    start = state_0.particle_q.numpy().copy()
    dt, t = 1e-3, 0.0
    with cc.Client(models=models_dir, device="cpu") as client:
        hook = cc.CollisionHook(client, [cc.ColliderPlacement("sphere")], eps=1e-3, friction=0.3)
        adapter = NewtonCollider(model, hook)
        assert hook.only_colliding  # the service computes contacts of colliding particles only
        contacts = []
        for _ in range(150):
            state_0.clear_forces()
            solver.step(state_0, state_1, control, None, dt)
            state_0, state_1 = state_1, state_0
            t += dt
            contacts.append(adapter.apply(state_0, t, dt))
    q = state_0.particle_q.numpy()
    assert np.isfinite(q).all()
    assert max(contacts) > 10                        # the cloth did land on the sphere
    assert q[:, 2].min() < start[:, 2].min() - 0.02  # and fell past its top around it
    depth = SPHERE_RADIUS_M - np.linalg.norm(q.astype(np.float64), axis=1)
    assert depth.max() < 1e-3                        # no particle ends inside (1 mm tolerance)


@pytest.mark.parametrize("offset", [0.0, 0.25])
def test_newton_cloth_on_an_animated_sphere_is_asked_at_newtons_time(models_dir, offset):
    """The adapter passes Newton's time: the cloth falls onto the pulsing, moving sphere
    (``pulse``, exact, animated; the analytic sphere of radius r(t) at c(t), within its 0.6 mm
    tessellation gap), and after every substep no particle is inside the sphere as it is at
    that time plus the placement's ``time_offset_s`` (0.25 s: a quarter period, the sphere
    0.12 m at x = +0.1 at t = 0, where 0.25 s earlier it is 0.08 m at x = -0.1)."""
    import collider_client as cc
    from collider_client.adapters.newton import NewtonCollider
    from collider_server.making.animations import pulsing_sphere

    _, reference = pulsing_sphere()
    wp.config.quiet = True
    builder = newton.ModelBuilder()
    cells, cell_m = 15, 0.01
    builder.add_cloth_grid(
        pos=wp.vec3(-cells * cell_m / 2, -cells * cell_m / 2, 0.13), rot=wp.quat_identity(),
        vel=wp.vec3(0.0, 0.0, 0.0), dim_x=cells, dim_y=cells, cell_x=cell_m, cell_y=cell_m,
        mass=1e-2, add_springs=True, spring_ke=500.0, spring_kd=0.0, particle_radius=1e-3)
    model = builder.finalize(device="cpu")
    solver = newton.solvers.SolverXPBD(model=model, iterations=10)
    state_0, state_1, control = model.state(), model.state(), model.control()
    dt, t = 1e-3, 0.0
    deepest, contacts = 0.0, []
    with cc.Client(models=models_dir, device="cpu") as client:
        hook = cc.CollisionHook(client, [cc.ColliderPlacement("pulse", time_offset_s=offset)],
                                eps=1e-3, friction=0.3)
        assert "velocity" in hook.fields
        adapter = NewtonCollider(model, hook)
        for _ in range(200):
            state_0.clear_forces()
            solver.step(state_0, state_1, control, None, dt)
            state_0, state_1 = state_1, state_0
            t += dt
            contacts.append(adapter.apply(state_0, t, dt))
            q = state_0.particle_q.numpy().astype(np.float64)
            depth = -reference.signed_distance(q, t + offset)
            deepest = max(deepest, float(depth.max()))
    assert np.isfinite(state_0.particle_q.numpy()).all()
    assert max(contacts) > 10  # the cloth met the sphere, growing up into it from t = 0
    assert deepest < 0.6e-3 + 1e-4  # never inside the sphere of that time (tessellation gap)


def test_adapter_needs_particles():
    from collider_client.adapters.newton import NewtonCollider

    model = newton.ModelBuilder().finalize(device="cpu")
    with pytest.raises(ValueError, match="no particles"):
        NewtonCollider(model, hook=None)


def test_the_example_writes_its_output_under_out_not_into_the_working_folder(tmp_path, models_dir):
    """``examples/newton_cloth_drop.py`` (two steps): the positions go to out/newton_cloth_drop.npy
    like every command's outputs; nothing else appears in the working folder."""
    import subprocess
    import sys
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "newton_cloth_drop.py"
    result = subprocess.run([sys.executable, str(example), "--models", str(models_dir), "--model", "sphere",
                             "--pose", "identity", "--steps", "2", "--cells", "5"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert np.load(tmp_path / "out" / "newton_cloth_drop.npy").shape == (25, 3)
    assert result.stdout.strip().endswith("wrote out/newton_cloth_drop.npy")
