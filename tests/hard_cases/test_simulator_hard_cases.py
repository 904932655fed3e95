"""Hard cases of the cloth simulator and the collision response, each against a closed-form or
independently computed expectation: every effect would fail here if its sign, its magnitude or its
presence were wrong. Units: metres, seconds, kilograms; world frame, gravity along -z.

Colliders are exact (``mesh`` kind) boxes, so what is measured is the simulator, not a model's
approximation: a floor (top face at z = 0) and a thin plate (0.2 mm thick, thinner than eps).
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest

import collider_client as cc
from collider_client.response import ColliderPlacement, CollisionHook
from collider_client.sim.cloth import FAMILIES
from collider_client.sim.scene import load_scene
from collider_client.sim.simulator import SimulationError, Simulator
from collider_client.sim.tables import SceneError

G = 9.81
EPS = 1e-3
PLATE_THICKNESS = 2e-4


def write_scene(tmp_path: Path, effects: str, *, width=3, height=3, spacing=0.01, dt=1e-3,
                duration=1.0, origin=(0.0, 0.0, 0.0), axes="xy", density=0.5, colliders="",
                name="case") -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(f"""
[scene]
duration_s = {duration}
dt_s = {dt}
frame_every_steps = 10

[cloth]
width = {width}
height = {height}
spacing_m = {spacing}
origin_m = {list(origin)}
axes = "{axes}"
density_kg_m2 = {density}
{colliders}
[effects]
{effects}
""")
    return path


def simulator(tmp_path, effects, client=None, **kwargs) -> Simulator:
    scene = load_scene(write_scene(tmp_path, effects, **kwargs))
    infos = None if client is None else {m.name: m for m in client.list_models()}
    return Simulator(scene, client, infos)


def run(sim: Simulator, steps: int) -> None:
    for _ in range(steps):
        sim.step()


def velocity(sim: Simulator) -> np.ndarray:
    return (sim.x - sim.x_prev) / sim.dt


# -- colliders: exact boxes ------------------------------------------------------------------------


def _box(extents, centre):
    import trimesh

    from collider_server.engine.meshes import Mesh

    box = trimesh.creation.box(extents=extents)
    return Mesh(np.asarray(box.vertices) + np.asarray(centre, float), np.asarray(box.faces), "box")


@pytest.fixture(scope="module")
def box_models(tmp_path_factory) -> Path:
    """``floor``: 1 x 1 x 0.1 m, top face at z = 0; ``plate``: 0.3 x 0.3 m, 0.2 mm thick, its
    faces at z = 0 and z = -0.2 mm. Exact mesh colliders, metres."""
    pytest.importorskip("collider_server")
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider

    root = tmp_path_factory.mktemp("boxes")
    for name, mesh in {"floor": _box((1.0, 1.0, 0.1), (0, 0, -0.05)),
                       "plate": _box((0.3, 0.3, PLATE_THICKNESS), (0, 0, -PLATE_THICKNESS / 2))}.items():
        save_collider(bake_collider(mesh, "mesh", name, show_progress=False), root / f"{name}.safetensors")
    return root


@pytest.fixture(scope="module")
def client(box_models):
    with cc.Client(models=box_models, device="cpu") as c:
        yield c


def floor_scene(position=(0, 0, 0), rotation=(0, 0, 0), model="floor", motion=""):
    return (f'[[colliders]]\nmodel = "{model}"\nposition_m = {list(position)}\n'
            f'rotation_deg = {list(rotation)}\n{motion}\n')


# -- 2. every effect against a closed form ---------------------------------------------------------


def test_gravity_follows_the_closed_form_free_fall(tmp_path):
    g = np.array([0.5, 0.0, -G])
    sim = simulator(tmp_path, "[effects.gravity]\nacceleration_m_s2 = [0.5, 0.0, -9.81]")
    n = 50
    run(sim, n)
    np.testing.assert_allclose(sim.x - sim.rest, np.broadcast_to(g * sim.dt**2 * n * (n + 1) / 2,
                                                                 sim.x.shape), rtol=1e-9)
    np.testing.assert_allclose(velocity(sim)[0, 0], g * n * sim.dt, rtol=1e-9)


def reference_spring_forces(x: np.ndarray, rest: np.ndarray, family: str, k: float) -> np.ndarray:
    """Forces (N) of one spring family, one spring at a time (the slow, obvious reference)."""
    h, w = x.shape[:2]
    forces = np.zeros_like(x)
    for dr, dc in FAMILIES[family]:
        for r in range(h):
            for c in range(w):
                r2, c2 = r + dr, c + dc
                if not (0 <= r2 < h and 0 <= c2 < w):
                    continue
                d = x[r2, c2] - x[r, c]
                length = np.linalg.norm(d)
                natural = np.linalg.norm(rest[r2, c2] - rest[r, c])
                f = k * (length - natural) * d / length  # pulls the two ends together when stretched
                forces[r, c] += f
                forces[r2, c2] -= f
    return forces


@pytest.mark.parametrize("family", ["stretch", "shear", "bend"])
def test_each_spring_family_gives_its_own_forces(tmp_path, family):
    k, density, spacing = 7.0, 0.5, 0.01
    sim = simulator(tmp_path, f"[effects.{family}]\nstiffness_n_m = {k}", width=5, height=4,
                    spacing=spacing, density=density, dt=1e-4)
    rng = np.random.default_rng(3)
    sim.x = sim.rest + rng.normal(scale=2e-3, size=sim.rest.shape)
    sim.x_prev = sim.x.copy()  # at rest: the step moves by F / m dt^2 only
    start = sim.x.copy()
    sim.step()
    mass = density * spacing**2
    expected = start + reference_spring_forces(start, sim.rest, family, k) / mass * sim.dt**2
    np.testing.assert_allclose(sim.x, expected, rtol=0, atol=1e-15)
    assert np.abs(sim.x - start).max() > 1e-9  # the family did act


def test_damping_decays_the_velocity_geometrically(tmp_path):
    c = 20.0
    sim = simulator(tmp_path, f"[effects.damping]\ncoefficient_1_s = {c}", dt=1e-3)
    v0 = np.array([0.3, -0.2, 0.1])
    sim.x_prev = sim.x - v0 * sim.dt
    n = 40
    run(sim, n)
    factor = 1.0 - c * sim.dt
    np.testing.assert_allclose(velocity(sim)[1, 1], v0 * factor**n, rtol=1e-9)
    travelled = v0 * sim.dt * sum(factor**k for k in range(1, n + 1))
    np.testing.assert_allclose(sim.x[1, 1] - sim.rest[1, 1], travelled, rtol=1e-9)
    assert sim.energy()["kinetic"] < 0.5 * sim.mass_kg * 9 * (v0 @ v0)  # it lost energy


def test_wind_drag_pulls_the_velocity_towards_the_wind(tmp_path):
    # v_{k+1} = v_k + drag (w - v_k) dt, so v_N = w (1 - (1 - drag dt)^N) from rest.
    w, drag = np.array([3.0, 1.0, 0.0]), 2.0
    sim = simulator(tmp_path, f"[effects.wind]\nvelocity_m_s = {w.tolist()}\ndrag_1_s = {drag}",
                    dt=1e-3)
    n = 200
    run(sim, n)
    np.testing.assert_allclose(velocity(sim)[2, 0], w * (1 - (1 - drag * sim.dt) ** n), rtol=1e-9)


def test_wind_and_damping_combine_as_one_linear_recurrence(tmp_path):
    w, drag, c = np.array([0.0, -2.0, 1.0]), 3.0, 5.0
    sim = simulator(tmp_path, f"[effects.wind]\nvelocity_m_s = {w.tolist()}\ndrag_1_s = {drag}\n"
                              f"[effects.damping]\ncoefficient_1_s = {c}", dt=1e-3)
    v = np.zeros(3)
    for _ in range(100):
        sim.step()
        v = (1 - c * sim.dt) * v + drag * sim.dt * (w - v)  # independent recurrence
    np.testing.assert_allclose(velocity(sim)[0, 2], v, rtol=1e-9)


def test_pins_hold_exactly_the_declared_vertices_and_nothing_else(tmp_path):
    sim = simulator(tmp_path, '[effects.gravity]\n[effects.pins]\ncorners = ["top-left"]\n'
                              "vertices = [[2, 0]]", width=4, height=3)
    n = 30
    run(sim, n)
    pinned = np.zeros((3, 4), bool)
    pinned[2, 0] = True  # top-left: column 0, row H - 1
    pinned[0, 2] = True  # vertex [column 2, row 0]
    np.testing.assert_array_equal(sim.x[pinned], sim.rest[pinned])
    fall = -G * sim.dt**2 * n * (n + 1) / 2
    np.testing.assert_allclose(sim.x[~pinned][:, 2] - sim.rest[~pinned][:, 2], fall, rtol=1e-9)


# -- energies against their closed forms -------------------------------------------------------


ENERGY_ORIGIN = (0.2, -0.1, 0.5)  # metres, world frame: away from the origin, 0.5 m up


def stretched_3_by_2(dx: float, spacing=0.01) -> tuple[np.ndarray, np.ndarray]:
    """Rest positions of a 3 wide x 2 high "xy" cloth, and the same with its right column
    (column 2) moved by ``dx`` metres along +x."""
    from collider_client.sim.cloth import grid_positions

    rest = grid_positions(3, 2, spacing, np.array(ENERGY_ORIGIN), "xy")
    x = rest.copy()
    x[:, 2, 0] += dx
    return rest, x


@pytest.mark.parametrize("dx", [3e-3, -2e-3])
def test_spring_energy_of_each_family_is_half_k_times_its_stretch_squared(dx):
    from collider_client.sim.cloth import SpringFamily

    s, k = 0.01, 40.0
    rest, x = stretched_3_by_2(dx, s)
    # stretch: the 2 springs from column 1 to column 2 change by dx (column 2's own vertical
    # spring moved as a whole); bend: the 2 springs from column 0 to column 2 likewise; shear:
    # 2 of the 4 diagonals (those ending in column 2) go from s sqrt(2) to sqrt((s + dx)^2 + s^2).
    diagonal = np.hypot(s + dx, s) - s * np.sqrt(2)
    expected = {"stretch": 2 * 0.5 * k * dx**2, "bend": 2 * 0.5 * k * dx**2,
                "shear": 2 * 0.5 * k * diagonal**2}
    for name, energy in expected.items():
        family = SpringFamily(name, rest, k)
        assert family.energy(rest) == 0.0
        assert family.energy(x) == pytest.approx(energy, rel=1e-9), name


def test_simulator_energy_is_kinetic_plus_gravity_plus_springs_in_closed_form(tmp_path):
    s, density, dt, dx = 0.01, 0.5, 2e-4, 3e-3
    sim = simulator(tmp_path, "[effects.gravity]\n[effects.stretch]\nstiffness_n_m = 40.0\n"
                              "[effects.shear]\nstiffness_n_m = 10.0", width=3, height=2,
                    spacing=s, density=density, dt=dt, origin=ENERGY_ORIGIN)
    _, x = stretched_3_by_2(dx, s)
    v = np.array([0.3, -0.2, 0.1])  # m/s, every vertex
    sim.x, sim.x_prev = x, x - v * dt
    m = density * s**2  # kg per vertex
    kinetic = 6 * 0.5 * m * (v @ v)
    gravity = 6 * m * G * ENERGY_ORIGIN[2]  # m g h, zero at the world origin
    springs = 40.0 * dx**2 + 10.0 * (np.hypot(s + dx, s) - s * np.sqrt(2)) ** 2
    energy = sim.energy()
    assert energy == pytest.approx({"kinetic": kinetic, "gravity": gravity, "springs": springs,
                                    "total": kinetic + gravity + springs}, rel=1e-9)


# -- collisions, friction, restitution, moving colliders (exact floor) ---------------------------


def drop_on_floor(tmp_path, client, friction="", height=0.02, steps=200, dt=2e-4, v0=None):
    sim = simulator(tmp_path, f"[effects.gravity]\n[effects.collisions]\neps_m = {EPS}\n{friction}",
                    client=client, colliders=floor_scene(), origin=(-0.005, -0.005, height), dt=dt,
                    width=2, height=2)
    if v0 is not None:
        sim.x_prev = sim.x - np.asarray(v0) * sim.dt
    heights, speeds = [], []
    for _ in range(steps):
        sim.step()
        heights.append(sim.x[..., 2].min())
        speeds.append(velocity(sim)[0, 0].copy())
    return sim, np.array(heights), np.array(speeds)


def test_collisions_keep_the_cloth_at_eps_above_the_floor(tmp_path, client):
    sim, heights, _ = drop_on_floor(tmp_path, client, height=0.01, steps=400)
    assert heights.min() >= EPS - 1e-9  # never below the offset surface after a step
    np.testing.assert_allclose(sim.x[..., 2], EPS, atol=1e-9)  # landed, resting at eps


@pytest.mark.parametrize("restitution", [0.0, 0.5])
def test_restitution_returns_that_fraction_of_the_impact_speed(tmp_path, client, restitution):
    friction = f"[effects.friction]\ncoefficient = 0.0\nrestitution = {restitution}"
    sim, _heights, speeds = drop_on_floor(tmp_path, client, friction, height=0.01, steps=300)
    impact = speeds[:, 2].min()  # most negative vertical speed, just before the contact
    rebound = speeds[np.argmin(speeds[:, 2]):, 2].max()
    assert impact < -0.3
    # One step of gravity (g dt) separates the measured speeds from the instant of contact.
    assert rebound == pytest.approx(-restitution * impact, abs=2 * G * sim.dt + 1e-6)


@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_sliding_friction_decelerates_at_mu_g(tmp_path, client, mu):
    v0 = np.array([0.5, 0.0, 0.0])
    friction = f"[effects.friction]\ncoefficient = {mu}"
    sim = simulator(tmp_path, f"[effects.gravity]\n[effects.collisions]\neps_m = {EPS}\n{friction}",
                    client=client, colliders=floor_scene(), origin=(-0.005, -0.005, EPS), width=2,
                    height=2, dt=1e-4)
    sim.x_prev = sim.x - v0 * sim.dt
    steps = 1000
    run(sim, steps)
    t = steps * sim.dt
    expected_v = max(v0[0] - mu * G * t, 0.0)
    assert velocity(sim)[0, 0, 0] == pytest.approx(expected_v, abs=0.01 * v0[0])
    travelled = sim.x[0, 0, 0] - sim.rest[0, 0, 0]
    expected_x = v0[0] * t - 0.5 * mu * G * t**2
    assert travelled == pytest.approx(expected_x, rel=0.02)


def slope(tmp_path, client, mu: float, theta_deg: float, steps: int, dt=1e-3):
    """A 2 x 2 cloth resting on the floor tilted theta about x, with friction mu."""
    friction = f"[effects.friction]\ncoefficient = {mu}"
    theta = np.radians(theta_deg)
    up = np.array([0.0, -np.sin(theta), np.cos(theta)])  # the tilted floor's normal
    sim = simulator(tmp_path, f"[effects.gravity]\n[effects.collisions]\neps_m = {EPS}\n{friction}",
                    client=client, colliders=floor_scene(rotation=(theta_deg, 0, 0)), width=2,
                    height=2, dt=dt, spacing=0.005)
    # Lay the cloth on the slope, eps above it.
    rot = np.array([[1, 0, 0], [0, np.cos(theta), -np.sin(theta)], [0, np.sin(theta), np.cos(theta)]])
    sim.rest = sim.rest @ rot.T + EPS * up
    sim.x, sim.x_prev = sim.rest.copy(), sim.rest.copy()
    start = sim.x.copy()
    run(sim, steps)
    downhill = np.array([0.0, -np.cos(theta), -np.sin(theta)])
    return (sim.x - start) @ downhill, sim, up


def test_static_friction_holds_below_the_friction_angle(tmp_path, client):
    # 20 deg slope, mu = 0.5 > tan 20 deg = 0.36: the cloth sticks (it crept 0.67 mm in 0.2 s).
    slid, sim, up = slope(tmp_path, client, mu=0.5, theta_deg=20.0, steps=200)
    assert np.abs(slid).max() < 1e-7, slid
    assert np.abs((sim.x - sim.rest) @ up).max() < 1e-6  # and stays on the surface


def test_friction_lets_the_cloth_slide_above_the_friction_angle(tmp_path, client):
    # mu = 0.2 < tan 20 deg: it slides with a = g (sin - mu cos).
    steps, theta = 200, np.radians(20.0)
    slid, sim, _ = slope(tmp_path, client, mu=0.2, theta_deg=20.0, steps=steps)
    t = steps * sim.dt
    expected = 0.5 * G * (np.sin(theta) - 0.2 * np.cos(theta)) * t**2
    np.testing.assert_allclose(slid, expected, rtol=0.03)


def test_a_resting_vertex_neither_jitters_nor_creeps_for_1000_steps(tmp_path, client):
    sim = simulator(tmp_path, f"[effects.gravity]\n[effects.collisions]\neps_m = {EPS}\n"
                              "[effects.friction]\ncoefficient = 0.4",
                    client=client, colliders=floor_scene(), origin=(0.01, 0.02, EPS), width=2,
                    height=2, dt=1e-3)
    track = []
    for _ in range(1000):
        sim.step()
        track.append(sim.x.copy())
    track = np.array(track)
    assert np.abs(track[..., 2] - EPS).max() < 1e-4  # jitter < 0.1 mm (measured 0)
    assert np.abs(track[..., :2] - sim.rest[..., :2]).max() < 1e-9  # no creep


def test_a_moving_collider_carries_the_cloth_resting_on_it(tmp_path, client):
    rise = 0.05  # m/s, the floor moving up
    motion = f'motion = {{ kind = "velocity", velocity_m_s = [0.0, 0.0, {rise}] }}'
    sim = simulator(tmp_path, f"[effects.gravity]\n[effects.collisions]\neps_m = {EPS}",
                    client=client, colliders=floor_scene(motion=motion), origin=(0.0, 0.0, EPS),
                    width=2, height=2, dt=1e-3)
    run(sim, 200)
    floor_top = rise * sim.t
    np.testing.assert_allclose(sim.x[..., 2], floor_top + EPS, atol=1e-4)
    np.testing.assert_allclose(velocity(sim)[..., 2], rise, rtol=0.05)


# -- 16. fast vertices and fast colliders against a thin plate -------------------------------------


def shoot_at_plate(client, speed: float, dt: float, check_step=True, plate_speed=0.0):
    """One vertex 5 mm above a 0.2 mm plate moving towards it (or the plate moving up towards the
    vertex); returns its height above the plate's top after the passage, metres."""
    t0 = 0.0
    plate = ColliderPlacement("plate", lambda t: np.array(
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, plate_speed * t], [0, 0, 0, 1.0]]))
    hook = CollisionHook(client, [plate], eps=EPS, check_step=check_step)
    x = np.array([[0.01, 0.02, 0.005]])
    v = np.array([[0.0, 0.0, -speed]])
    t = t0
    for _ in range(int(round(0.02 / (max(speed, plate_speed) * dt))) + 2):
        t += dt
        x = x + v * dt
        x, v, _ = hook.apply(x, v, t, dt)
    return float(x[0, 2] - plate_speed * t)


@pytest.mark.parametrize("steps_per_eps", [0.5, 4.0, 30.0])
def test_fast_vertices_do_not_tunnel_through_a_thin_plate(client, steps_per_eps):
    dt = 1e-3
    speed = steps_per_eps * EPS / dt  # speed x dt = steps_per_eps x eps, plate 0.2 mm thick
    assert shoot_at_plate(client, speed, dt) > 0.5 * EPS


def test_without_the_step_check_a_fast_vertex_does_tunnel(client):
    # The limit, shown: speed x dt = 4 eps and no sub-checks: the vertex ends below the plate.
    assert shoot_at_plate(client, 4.0, 1e-3, check_step=False) < -PLATE_THICKNESS


def test_a_fast_moving_plate_does_not_pass_through_a_vertex(client):
    assert shoot_at_plate(client, 0.0, 1e-3, plate_speed=3.0) > 0.5 * EPS


def test_beyond_the_substep_limit_the_hook_refuses(client):
    from collider_client.response import TunnellingError

    with pytest.raises(TunnellingError, match="speed x dt below eps"):
        shoot_at_plate(client, 200.0, 1e-3)


# -- blow-ups are refused before or stopped at the first bad step ----------------------------------


def test_damping_beyond_its_stability_limit_is_refused_before_the_run(tmp_path):
    with pytest.raises(SceneError, match=r"damping.coefficient_1_s \+ effects.wind.drag_1_s = 50000 .*"
                                         r"dt_s <= 2e-05"):
        load_scene(write_scene(tmp_path, "[effects.damping]\ncoefficient_1_s = 50000", dt=1e-4))
    with pytest.raises(SceneError, match="dt_s <= 0.0005"):
        load_scene(write_scene(tmp_path, "[effects.wind]\nvelocity_m_s = [1, 0, 0]\ndrag_1_s = 1500\n"
                                         "[effects.damping]\ncoefficient_1_s = 500", dt=1e-3))
    load_scene(write_scene(tmp_path, "[effects.damping]\ncoefficient_1_s = 500", dt=2e-3))  # limit


def test_a_runaway_state_stops_the_run_at_its_first_step(tmp_path):
    sim = simulator(tmp_path, "[effects.gravity]", dt=1e-3)
    sim.x_prev = sim.x - np.array([0.0, 0.0, 100.0])  # 100 m in one step: far beyond the cloth
    with pytest.raises(SimulationError, match="blew up at step 1 .*moved 100 m in one step"):
        sim.step()
    sim = simulator(tmp_path, "[effects.gravity]", dt=1e-3)
    sim.x[1, 1, 0] = np.nan
    with pytest.raises(SimulationError, match="non-finite"):
        sim.step()


# -- 17. a long run, shortened: drape on a voxel bunny ------------------------------------------


@pytest.mark.slow
def test_drape_on_a_voxel_bunny_stays_finite_bounded_and_outside(tmp_path, load_shared_mesh):
    """The paper's drape, coarsened (40 x 40 vertices 6 mm apart, 0.25 s): no NaN, the energy
    never rises above its start, no vertex deeper than 0.1 mm inside the exact mesh at any frame.
    The full 5 s run is ``benchmarks/long_drape.py`` (README, hard cases)."""
    from collider_client.sim.motion import pose_function
    from collider_client.sim.scene import SCENES_DIR
    from collider_server.engine.meshes import ExactSDF
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider

    mesh = load_shared_mesh("stanford-bunny.obj")
    save_collider(bake_collider(mesh, "voxel", "bunny", resolution=64, show_progress=False),
                  tmp_path / "models" / "bunny.safetensors")
    scene = load_scene(SCENES_DIR / "drape_bunny.toml")
    scene.cloth.width = scene.cloth.height = 40
    scene.cloth.spacing_m = 6e-3
    scene.cloth.origin_m = np.array([-0.117, -0.1, 0.20])
    exact = ExactSDF(mesh)
    pose = pose_function(scene.colliders[0])(0.0)
    with cc.Client(models=tmp_path / "models", device="cpu") as client:
        sim = Simulator(scene, client, {m.name: m for m in client.list_models()})
        start = sim.energy()["total"]
        deepest, energies = 0.0, []
        for i in range(1, 1251):
            sim.step()
            if i % 50 == 0:
                energies.append(sim.energy()["total"])
                local = (sim.vertices - pose[:3, 3]) @ pose[:3, :3]
                deepest = max(deepest, float(-exact.signed_distance(local).min()))
    assert np.isfinite(sim.x).all()
    assert sim.hook.stats.colliding_max > 20  # it did drape over the bunny (measured 48)
    assert max(energies) <= start + 1e-9, (start, max(energies))
    assert deepest < 1e-4, deepest


# -- what a run refuses before it starts, and what it writes -----------------------------------------


def cli(*args, timeout=300):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "collider_cli", "simulate", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def test_cli_blow_up_through_damping_exits_non_zero_before_the_run(tmp_path):
    # The run: damping 50,000 1/s at dt 1e-4 s exited 0 with inf in the PC2.
    path = write_scene(tmp_path, "[effects.gravity]\n[effects.damping]\ncoefficient_1_s = 50000",
                       dt=1e-4, duration=0.01)
    out = cli(path, "--no-preview", "--quiet", "--output", tmp_path / "out")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "unstable" in out.stderr and "dt_s <= 2e-05" in out.stderr
    assert not (tmp_path / "out").exists()


def test_cli_check_mesh_of_an_unused_model_is_refused_before_the_run(tmp_path, box_models):
    path = write_scene(tmp_path, f"[effects.gravity]\n[effects.collisions]\neps_m = {EPS}",
                       colliders=floor_scene(), origin=(0, 0, 0.01), duration=0.01)
    mesh = tmp_path / "m.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    out = cli(path, "--models", box_models, "--check-mesh", f"plate={mesh}", "--quiet",
              "--output", tmp_path / "out")
    assert out.returncode == 2 and "['plate'] that the scene does not use" in out.stderr
    assert not (tmp_path / "out" / "case.pc2").exists()  # refused before anything ran


def test_cli_without_preview_does_not_claim_a_png(tmp_path):
    path = write_scene(tmp_path, "[effects.gravity]", duration=0.01)
    out = cli(path, "--no-preview", "--quiet", "--output", tmp_path / "out")
    assert out.returncode == 0, out.stderr
    assert ".png" not in out.stdout and not (tmp_path / "out" / "case.png").exists()
    assert "case.obj, .pc2, .report.json" in out.stdout


def test_a_huge_cloth_is_estimated_warned_about_and_refused_where_it_cannot_fit(tmp_path, capsys,
                                                                             monkeypatch):
    from collider_client.sim import run as run_module

    scene = load_scene(write_scene(tmp_path, "[effects.gravity]", width=4096, height=4096,
                                   spacing=1e-3, dt=1e-3, duration=0.1))
    need = run_module.resource_estimate(scene, scene.steps)
    assert need["memory"] == 4096 * 4096 * run_module.STATE_BYTES_PER_VERTEX  # 6.4 GB
    assert need["pc2"] == 32 + (100 // 10 + 2) * 4096 * 4096 * 12
    monkeypatch.setattr(run_module, "_physical_memory", lambda: 64 * 2**30)
    run_module.check_resources(scene, scene.steps)
    assert "4096 x 4096 cloth: about 6.0 GiB of memory" in capsys.readouterr().err
    monkeypatch.setattr(run_module, "_physical_memory", lambda: 4 * 2**30)  # a small machine
    with pytest.raises(ValueError, match="needs about 6.0 GiB of memory"):
        run_module.check_resources(scene, scene.steps)


def test_frames_are_streamed_to_the_pc2_file(tmp_path):
    from collider_client.sim.output import PC2Frames
    from collider_client.sim.run import run_scene
    from collider_contract.point_cache import read_pc2

    scene = load_scene(write_scene(tmp_path, "[effects.gravity]", duration=0.05))
    report, frames = run_scene(scene, None, tmp_path / "out", show_progress=False, preview=False)
    assert isinstance(frames, PC2Frames) and len(frames) == report.frames == 6
    stored = read_pc2(tmp_path / "out" / "case.pc2")
    for (t, vertices), expected in zip(frames, stored):
        np.testing.assert_array_equal(vertices, expected)
    assert frames[-1][0] == pytest.approx(0.05)


def test_newton_style_placement_takes_a_fixed_matrix(client):
    pose = np.eye(4)
    pose[2, 3] = 0.5  # the floor raised by 0.5 m
    hook = CollisionHook(client, [ColliderPlacement("floor", pose)], eps=EPS)
    positions, _, mask = hook.apply(np.array([[0.0, 0.0, 0.4995]]), np.zeros((1, 3)), 0.1, 1e-3)
    assert mask.all()
    np.testing.assert_allclose(positions[0, 2], 0.5 + EPS, atol=1e-9)
    with pytest.raises(ValueError, match="finite 4x4"):
        ColliderPlacement("floor", np.eye(3))


# -- the step's declared effects, pins against contacts, the blow-up check and its message -------


def test_every_declared_effect_is_listed_in_step_order_and_configures_the_hook(tmp_path, client):
    springs = "".join(f"[effects.{n}]\nstiffness_n_m = 1.0\n" for n in ("stretch", "shear", "bend"))
    effects = (f"[effects.gravity]\n{springs}[effects.wind]\nvelocity_m_s = [1, 0, 0]\n"
               "[effects.damping]\ncoefficient_1_s = 2.0\n[effects.pins]\ncorners = ['top-left']\n"
               f"[effects.collisions]\neps_m = 2e-3\n")
    sim = simulator(tmp_path, effects + "[effects.friction]\ncoefficient = 0.4\nrestitution = 0.3",
                    client=client, colliders=floor_scene(), dt=1e-4)
    assert sim.effects == ["gravity", "stretch", "shear", "bend", "wind", "damping", "pins",
                           "collisions", "friction"]
    assert (sim.hook.eps, sim.hook.friction, sim.hook.restitution) == (2e-3, 0.4, 0.3)
    sim = simulator(tmp_path, effects, client=client, colliders=floor_scene(), dt=1e-4)
    assert sim.effects[-1] == "collisions"  # no friction: the contact keeps the collider's velocity
    assert (sim.hook.friction, sim.hook.restitution) == (None, 0.0)


def test_a_scene_with_colliders_and_no_client_is_refused(tmp_path):
    path = write_scene(tmp_path, f"[effects.gravity]\n[effects.collisions]\neps_m = {EPS}",
                       colliders=floor_scene())
    with pytest.raises(ValueError, match=f"^{re.escape(str(path))}: the scene has colliders; a "
                                         "client is needed$"):
        Simulator(load_scene(path), None)


def test_pins_at_the_four_corners_hold_exactly_those(tmp_path):
    sim = simulator(tmp_path, "[effects.gravity]\n[effects.pins]\ncorners = ['bottom-left', "
                              "'bottom-right', 'top-left', 'top-right']", width=4, height=3)
    run(sim, 10)
    pinned = np.zeros((3, 4), bool)
    pinned[[0, 0, 2, 2], [0, 3, 0, 3]] = True  # rows 0 and H - 1, columns 0 and W - 1
    np.testing.assert_array_equal(sim.x[pinned], sim.rest[pinned])
    assert (sim.x[~pinned][:, 2] < sim.rest[~pinned][:, 2]).all()  # every other vertex fell


def test_a_pin_wins_over_the_contact_and_colliding_is_the_last_steps_mask(tmp_path, client):
    """A 3 x 3 cloth 0.5 mm above the floor, inside eps (1 mm): the contact lifts every vertex to
    eps, except the pinned bottom-left one, which stays where it was pinned, at rest."""
    sim = simulator(tmp_path, f"[effects.gravity]\n[effects.pins]\ncorners = ['bottom-left']\n"
                              f"[effects.collisions]\neps_m = {EPS}", client=client,
                    colliders=floor_scene(), origin=(0.0, 0.0, 5e-4))
    assert sim.colliding is None  # nothing to show before the first step
    started, sums = time.perf_counter(), []
    for _ in range(8):
        sim.step()
        sums.append((sim.timings.integration_s, sim.timings.collision_s, sim.timings.query_s))
    elapsed = time.perf_counter() - started
    assert (np.diff(sums, axis=0) > 0).all()  # each step adds its own time to each sum
    np.testing.assert_array_equal(sim.x[0, 0], sim.rest[0, 0])
    np.testing.assert_array_equal(sim.x_prev[0, 0], sim.rest[0, 0])  # no velocity either
    np.testing.assert_allclose(sim.x[..., 2].ravel()[1:], EPS, atol=1e-9)
    assert sim.colliding.shape == (9,) and sim.colliding.all()
    # The time spent: all of the hook's query time, and the rest split, within the steps' time.
    t = sim.timings
    assert t.query_s == pytest.approx(sim.hook.stats.query_s, rel=1e-9) and t.query_s > 0.0
    assert t.integration_s > 0.0 and t.collision_s > 0.0
    assert t.integration_s + t.collision_s + t.query_s <= elapsed
    lifted = sim.rest + np.array([0.0, 0.0, 0.5])  # all but the pinned vertex far above the floor
    lifted[0, 0] = sim.rest[0, 0]
    sim.x, sim.x_prev = lifted, lifted.copy()
    sim.step()
    np.testing.assert_array_equal(sim.colliding, np.arange(9) == 0)  # this step's contacts only


def test_a_vertex_moving_farther_than_the_cloth_diagonal_stops_the_run_and_says_where(tmp_path):
    # A 4 x 3 cloth 1 cm apart: its rest diagonal is hypot(3, 2) cm = 0.0361 m. No forces, so each
    # step moves every vertex by exactly x - x_prev.
    path = write_scene(tmp_path, "[effects.gravity]\nacceleration_m_s2 = [0, 0, 0]", width=4,
                       height=3, dt=1e-3)
    sim = Simulator(load_scene(path))
    sim.x_prev = sim.x - np.array([0.0360, 0.0, 0.0])  # just within the diagonal: two steps run
    run(sim, 2)
    sim.x_prev = sim.x - np.array([0.0, 0.0365, 0.0])
    with pytest.raises(SimulationError, match=f"^{re.escape(str(path))}: the cloth blew up at step "
                       r"3 \(t = 0\.003 s\): a vertex moved 0\.0365 m in one step, more than the "
                       r"cloth's size \(0\.0361 m\); lower scene\.dt_s, the spring stiffness, the "
                       "damping or the wind drag$"):
        sim.step()
    sim = Simulator(load_scene(path))
    sim.x[2, 3, 1] = np.nan
    with pytest.raises(SimulationError, match=f"^{re.escape(str(path))}: the cloth blew up at step "
                       r"1 \(t = 0\.001 s\): a position became non-finite; lower scene\.dt_s, "):
        sim.step()


def test_wind_adds_its_drag_to_gravity(tmp_path):
    # v_{k+1} = v_k + (g + drag (w - v_k)) dt from rest, every vertex (no springs).
    w, drag = np.array([2.0, 0.0, 0.0]), 4.0
    sim = simulator(tmp_path, f"[effects.gravity]\n[effects.wind]\nvelocity_m_s = {w.tolist()}\n"
                              f"drag_1_s = {drag}", dt=1e-3)
    v, g = np.zeros(3), np.array([0.0, 0.0, -G])
    for _ in range(50):
        sim.step()
        v = v + (g + drag * (w - v)) * sim.dt
    np.testing.assert_allclose(velocity(sim)[1, 2], v, rtol=1e-9)


class _ListingRefused:
    """The real client, except that listing its models fails: the simulator must use the model
    infos it was handed instead of asking again (one round trip less for a remote client)."""

    def __init__(self, client):
        self._client = client

    def __getattr__(self, name):
        return getattr(self._client, name)

    def list_models(self):
        raise AssertionError("list_models called although the model infos were given")


def test_the_simulator_uses_the_model_infos_it_is_given(tmp_path, client):
    path = write_scene(tmp_path, f"[effects.gravity]\n[effects.collisions]\neps_m = {EPS}",
                       colliders=floor_scene(), origin=(0.0, 0.0, 5e-4))
    infos = {m.name: m for m in client.list_models()}
    sim = Simulator(load_scene(path), _ListingRefused(client), infos)
    sim.step()
    np.testing.assert_allclose(sim.x[..., 2], EPS, atol=1e-9)
