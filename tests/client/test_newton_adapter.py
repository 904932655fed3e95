"""The Newton adapter: a small Newton cloth (XPBD, CPU) dropped on a real (voxel) sphere ends with
no particle inside it; on an animated sphere, asked at Newton's time, none is ever inside the
sphere of that time. Skips when Newton (the ``newton`` extra) is not installed."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from .conftest import SPHERE_RADIUS_M

# Found, not imported, at collection: importing Newton (and Warp) costs seconds in every worker.
pytestmark = pytest.mark.skipif(importlib.util.find_spec("newton") is None,
                                reason="Newton is not installed (pip install '.[newton]')")


@pytest.fixture(autouse=True)
def newton_modules():
    """Newton and Warp as the module's ``newton`` and ``wp``, imported by the first test."""
    global newton, wp
    import newton
    import warp as wp


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


def test_the_example_writes_its_output_under_out_not_into_the_working_folder(tmp_path, models_dir,
                                                                            monkeypatch, capsys):
    """``examples/newton_cloth_drop.py`` (two steps): the positions go to out/newton_cloth_drop.npy
    like every command's outputs; nothing else appears in the working folder. Its ``main`` runs
    in this process (a process of its own spent ~10 s of CPU importing torch, Newton and Warp
    again; the working folder is what is tested, and the test's is the example's)."""
    import importlib.util
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "newton_cloth_drop.py"
    spec = importlib.util.spec_from_file_location("newton_cloth_drop", example)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.chdir(tmp_path)
    code = module.main(["--models", str(models_dir), "--model", "sphere", "--pose", "identity",
                        "--steps", "2", "--cells", "5"])
    assert code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert np.load(tmp_path / "out" / "newton_cloth_drop.npy").shape == (25, 3)
    assert capsys.readouterr().out.strip().endswith("wrote out/newton_cloth_drop.npy")


def test_a_skinned_collider_follows_newtons_bodies(models_dir):
    """Newton bodies placed and moving as the skinned arm's joints in clip "wave" at 0.3 s:
    :func:`articulation_pose` gives back the clip's joint transforms and their exact time
    derivatives (float32 state: to 1e-6), and a query at them answers as the clip does."""
    from scipy.spatial.transform import Rotation

    import collider_client as cc
    from collider_client.adapters.newton import articulation_pose
    from collider_server.engine.skinning import pose_at
    from collider_server.making.skinned import skinned_arm

    wp.config.quiet = True
    transforms, rates = pose_at(skinned_arm(), "wave", 0.3)
    coms = np.array([[0.1, 0.0, 0.0], [0.08, 0.01, 0.0], [0.03, 0.0, -0.01]])  # body frames
    builder = newton.ModelBuilder()
    for com in coms:
        builder.add_body(com=wp.vec3(*com), mass=1.0)
    model = builder.finalize(device="cpu")
    state = model.state()
    rotation = transforms[:, :3, :3]
    # Newton's twist: the centre of mass's velocity and the angular velocity, world frame
    omega_x = rates[:, :3, :3] @ rotation.transpose(0, 2, 1)
    omega = np.stack([omega_x[:, 2, 1], omega_x[:, 0, 2], omega_x[:, 1, 0]], axis=1)
    com_velocity = rates[:, :3, 3] + np.cross(omega, np.einsum("jab,jb->ja", rotation, coms))
    body_q = np.concatenate([transforms[:, :3, 3], Rotation.from_matrix(rotation).as_quat()], axis=1)
    state.body_q.assign(body_q.astype(np.float32))
    state.body_qd.assign(np.concatenate([com_velocity, omega], axis=1).astype(np.float32))
    got, got_rates = articulation_pose(model, state, [0, 1, 2])
    np.testing.assert_allclose(got, transforms, atol=1e-6)
    np.testing.assert_allclose(got_rates, rates, atol=2e-6)
    assert np.abs(rates).max() > 0.5  # the arm moves: not 0 == 0
    # a collider placed elsewhere in Newton's world: the transforms come back in its frame
    placed = np.eye(4)
    placed[:3, 3] = [1.0, 2.0, 0.5]
    shifted = body_q.copy()
    shifted[:, :3] += placed[:3, 3]
    state.body_q.assign(shifted.astype(np.float32))
    np.testing.assert_allclose(articulation_pose(model, state, [0, 1, 2], placed)[0], transforms,
                               atol=1e-5)
    points = np.random.default_rng(2).uniform([-0.1, -0.15, -0.1], [0.6, 0.15, 0.4], (200, 3))
    with cc.Client(models=models_dir, device="cpu") as client:
        by_clip = client.query("arm", points, fields=["distance", "velocity"], clip="wave", time=0.3)
        by_bodies = client.query("arm", points, fields=["distance", "velocity"],
                                 joint_transforms=got, joint_velocities=got_rates)
    np.testing.assert_allclose(by_bodies.distance, by_clip.distance, atol=2e-6)
    np.testing.assert_allclose(by_bodies.velocity, by_clip.velocity, atol=2e-5)
