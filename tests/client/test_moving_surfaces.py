"""Surfaces that move, rigidly (a pose over time) or by deforming (an animated mesh, its vertices
moving): the collision hook takes the surface's velocity from the service and responds relative
to it. Closed forms:

- a point resting on a moving surface moves with it under static friction (the surface's
  displacement, to a micrometre, while staying eps above it);
- a surface moving 10 eps per step neither passes through a free point nor leaves it inside: a
  floor and a 0.2 mm plate rising at 10 mm a step (eps 1 mm) carry the point on top.

Exact (``mesh`` kind) boxes through the embedded client; metres, seconds, world frame z up."""

from __future__ import annotations

import numpy as np
import pytest

import collider_client as cc
from collider_client import ColliderPlacement, CollisionHook

EPS = 1e-3
GRAVITY = np.array([0.0, 0.0, -9.81])


def box(extents, centre):
    import trimesh

    from collider_server.engine.meshes import Mesh

    shape = trimesh.creation.box(extents=extents)
    return Mesh(np.asarray(shape.vertices) + np.asarray(centre, float), np.asarray(shape.faces), "box")


def translation(x=0.0, y=0.0, z=0.0):
    pose = np.eye(4)
    pose[:3, 3] = [x, y, z]
    return pose


def translated(mesh, offsets, fps):
    """An animated mesh: ``mesh`` moved by each of ``offsets`` (k, 3) in turn, clamped."""
    from collider_contract import Timeline
    from collider_server.engine.animated_meshes import AnimatedMesh, max_surface_speed

    frames = mesh.vertices[None] + np.asarray(offsets, float)[:, None, :]
    return AnimatedMesh(frames, mesh.faces, Timeline(len(frames), fps, False,
                                                     max_surface_speed(frames, fps)))


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    """Exact colliders: ``floor`` 1 x 1 x 0.1 m (top at z = 0), ``plate`` 0.3 x 0.3 m, 0.2 mm
    thick (top at z = 0); animated: ``sliding-floor`` (the floor moving +x at 0.5 m/s for 4 s),
    ``rising-floor`` and ``rising-plate`` (moving +z at 1 m/s for 1 s)."""
    pytest.importorskip("collider_server")
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_animated_collider, bake_collider

    root = tmp_path_factory.mktemp("moving")
    floor = box((1.0, 1.0, 0.1), (0, 0, -0.05))
    plate = box((0.3, 0.3, 2e-4), (0, 0, -1e-4))
    for name, mesh in {"floor": floor, "plate": plate}.items():
        save_collider(bake_collider(mesh, "mesh", name), root / f"{name}.safetensors")
    animated = {"sliding-floor": translated(floor, [[0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]], 0.5),
                "rising-floor": translated(floor, [[0, 0, 0], [0, 0, 1.0]], 1.0),
                "rising-plate": translated(plate, [[0, 0, 0], [0, 0, 1.0]], 1.0)}
    for name, animation in animated.items():
        save_collider(bake_animated_collider(animation, "mesh", name), root / f"{name}.safetensors")
    with cc.Client(models=root, device="cpu") as embedded:
        yield embedded


def run(hook, x, v, t0, dt, steps, gravity=GRAVITY, each=None):
    """Verlet steps of free points as the reference simulator takes them, the hook after
    each; ``each(t, positions)`` is called after every step. Returns (positions, velocities)."""
    x = np.array(x, dtype=np.float64)
    previous = x - np.asarray(v, dtype=np.float64) * dt
    t = t0
    for _ in range(steps):
        new = x + (x - previous) + gravity * dt * dt
        t += dt
        positions, velocities, _ = hook.apply(new, (new - x) / dt, t, dt)
        previous, x = positions - velocities * dt, positions
        if each is not None:
            each(t, x)
    return x, (x - previous) / dt


# Oscillating along x: x_s(t) = A sin(w t), acceleration at most A w^2 = 0.02 x 25 = 0.5 m/s^2,
# below mu g = 0.6 x 9.81: static friction holds the point.
A, W = 0.02, 5.0


def test_a_point_resting_on_a_rigidly_moving_floor_moves_with_it(client):
    """The floor's pose oscillates along x; the point resting on it (eps above, at rest relative
    to it) follows it exactly: its displacement is the floor's."""
    floor = ColliderPlacement("floor", lambda t: translation(x=A * np.sin(W * t)))
    hook = CollisionHook(client, [floor], eps=EPS, friction=0.6)
    assert "velocity" in hook.fields
    dt, steps = 1e-3, 1000
    start = np.array([[0.1, 0.05, EPS]])
    heights = []
    x, v = run(hook, start, [[A * W, 0.0, 0.0]], 0.0, dt, steps,
               each=lambda t, p: heights.append(p[0, 2]))
    T = steps * dt
    np.testing.assert_allclose(x[0, 0] - start[0, 0], A * np.sin(W * T), atol=2e-6)
    np.testing.assert_allclose(v[0, 0], A * W * np.cos(W * T), atol=1e-3)
    assert abs(x[0, 1] - start[0, 1]) < 1e-9
    np.testing.assert_allclose(heights, EPS, atol=1e-7)  # resting eps above, never inside


def test_a_point_resting_on_a_deforming_surface_moves_with_it(client):
    """The animated floor's vertices move +x at 0.5 m/s (its pose is still): the surface's
    velocity comes from the interpolated vertex velocities, and the resting point, moving with
    it, keeps moving with it (with a still surface assumed, friction would stop it within
    0.5 / (0.6 g) = 85 ms)."""
    hook = CollisionHook(client, [ColliderPlacement("sliding-floor")], eps=EPS, friction=0.6)
    dt, steps = 1e-3, 1500
    start = np.array([[0.1, 0.05, EPS]])
    heights = []
    x, v = run(hook, start, [[0.5, 0.0, 0.0]], 0.0, dt, steps,
               each=lambda t, p: heights.append(p[0, 2]))
    np.testing.assert_allclose(x[0, 0] - start[0, 0], 0.5 * steps * dt, atol=1e-6)
    np.testing.assert_allclose(v[0], [0.5, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(heights, EPS, atol=1e-7)


def test_static_friction_is_measured_against_the_surface_not_the_world(client):
    """The control: a point at rest on the sliding floor (0.5 m/s slower than it) is dragged
    along by sliding friction, its speed rising by mu g dt a step (Coulomb), not jumping to the
    floor's: the response is relative to the surface's velocity, bounded as Coulomb says."""
    hook = CollisionHook(client, [ColliderPlacement("sliding-floor")], eps=EPS, friction=0.6)
    dt, steps = 1e-3, 40
    _, v = run(hook, [[0.1, 0.05, EPS]], [[0.0, 0.0, 0.0]], 0.0, dt, steps)
    np.testing.assert_allclose(v[0, 0], 0.6 * 9.81 * dt * steps, rtol=0.05)


@pytest.mark.parametrize("model, thickness", [("floor", 0.1), ("plate", 2e-4)])
@pytest.mark.parametrize("motion", ["pose", "animated"])
def test_a_surface_moving_10_eps_a_step_does_not_pass_through_a_point(client, model, motion, thickness):
    """A floor, and a plate thinner than a fifth of eps, rise at 1 m/s with dt = 10 ms: 10 mm, 10
    eps, a step, towards a free point 55.5 mm above (no gravity; checked only at the steps' ends,
    the plate would jump from 5.5 mm below it to 4.3 mm above it). The point is caught and
    carried: after every step it is on top, at least eps above the top face (never inside or
    below), and it ends moving up with the surface."""
    speed, dt = 1.0, 1e-2
    if motion == "pose":
        placement = ColliderPlacement(model, lambda t: translation(z=speed * t))
    else:
        placement = ColliderPlacement(f"rising-{model}")
    hook = CollisionHook(client, [placement], eps=EPS)
    gaps = []
    x, v = run(hook, [[0.02, -0.03, 0.0555]], [[0.0, 0.0, 0.0]], 0.0, dt, 40, gravity=np.zeros(3),
               each=lambda t, p: gaps.append(p[0, 2] - speed * t))
    gaps = np.array(gaps)
    assert (gaps >= EPS * (1 - 1e-6)).all(), gaps.min()  # on top, eps above, at every step
    assert np.abs(gaps[10:] - EPS).max() < 1e-9  # carried: caught by step 5, riding since
    np.testing.assert_allclose(v[0], [0.0, 0.0, speed], atol=1e-9)
    assert x[0, 2] > 0.39  # it went up with the surface, not through it


def test_a_surface_that_speeds_up_within_a_step_does_not_leave_a_point_inside(client):
    """The floor accelerates upwards at 20 m/s^2 (z = 10 t^2), its speed growing 0.2 m/s a step
    (dt = 10 ms) to 2 m/s: a point caught part-way through a step and moved on with the floor's
    velocity there would fall behind the faster floor by the step's end (up to 2 mm, 2 eps)
    were it not checked again at the step's later checks. After every step it is on top, eps
    above."""
    floor = ColliderPlacement("floor", lambda t: translation(z=10.0 * t * t))
    hook = CollisionHook(client, [floor], eps=EPS)
    gaps = []
    run(hook, [[0.02, -0.03, 0.0123]], [[0.0, 0.0, 0.0]], 0.0, 1e-2, 10, gravity=np.zeros(3),
        each=lambda t, p: gaps.append(p[0, 2] - 10.0 * t * t))
    assert min(gaps) >= EPS * (1 - 1e-6), gaps
    assert hook.stats.colliding_last == 1


def test_the_duration_probe_asks_an_animated_collider_at_a_time(tmp_path):
    """`collider simulate`'s duration estimate probes the first collider as the hook asks; an
    animated one refuses a query without a time, so the probe gives it the first frame's."""
    from tests.conftest import REPO_ROOT

    from collider_client.sim.run import query_cost_per_point
    from collider_client.sim.scene import load_scene, resolve_scene

    scene = load_scene(resolve_scene("cloth_on_arm"))
    with cc.Client(models=REPO_ROOT / "models") as arm_client:
        assert {m.name: m for m in arm_client.list_models()}["arm"].animated
        hook = CollisionHook(arm_client, [ColliderPlacement("arm")], friction=0.3)
        per_point = query_cost_per_point(arm_client, scene, hook)
    assert per_point is not None and 0 < per_point < 1e-3
