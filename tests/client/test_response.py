"""Collision response helpers on analytic cases: a plane, a sphere, Coulomb friction sticking
below and sliding above its threshold, restitution, moving colliders. World frame, metres, m/s."""

from __future__ import annotations

import time

import numpy as np
import pytest

from collider_client import (
    ColliderPlacement,
    CollisionHook,
    collider_velocity,
    project_to_contacts,
    respond_velocities,
)
from collider_client.response import TunnellingError, world_box
from collider_contract import ModelInfo

UP = np.array([[0.0, 0.0, 1.0]])


def test_plane_projection_to_offset_surface():
    # Plane z = 0, eps 1 mm: contact = p + (eps - d) n with d = z.
    eps = 1e-3
    points = np.array([[0.1, 0.2, -0.004], [0.0, 0.0, 0.0005], [0.3, 0.1, 0.01]])
    d = points[:, 2]
    contact = points + (eps - d)[:, None] * UP
    moved = project_to_contacts(points, contact, d < eps)
    np.testing.assert_allclose(moved[:2, 2], eps)
    np.testing.assert_allclose(moved[:2, :2], points[:2, :2])  # no tangential drift
    np.testing.assert_array_equal(moved[2], points[2])          # not colliding: untouched


def test_sphere_projection_lands_on_the_offset_sphere():
    rng = np.random.default_rng(3)
    radius, eps = 0.1, 1e-3
    p = rng.normal(size=(200, 3))
    p = p / np.linalg.norm(p, axis=1, keepdims=True) * rng.uniform(0.05, 0.12, (200, 1))
    d = np.linalg.norm(p, axis=1) - radius
    n = p / np.linalg.norm(p, axis=1, keepdims=True)
    moved = project_to_contacts(p, p + (eps - d)[:, None] * n, d < eps)
    r = np.linalg.norm(moved, axis=1)
    np.testing.assert_allclose(r[d < eps], radius + eps, atol=1e-12)
    np.testing.assert_allclose(r[d >= eps], np.linalg.norm(p[d >= eps], axis=1))


def test_normal_velocity_into_plane_is_removed():
    v = np.array([[0.3, -0.2, -2.0]])
    out = respond_velocities(v, UP, np.array([True]), friction=0.0)
    np.testing.assert_allclose(out, [[0.3, -0.2, 0.0]])


def test_separating_velocity_is_kept():
    v = np.array([[0.3, 0.0, 1.0]])
    out = respond_velocities(v, UP, np.array([True]), friction=0.9)
    np.testing.assert_allclose(out, v)


@pytest.mark.parametrize("tangential, mu, expected", [
    (0.5, 0.6, 0.0),    # |v_t| = 0.5 <= mu |dv_n| = 0.6: sticks
    (0.5, 0.5, 0.0),    # exactly at the threshold: sticks
    (0.5, 0.3, 0.2),    # above: slides, slowed by mu |dv_n| = 0.3
    (2.0, 0.25, 1.75),
])
def test_coulomb_friction_sticks_below_and_slides_above_threshold(tangential, mu, expected):
    v = np.array([[tangential, 0.0, -1.0]])
    out = respond_velocities(v, UP, np.array([True]), friction=mu)
    np.testing.assert_allclose(out, [[expected, 0.0, 0.0]], atol=1e-12)


def test_restitution_reflects_part_of_the_normal_velocity():
    v = np.array([[0.0, 0.0, -2.0]])
    out = respond_velocities(v, UP, np.array([True]), restitution=0.5)
    np.testing.assert_allclose(out, [[0.0, 0.0, 1.0]])
    # Friction grows with the normal impulse (1 + e) |v_n| = 3: tangential 2.5 sticks at mu = 1.
    v = np.array([[2.5, 0.0, -2.0]])
    out = respond_velocities(v, UP, np.array([True]), friction=1.0, restitution=0.5)
    np.testing.assert_allclose(out, [[0.0, 0.0, 1.0]], atol=1e-12)


def test_sphere_normals_and_mask():
    p = np.array([[0.0, 0.0, 0.099], [0.2, 0.0, 0.0]])
    n = p / np.linalg.norm(p, axis=1, keepdims=True)
    v = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])
    out = respond_velocities(v, n, np.array([True, False]))
    np.testing.assert_allclose(out, [[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])


def test_moving_collider_relative_velocity():
    # Plane moving up at 1 m/s; a resting point in contact is carried along (sticking friction).
    v = np.array([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0]])
    vc = np.array([0.0, 0.0, 1.0])
    out = respond_velocities(v, np.repeat(UP, 2, 0), np.array([True, True]), friction=1.0,
                             collider_velocity=vc)
    np.testing.assert_allclose(out, [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], atol=1e-12)
    # Frictionless: the tangential velocity stays, the normal one matches the plane's.
    out = respond_velocities(v, np.repeat(UP, 2, 0), np.array([True, True]), friction=0.0,
                             collider_velocity=vc)
    np.testing.assert_allclose(out, [[0.0, 0.0, 1.0], [0.4, 0.0, 1.0]], atol=1e-12)


def test_collider_velocity_from_poses():
    dt = 1e-3
    before, after = np.eye(4), np.eye(4)
    after[:3, 3] = [0.002, 0.0, -0.001]  # translation 2 mm, -1 mm in 1 ms
    pts = np.array([[0.1, 0.2, 0.3], [-1.0, 0.0, 0.0]])
    np.testing.assert_allclose(collider_velocity(before, after, pts, dt), [[2.0, 0.0, -1.0]] * 2)
    # Rotation about z at omega rad/s: v = omega x r.
    omega = 2.0
    c, s = np.cos(omega * dt), np.sin(omega * dt)
    after = np.eye(4)
    after[:2, :2] = [[c, -s], [s, c]]
    v = collider_velocity(np.eye(4), after, np.array([[1.0, 0.0, 0.0]]), dt)
    np.testing.assert_allclose(v, [[0.0, omega, 0.0]], atol=2e-3)
    with pytest.raises(ValueError, match="dt"):
        collider_velocity(before, after, pts, 0.0)


def test_collider_velocity_keeps_float32_poses_accurate():
    # A float32 pose (as a float32 simulator gives it), rotating 2 rad/s about z: the velocity is
    # that of the same poses in float64, not one spoiled by a float32 inverse (1e-7 / dt).
    dt, omega = 1e-3, 2.0
    c, s = np.cos(omega * dt), np.sin(omega * dt)
    after = np.eye(4, dtype=np.float32)
    after[:2, :2] = [[c, -s], [s, c]]
    after[:3, 3] = [0.3, -0.1, 0.2]
    before = np.eye(4, dtype=np.float32)
    before[:3, 3] = [0.3, -0.1, 0.2]
    points = np.array([[1.0, 0.5, 0.0], [-0.4, 2.0, 1.0]])
    expected = collider_velocity(before.astype(np.float64), after.astype(np.float64), points, dt)
    np.testing.assert_allclose(collider_velocity(before, after, points, dt), expected, atol=1e-9)


def test_bad_coefficients_are_rejected():
    with pytest.raises(ValueError, match="friction"):
        respond_velocities(np.zeros((1, 3)), UP, np.array([True]), friction=-0.1)
    with pytest.raises(ValueError, match="restitution"):
        respond_velocities(np.zeros((1, 3)), UP, np.array([True]), restitution=1.5)


def test_world_box_moves_with_the_pose():
    info = ModelInfo("m", "voxel", domain_min=np.array([-1.0, -2.0, -3.0]),
                     domain_max=np.array([1.0, 2.0, 3.0]))
    lo, hi = world_box(info, None, 0.5)
    np.testing.assert_allclose(lo, [-1.5, -2.5, -3.5])
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # +90 deg about x: y -> z
    pose[:3, 3] = [10, 0, 0]
    lo, hi = world_box(info, pose, 0.0)
    np.testing.assert_allclose(lo, [9, -3, -2])
    np.testing.assert_allclose(hi, [11, 3, 2])


def test_hook_against_embedded_sphere(models_dir):
    """The hook pushes points out of a real (voxel) sphere, sends only the near ones and asks
    only for the fields its response needs."""
    import collider_client as cc

    rng = np.random.default_rng(0)
    near = rng.normal(size=(300, 3))
    near = near / np.linalg.norm(near, axis=1, keepdims=True) * 0.098  # 2 mm inside
    far = rng.uniform(5.0, 6.0, size=(100, 3))                         # outside every box
    points = np.concatenate([near, far])
    velocities = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    with cc.Client(models=models_dir, device="cpu") as client:
        sticky = CollisionHook(client, [ColliderPlacement("sphere")], eps=1e-3)
        assert sticky.fields == ["distance", "contact", "collides"]  # no normals without friction
        assert sticky.only_colliding
        pos, vel, mask = sticky.apply(points, velocities, t=0.0, dt=1e-3)
        assert sticky.stats.points_sent == 300 and sticky.stats.points_total == 400
        assert mask[:300].all() and not mask[300:].any()
        r = np.linalg.norm(pos[:300], axis=1)
        assert np.abs(r - 0.101).max() < 2e-3      # on the offset surface (voxel accuracy)
        np.testing.assert_array_equal(vel[:300], 0.0)  # static collider, sticky: stopped
        np.testing.assert_array_equal(pos[300:], points[300:])
        slide = CollisionHook(client, [ColliderPlacement("sphere")], eps=1e-3, friction=0.0)
        assert slide.fields == ["distance", "contact", "collides", "normal"]
        _, vel, _ = slide.apply(points, velocities, t=0.0, dt=1e-3)
        normals = near / 0.098
        inward = np.einsum("ij,ij->i", vel[:300], normals)
        assert inward.min() > -0.05  # no velocity left into the sphere (up to voxel normals)
        with pytest.raises(ValueError, match="unknown model"):
            CollisionHook(client, [ColliderPlacement("nope")])


# -- the helpers' edges: defaults, dtypes, inputs left alone ----------------------------------------


def test_respond_velocities_defaults_to_frictionless_and_inelastic():
    v = np.array([[0.3, -0.2, -2.0]])
    np.testing.assert_allclose(respond_velocities(v, UP, np.array([True])), [[0.3, -0.2, 0.0]])


def test_fully_elastic_restitution_is_accepted_and_reflects_the_normal_velocity():
    v = np.array([[0.5, 0.0, -2.0]])
    out = respond_velocities(v, UP, np.array([True]), restitution=1.0)
    np.testing.assert_allclose(out, [[0.5, 0.0, 2.0]])


def test_slowly_separating_points_keep_their_velocity():
    # u_n = +0.5 m/s (< 1): separating, however slowly; friction must not touch it either.
    v = np.array([[0.2, 0.0, 0.5]])
    out = respond_velocities(v, UP, np.array([True]), friction=0.8, restitution=0.5)
    np.testing.assert_array_equal(out, v)


def test_integer_velocities_give_exact_fractional_responses():
    # Velocities given as integers (m/s): the response (-0.25 x -2 = 0.5 m/s) is not truncated.
    out = respond_velocities(np.array([[0, 0, -2]]), UP, np.array([True]), restitution=0.25)
    np.testing.assert_allclose(out, [[0.0, 0.0, 0.5]])


def test_a_head_on_contact_without_tangential_velocity_raises_no_numpy_warning():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a 0/0 in Coulomb's shrink factor would warn
        out = respond_velocities(np.array([[0.0, 0.0, -1.0]]), UP, np.array([True]), friction=0.0)
    np.testing.assert_array_equal(out, [[0.0, 0.0, 0.0]])


def test_unit_rows_keeps_zero_rows_zero_without_warning():
    import warnings

    from collider_client.physics import unit_rows

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = unit_rows(np.array([[0.0, 0.0, 0.0], [0.0, 3.0, 4.0]]))
    np.testing.assert_allclose(out, [[0.0, 0.0, 0.0], [0.0, 0.6, 0.8]])


def test_project_to_contacts_leaves_its_input_alone_and_keeps_float32():
    positions = np.array([[0.0, 0.0, -0.002], [0.1, 0.0, 0.5]])
    before = positions.copy()
    contact = np.array([[0.0, 0.0, 0.001], [9.0, 9.0, 9.0]])
    out = project_to_contacts(positions, contact, np.array([True, False]))
    np.testing.assert_array_equal(positions, before)  # a new array, not the input edited
    np.testing.assert_array_equal(out, [[0.0, 0.0, 0.001], [0.1, 0.0, 0.5]])
    single = project_to_contacts(positions.astype(np.float32), contact, np.array([True, False]))
    assert single.dtype == np.float32  # a float32 simulator gets float32 back
    # Integer positions (a grid in whole metres) are not truncated on the way out.
    out = project_to_contacts(np.array([[0, 0, -1], [2, 3, 4]]), contact, np.array([True, False]))
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, [[0.0, 0.0, 0.001], [2.0, 3.0, 4.0]])


def test_world_box_grows_both_sides_by_the_margin():
    info = ModelInfo("m", "voxel", domain_min=np.array([-1.0, -2.0, -3.0]),
                     domain_max=np.array([1.0, 2.0, 3.0]))
    lo, hi = world_box(info, None, 0.25)
    np.testing.assert_allclose(lo, [-1.25, -2.25, -3.25])
    np.testing.assert_allclose(hi, [1.25, 2.25, 3.25])


def test_placement_static_flag_and_float_poses():
    assert ColliderPlacement("m").static is True
    fixed = ColliderPlacement("m", [[1, 0, 0, 0], [0, 1, 0, 2], [0, 0, 1, 0], [0, 0, 0, 1]])
    assert fixed.static is True
    assert fixed.pose(3.0).dtype == np.float64
    np.testing.assert_array_equal(fixed.pose(3.0)[:3, 3], [0.0, 2.0, 0.0])
    moving = ColliderPlacement("m", lambda t: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, t], [0, 0, 0, 1]])
    assert moving.static is False
    assert moving.pose(1).dtype == np.float64


# -- the hook's substep count and collider moves, closed forms (no queries) ------------------------


BOX = ModelInfo("box", "mesh", domain_min=np.array([-0.1, -0.5, -0.9]),
                domain_max=np.array([0.2, 0.3, 0.7]))


def _hook(colliders, **kwargs):
    """A hook that only computes (no query is sent): the model's domain box given as ``infos``."""
    return CollisionHook(None, colliders, infos={"box": BOX}, **kwargs)


def _pose_at(t: float) -> np.ndarray:
    """Rotation about z by 5 t rad, translation (0.1 + 0.3 t^2, -0.2, 0.05 t) m: accelerating."""
    c, s = np.cos(5.0 * t), np.sin(5.0 * t)
    return np.array([[c, -s, 0, 0.1 + 0.3 * t * t], [s, c, 0, -0.2], [0, 0, 1, 0.05 * t],
                     [0, 0, 0, 1.0]])


def test_collider_moves_is_the_largest_corner_displacement_over_the_step():
    t, dt = 1.0, 0.1
    hook = _hook([ColliderPlacement("box"), ColliderPlacement("box", np.eye(4)),
                  ColliderPlacement("box", _pose_at)])
    corners = np.array([[x, y, z] for x in (-0.1, 0.2) for y in (-0.5, 0.3) for z in (-0.9, 0.7)])

    def world(pose):
        return corners @ pose[:3, :3].T + pose[:3, 3]

    expected = np.linalg.norm(world(_pose_at(t)) - world(_pose_at(t - dt)), axis=1).max()
    poses = [np.eye(4), np.eye(4), _pose_at(t)]
    moves = hook.collider_moves(poses, t, dt)
    assert moves[:2] == [0.0, 0.0]  # static ones
    assert moves[2] == pytest.approx(expected, rel=1e-12)


def test_substeps_is_floor_of_relative_displacement_over_eps_plus_one():
    hook = _hook([ColliderPlacement("box")], eps=1e-3)
    v = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 4.0], [0.0, 0.0, 100.0]])  # m/s; the last not near
    # own: the fastest near point, 5 m/s x 1 ms = 5 mm; the collider 2.5 mm: 7.5 eps -> 8 checks.
    assert hook.substeps(v, np.array([0, 1]), [0.0, 2.5e-3], 0.0, 1e-3) == 8
    # No near point: the collider's move alone, 2.5 eps -> 3.
    assert hook.substeps(v, np.array([], dtype=int), [2.5e-3], 0.0, 1e-3) == 3
    # Slow (0.3 mm a step) and no collider move: a single check.
    assert hook.substeps(np.array([[0.3, 0.0, 0.0]]), np.array([0]), [], 0.0, 1e-3) == 1
    # 63.5 eps: 64 checks, the most allowed; 64.5 eps is refused.
    assert hook.substeps(np.array([[63.5, 0.0, 0.0]]), np.array([0]), [0.0], 0.0, 1e-3) == 64
    with pytest.raises(TunnellingError):
        hook.substeps(np.array([[64.5, 0.0, 0.0]]), np.array([0]), [0.0], 0.0, 1e-3)


def test_substeps_refusal_messages_give_the_numbers():
    hook = _hook([ColliderPlacement("box")], eps=0.001994)
    with pytest.raises(TunnellingError) as caught:
        hook.substeps(np.array([[56.7, 0.0, 0.0]]), np.array([0]), [0.0797], 0.25, 1e-3)
    assert str(caught.value) == (
        "at t = 0.25 s a point near a collider moved 136 mm relative to it in one step (56.7 mm "
        "itself at 56.7 m/s, 79.7 mm the collider's surface): more than 64 x eps = 1.99 mm, it could "
        "pass through a thin feature unseen. Keep speed x dt below eps: lower dt or raise eps")
    with pytest.raises(TunnellingError, match=r"^at t = 0.5 s a point near a collider has a "
                                              r"non-finite velocity$"):
        hook.substeps(np.array([[np.nan, 0.0, 0.0]]), np.array([0]), [0.0], 0.5, 1e-3)


def test_hook_arguments_are_checked():
    with pytest.raises(ValueError, match="^eps must be > 0, got 0.0$"):
        _hook([ColliderPlacement("box")], eps=0.0)
    with pytest.raises(ValueError, match="^CollisionHook needs at least one collider$"):
        _hook([])
    hook = _hook([ColliderPlacement("box")], friction=0.3)
    assert hook.eps == 1e-3 and hook.restitution == 0.0 and hook.check_step
    assert hook.stats.fields == hook.fields == ["distance", "contact", "collides", "normal"]


# -- the hook against exact boxes: responses in closed form ----------------------------------------


def _box_mesh(extents, centre, name):
    import trimesh

    from collider_server.engine.meshes import Mesh

    box = trimesh.creation.box(extents=extents)
    return Mesh(np.asarray(box.vertices) + np.asarray(centre, float), np.asarray(box.faces), name)


@pytest.fixture(scope="module")
def exact_client(tmp_path_factory):
    """Embedded client over exact (``mesh`` kind) boxes, metres: ``floor`` 1 x 1 x 0.1 m, top face
    at z = 0; ``plate`` 0.3 x 0.3 m, 0.2 mm thick, faces at z = 0 and z = -0.2 mm."""
    pytest.importorskip("collider_server")
    import collider_client as cc
    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider

    root = tmp_path_factory.mktemp("exact")
    for name, mesh in {"floor": _box_mesh((1.0, 1.0, 0.1), (0, 0, -0.05), "floor"),
                       "plate": _box_mesh((0.3, 0.3, 2e-4), (0, 0, -1e-4), "plate")}.items():
        save_collider(bake_collider(mesh, "mesh", name, show_progress=False), root / f"{name}.safetensors")
    with cc.Client(models=root, device="cpu") as client:
        yield client


class Recorder:
    """The real client, logging what the hook asks of it: (method, colliders, n points, options)."""

    def __init__(self, client):
        self.client, self.calls = client, []

    def list_models(self):
        return self.client.list_models()

    def query(self, model, points, **options):
        self.calls.append(("query", model, len(points), options))
        return self.client.query(model, points, **options)

    def scene_query(self, colliders, points, **options):
        self.calls.append(("scene_query", colliders, len(points), options))
        return self.client.scene_query(colliders, points, **options)


def _translation(x, y, z):
    pose = np.eye(4)
    pose[:3, 3] = [x, y, z]
    return pose


# A point that crosses the floor's top (z = 0) within one step: from z = 2 mm to z = -2 mm at
# v = (1, 0, -4) m/s in dt = 1 ms. |v| dt = 4.12 eps: 5 checks, at 1/5 .. 5/5 of the step; the
# second (z = 0.4 mm < eps, x = 0.4 mm) catches it, 0.4 ms into the step, 0.6 ms before its end.
# After the response the point sits at the contact (z = eps) minus the tangential part of the
# velocity change over the 0.4 ms travelled, then moves on 0.6 ms with the new velocity.
@pytest.mark.parametrize("options, velocity, position", [
    ({}, [0.0, 0.0, 0.0], [0.0, 0.0, 1e-3]),  # sticky: stops where it met the floor, no creep
    ({"friction": 0.0}, [1.0, 0.0, 0.0], [1e-3, 0.0, 1e-3]),  # default restitution 0
    ({"friction": 0.0, "restitution": 0.5}, [1.0, 0.0, 2.0], [1e-3, 0.0, 1e-3 + 1.2e-3]),
    # Coulomb, sliding: |u_t| = 1 > mu dv_n = 0.4: u_t -> 0.6 m/s; x = 0.4 - 0.16 + 0.36 mm.
    ({"friction": 0.1}, [0.6, 0.0, 0.0], [0.6e-3, 0.0, 1e-3]),
    # Sticking: mu dv_n = 5 >= 1; the bounce 0.25 x 4 = 1 m/s for 0.6 ms.
    ({"friction": 1.0, "restitution": 0.25}, [0.0, 0.0, 1.0], [0.0, 0.0, 1.6e-3]),
])
def test_hook_catches_a_point_part_way_through_the_step(exact_client, options, velocity, position):
    hook = CollisionHook(exact_client, [ColliderPlacement("floor")], **options)
    # The second point: near, never in contact; the third: far, and too fast to matter.
    x = np.array([[1e-3, 0.0, -2e-3], [0.3, 0.2, 0.05], [5.0, 5.0, 0.0]])
    v = np.array([[1.0, 0.0, -4.0], [0.0, 0.0, 0.0], [0.0, 0.0, 30.0]])
    x_in, v_in = x.copy(), v.copy()
    started = time.perf_counter()
    pos, vel, mask = hook.apply(x, v, t=0.5, dt=1e-3)
    wall = time.perf_counter() - started
    np.testing.assert_array_equal(x, x_in)  # the caller's arrays are not edited
    np.testing.assert_array_equal(v, v_in)
    np.testing.assert_allclose(pos[0], position, atol=1e-12)
    np.testing.assert_allclose(vel[0], velocity, atol=1e-12)
    np.testing.assert_array_equal(pos[1:], x[1:])
    np.testing.assert_array_equal(vel[1:], v[1:])
    np.testing.assert_array_equal(mask, [True, False, False])
    # Checks at 1/5 (both sent), 2/5 (both; the first caught), then 3/5 .. 5/5 (the second).
    assert hook.stats.queries == 5 and hook.stats.points_sent == 7
    assert hook.stats.colliding_last == hook.stats.colliding_max == 1
    assert 0 < hook.stats.query_s and 0 < hook.stats.response_s
    assert hook.stats.query_s + hook.stats.response_s <= wall  # the two split the call's time


def test_hook_responds_to_integer_velocities_without_truncating(exact_client):
    hook = CollisionHook(exact_client, [ColliderPlacement("floor")], friction=0.0, restitution=0.5)
    pos, vel, mask = hook.apply(np.array([[0.1, 0.0, 5e-4]]), np.array([[0, 0, -3]]), 0.1, 1e-3)
    assert mask.all()
    np.testing.assert_allclose(vel, [[0.0, 0.0, 1.5]], atol=1e-12)
    np.testing.assert_allclose(pos, [[0.1, 0.0, 1e-3]], atol=1e-12)


def test_a_contact_deeper_than_the_point_could_have_gone_since_the_last_call_is_no_contact(exact_client):
    """A signed distance changes no faster than the point's travel plus the surface's: a point
    that ended the last call outside and is answered deeper than that (here: the caller put it
    30 mm into the floor and says it did not move) is a false contact, not responded and
    counted; a point whose step took it there is pushed fully out; a call with other points (a
    new count) pushes every point fully out."""
    hook = CollisionHook(exact_client, [ColliderPlacement("floor")], eps=1e-3)
    start = np.array([[0.1, 0.0, -3e-3], [0.2, 0.0, 5e-3]])
    pos, _, mask = hook.apply(start, np.zeros((2, 3)), 0.0, 1e-3)  # the first call: no bound
    np.testing.assert_allclose(pos[:, 2], [1e-3, 5e-3], atol=1e-9)
    assert hook.stats.false_contacts == 0
    jumped = np.array([[0.1, 0.0, -30e-3], [0.2, 0.0, -15e-3]])
    pos, _, mask = hook.apply(jumped, np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -20.0]]), 1e-3, 1e-3)
    assert mask.tolist() == [False, True]
    np.testing.assert_allclose(pos[:, 2], [-30e-3, 1e-3], atol=1e-9)
    assert hook.stats.false_contacts == 1
    # Again in the next call: the count adds up over the calls.
    pos, _, _ = hook.apply(np.array([[0.1, 0.0, -30e-3], [0.2, 0.0, 5e-3]]), np.zeros((2, 3)), 2e-3, 1e-3)
    np.testing.assert_allclose(pos[:, 2], [-30e-3, 5e-3], atol=1e-9)
    assert hook.stats.false_contacts == 2
    pos, _, _ = hook.apply(np.array([[0.1, 0.0, -30e-3]] * 3), np.zeros((3, 3)), 3e-3, 1e-3)
    np.testing.assert_allclose(pos[:, 2], 1e-3, atol=1e-9)
    assert hook.stats.false_contacts == 2


class FalseContacts:
    """The real client, but the points that ``where(points, t)`` picks (``(n,) bool`` and the
    picked ones' unit outward normals, (k, 3)) are answered ``depth`` metres deep along those
    normals (a learned field wrong off its skin): the contact ``p + (eps + depth) normal``, the
    surface's velocity there ``velocity`` (m/s). ``depth`` may be a list, one per query (the
    last kept). ``t`` is what the caller sets, seconds."""

    def __init__(self, client, depth, where, velocity=0.0):
        self.client, self.where, self.velocity, self.t = client, where, velocity, 0.0
        self.depths = list(np.atleast_1d(depth))

    def list_models(self):
        return self.client.list_models()

    def query(self, model, points, **options):
        result = self.client.query(model, points, **options)
        depth = self.depths.pop(0) if len(self.depths) > 1 else self.depths[0]
        points = np.asarray(points, dtype=np.float64)
        wrong, normal = self.where(points, self.t)
        if not wrong.any():
            return result
        answer = {name: np.array(value, copy=True) for name, value in result.fields().items()}
        answer["distance"][wrong] = -depth
        answer["collides"][wrong] = True
        answer["contact"][wrong] = points[wrong] + (options["eps"] + depth) * normal
        for name, value in (("normal", normal), ("velocity", self.velocity)):
            if name in answer:
                answer[name][wrong] = value
        return type(result)(model=result.model, **answer)


def _band_along_x(points, t):
    """Points with 0.1 <= x < 0.2 m, their false normal +x."""
    wrong = (points[:, 0] >= 0.1) & (points[:, 0] < 0.2)
    return wrong, np.tile([1.0, 0.0, 0.0], (int(wrong.sum()), 1))


def _everywhere_up(points, t):
    """Every point, its false normal +z."""
    return np.ones(len(points), dtype=bool), np.tile([0.0, 0.0, 1.0], (len(points), 1))


def _patches(points, t):
    """A fiftieth of 3 mm cells, drawn anew every 20 ms, each with a normal of its own; none at
    t = 0 (the first step, whose pushes are not bounded)."""
    cell = np.floor(points / 3e-3).astype(np.int64)
    key = (cell @ np.array([73856093, 19349663, 83492791]) + int(t / 0.02) * 2654435761) % 1000003
    wrong = (key % 50 == 0) & (t > 0.0)
    normal = np.stack([np.sin(key * 1.1), np.cos(key * 2.3), np.sin(key * 3.7)], axis=1)[wrong]
    return wrong, normal / np.linalg.norm(normal, axis=1, keepdims=True)


@pytest.mark.parametrize("depth", [20e-3, 0.5e-3])
def test_a_false_contact_is_not_responded_nor_pushed_along_the_false_normal(exact_client, depth):
    """A point sliding 5 mm above the floor (0.5 m/s along x, 0.2 m/s down) is answered ``depth``
    deep with a sideways normal: no push along that normal (it stretched a cloth's springs and
    threw it), no response at all: the point goes on as it was. 20 mm is beyond its reach
    (eps + its step, 1.54 mm); 0.5 mm is within it, but the point moved away from that normal's
    surface, so it cannot be 0.5 mm deep in it. Pushed along the normal, it ended 2 mm from
    there."""
    client = FalseContacts(exact_client, depth, _band_along_x)
    hook = CollisionHook(client, [ColliderPlacement("floor")], eps=1e-3, friction=0.3)
    hook.apply(np.array([[0.05, 0.0, 5e-3]]), np.zeros((1, 3)), 0.0, 1e-3)
    velocity = np.array([[0.5, 0.0, -0.2]])
    end = np.array([[0.1499, 0.0, 5e-3]]) + velocity * 1e-3
    pos, vel, mask = hook.apply(end, velocity, 1e-3, 1e-3)
    assert not mask.any() and hook.stats.false_contacts == 1
    np.testing.assert_allclose(pos, end, atol=1e-12)
    np.testing.assert_allclose(vel, velocity, atol=1e-12)


@pytest.mark.parametrize("depth", [15e-3, 0.5e-3])
def test_a_cloth_answered_false_contacts_in_patches_is_not_thrown(exact_client, tmp_path, depth):
    """A cloth sliding down the floor tilted 25 degrees (friction 0.3), its collider answering a
    fiftieth of the points near it ``depth`` deep along a normal of its own (3 mm patches that
    change every 20 ms: a learned field wrong off its skin): the run ends, its energy never
    above its start, none through the floor. Pushed out by the reach along the false normals
    (the rule before stop 50), the cloth was thrown (the hook's tunnelling check) at
    t = 0.018 s (15 mm) and 0.21 s (0.5 mm); kept where they were beyond the reach only (not
    beyond the approach along the normal), the 0.5 mm cloth at 0.32 s."""
    from collider_client.sim.scene import load_scene
    from collider_client.sim.simulator import Simulator

    scene_file = tmp_path / "patches.toml"
    scene_file.write_text("""
[scene]
duration_s = 0.45
dt_s = 5e-4
[cloth]
width = 30
height = 30
spacing_m = 4.2e-3
origin_m = [-0.06, -0.06, 0.03]
axes = "xy"
density_kg_m2 = 1.0
[[colliders]]
model = "floor"
rotation_deg = [0.0, 25.0, 0.0]
[effects.gravity]
[effects.stretch]
stiffness_n_m = 15.0
[effects.shear]
stiffness_n_m = 15.0
[effects.bend]
stiffness_n_m = 15.0
[effects.damping]
coefficient_1_s = 2.0
[effects.collisions]
eps_m = 1e-3
[effects.friction]
coefficient = 0.3
""")
    client = FalseContacts(exact_client, depth, _patches)
    sim = Simulator(load_scene(scene_file), client)
    start = sim.energy()["total"]
    for _ in range(900):
        client.t = sim.t
        sim.step()
        assert sim.energy()["total"] <= start + 1e-12, f"energy above its start at t = {sim.t:.4f} s"
    assert sim.hook.stats.false_contacts > 1000
    up = np.array([np.sin(np.radians(25.0)), 0.0, np.cos(np.radians(25.0))])  # the floor's normal
    assert (sim.x @ up).min() > 0.0  # none through the floor


def test_hook_without_check_step_is_refused_by_default_for_a_fast_point(exact_client):
    hook = CollisionHook(exact_client, [ColliderPlacement("floor")])
    with pytest.raises(TunnellingError, match="speed x dt below eps"):
        hook.apply(np.array([[0.0, 0.0, 5e-4]]), np.array([[0.0, 0.0, -200.0]]), 0.1, 1e-3)


@pytest.mark.parametrize("only_colliding", [True, False])
@pytest.mark.parametrize("two", [False, True])
def test_hook_sends_its_eps_fields_and_only_colliding(exact_client, two, only_colliding):
    """eps = 2 mm (not the client's 1 mm default): penetrating points land 2 mm above the top
    face of the floor they are in; one collider is one query, several are one scene query."""
    spy = Recorder(exact_client)
    far = _translation(5.0, 0.0, 0.0)  # a second floor 5 m along x
    colliders = [ColliderPlacement("floor")] + ([ColliderPlacement("floor", far)] if two else [])
    hook = CollisionHook(spy, colliders, eps=2e-3, friction=0.5, only_colliding=only_colliding)
    x = np.array([[0.1, 0.2, -3e-3], [5.1, -0.2, -5e-4], [0.3, 0.0, 0.05]])
    pos, vel, mask = hook.apply(x, np.zeros((3, 3)), 0.0, 1e-3)
    expected = x.copy()
    expected[0, 2] = 2e-3
    if two:
        expected[1, 2] = 2e-3
    np.testing.assert_allclose(pos, expected, atol=1e-12)
    np.testing.assert_array_equal(vel, 0.0)
    np.testing.assert_array_equal(mask, [True, two, False])
    assert hook.stats.deepest_penetration_m == pytest.approx(-3e-3, abs=1e-9)  # float32 distances
    options = {"fields": ["distance", "contact", "collides", "normal"], "eps": 2e-3,
               "only_colliding": only_colliding}
    assert len(spy.calls) == 1
    method, sent_colliders, n, sent_options = spy.calls[0]
    assert n == 2 + two
    if two:
        assert method == "scene_query"
        assert [c.model for c in sent_colliders] == ["floor", "floor"]
        np.testing.assert_array_equal(sent_colliders[0].pose, np.eye(4))
        np.testing.assert_array_equal(sent_colliders[1].pose, far)
        # Static floors: no time, no pose velocity.
        assert [(c.time, c.pose_velocity) for c in sent_colliders] == [(None, None)] * 2
    else:
        assert (method, sent_colliders) == ("query", "floor")
        np.testing.assert_array_equal(sent_options.pop("pose"), np.eye(4))
        options.update(time=None, pose_velocity=None, clip=None)
    assert sent_options == options


@pytest.mark.parametrize("friction", [None, 0.0])
def test_hook_gives_each_point_its_own_colliders_velocity(exact_client, friction):
    """A static floor first, then a floor at x = 5 m rising at 0.5 m/s: points resting in each
    take that floor's velocity (sticky, or frictionless with restitution 0: the normal part)."""
    rising = ColliderPlacement("floor", lambda t: _translation(5.0, 0.0, 0.5 * t))
    hook = CollisionHook(exact_client, [ColliderPlacement("floor"), rising], friction=friction)
    t = 0.1  # the rising floor's top at z = 0.05
    x = np.array([[0.1, 0.0, -5e-4], [5.1, 0.0, 0.05 - 5e-4]])
    pos, vel, mask = hook.apply(x, np.zeros((2, 3)), t, 1e-3)
    assert mask.all()
    np.testing.assert_allclose(vel, [[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]], atol=1e-9)
    np.testing.assert_allclose(pos, [[0.1, 0.0, 1e-3], [5.1, 0.0, 0.05 + 1e-3]], atol=1e-9)


def test_a_plate_moving_past_a_resting_point_in_one_step_is_caught(exact_client):
    """The 0.2 mm plate falls 0.2 m in one step (20 m/s, dt = 10 ms) past a point at z = -5 cm
    that ends the step outside the plate's box: only its move brings the point into the check.
    eps = 5 mm: 41 checks; the 10th finds the plate's underside at z = -0.2 x 10/41 m - 0.2 mm,
    within eps; the point is pushed under it and carried down with it (sticky), checked again
    at the 31 later checks (the plate moves): it ends eps below the underside at the step's end,
    at 20 m/s downwards."""
    eps, dt, t = 5e-3, 1e-2, 1e-2
    plate = ColliderPlacement("plate", lambda time: _translation(0.0, 0.0, -20.0 * time))
    hook = CollisionHook(exact_client, [plate], eps=eps)
    info = {m.name: m for m in exact_client.list_models()}["plate"]
    z_point = -0.05
    assert z_point - (-0.2 + info.domain_max[2]) > eps  # outside the plate's box at t
    pos, vel, mask = hook.apply(np.array([[0.01, 0.02, z_point]]), np.zeros((1, 3)), t, dt)
    assert mask.all() and hook.stats.queries == 41
    np.testing.assert_allclose(pos, [[0.01, 0.02, -0.2 - 2e-4 - eps]], atol=1e-9)
    np.testing.assert_allclose(vel, [[0.0, 0.0, -20.0]], atol=1e-9)


@pytest.mark.parametrize("check_step", [False, True])
def test_hook_sends_only_the_points_near_a_collider(exact_client, check_step):
    """Floors at x = 0 (static) and at x = 5 m (rising at 1 m/s; its top at z = t): the points in
    either's box (padded 0.1 m) grown by eps, by its move over the step and along each point's
    path when the step is checked, are sent; no others."""
    rising = ColliderPlacement("floor", lambda t: _translation(5.0, 0.0, t))
    hook = CollisionHook(exact_client, [ColliderPlacement("floor"), rising], check_step=check_step)
    dt = 0.1 if not check_step else 0.01  # the rising floor moves 0.1 m / 10 mm in the step
    x = np.array([[0.2, 0.0, 0.05],     # in the static floor's box
                  [5.2, 0.0, 0.15],     # in the rising one's box
                  [2.5, 0.0, 0.0],      # between the two
                  [1.2, 0.0, 0.0],      # 0.5 m outside the static box
                  [5.0, 0.0, 0.25],     # 5 cm above the rising box: within its 0.1 m move
                  [0.2, 0.0, 0.5]])     # above the static box, coming from inside it
    v = np.zeros((6, 3))
    v[5, 2] = 0.45 / dt  # from z = 0.05 to 0.5 in the step
    if check_step:
        x[4, 2], x[5, 2], v[5, 2] = 0.215, 0.3, 0.1  # 5 mm above its 10 mm move; slow, far
    pos, _vel, mask = hook.apply(x, v, 0.1, dt)
    assert not mask.any()
    np.testing.assert_array_equal(pos, x)
    sent = hook.stats.points_sent
    if check_step:
        assert sent == 2 * hook.stats.queries  # the first two, at every check
    else:
        assert sent == 2 and hook.stats.queries == 1
    unculled = CollisionHook(exact_client, [ColliderPlacement("floor")], cull=False,
                             check_step=False)
    unculled.apply(x, np.zeros((6, 3)), 0.1, dt)
    assert unculled.stats.points_sent == 6


def test_hook_stats_add_up_over_calls(exact_client):
    hook = CollisionHook(exact_client, [ColliderPlacement("floor")])
    near = np.array([[0.1, 0.0, -2e-3], [0.2, 0.0, 0.05], [5.0, 0.0, 0.0]])
    far = np.array([[5.0, 0.0, 0.0], [0.0, 6.0, 0.0]])
    wall = 0.0
    history = []
    for x in (near, far, near):
        started = time.perf_counter()
        hook.apply(x, np.zeros_like(x), 0.0, 1e-3)
        wall += time.perf_counter() - started
        s = hook.stats
        history.append((s.calls, s.points_total, s.points_sent, s.queries, s.colliding_last,
                        s.colliding_max, s.query_s, s.response_s))
        assert s.query_s + s.response_s <= wall
    assert [h[:6] for h in history] == [(1, 3, 2, 1, 1, 1), (2, 5, 2, 1, 0, 1), (3, 8, 4, 2, 1, 1)]
    assert 0 < history[0][6] == history[1][6] < history[2][6]  # query time adds up
    assert 0 < history[0][7] <= history[1][7] <= history[2][7]  # so does the response's
    assert hook.stats.deepest_penetration_m == pytest.approx(-2e-3, abs=1e-9)


# -- a skinned collider: its clip, its clip's speed bound -------------------------------------------

ARM = ModelInfo("arm", "skinned", domain_min=np.array([-0.1, -0.2, -0.1]),
                domain_max=np.array([0.6, 0.2, 0.4]),
                skeleton={"joints": ["shoulder"], "parents": [-1], "loop": True,
                          "clips": [{"name": "wave", "duration_s": 1.0, "max_surface_speed": 1.5},
                                    {"name": "reach", "duration_s": 2.0, "max_surface_speed": 0.5}]})


def test_a_skinned_collider_moves_by_its_clips_speed_times_scale_and_dt():
    scaled = np.diag([2.0, 2.0, 2.0, 1.0])
    hook = CollisionHook(None, [ColliderPlacement("arm"), ColliderPlacement("arm", scaled, clip="reach")],
                         infos={"arm": ARM})
    assert hook.clips == ["wave", "reach"]  # None: the first clip
    assert [line.duration_s for line in hook.timelines] == pytest.approx([1.0, 2.0])
    assert hook.moving and "velocity" in hook.fields
    # wave: 1.5 m/s x 1 x 10 ms; reach: 0.5 m/s x 2 x 10 ms (a fixed pose: no frame motion).
    assert hook.collider_moves([np.eye(4), scaled], 0.3, 0.01) == pytest.approx([0.015, 0.01])
    # The clip's speed decides the checks: 15 mm in a step of eps 1 mm is 16 checks.
    assert hook.substeps(np.zeros((1, 3)), np.array([0]), hook.collider_moves(
        [np.eye(4), scaled], 0.3, 0.01), 0.3, 0.01) == 16


def test_a_clip_is_refused_where_it_does_not_fit():
    infos = {"arm": ARM, "box": BOX}
    with pytest.raises(ValueError, match=r"^ColliderPlacement\('box'\): clip applies to skinned "
                                         r"models; this one is mesh$"):
        CollisionHook(None, [ColliderPlacement("box", clip="wave")], infos=infos)
    with pytest.raises(ValueError, match=r"^ColliderPlacement\('arm'\): model 'arm' has no clip "
                                         r"'run'; its clips: \['wave', 'reach'\]$"):
        CollisionHook(None, [ColliderPlacement("arm", clip="run")], infos=infos)
    old = ModelInfo("arm", "skinned", skeleton={**ARM.skeleton, "clips": [
        {"name": "wave", "duration_s": 1.0}]})
    with pytest.raises(ValueError, match=r"^ColliderPlacement\('arm'\): model 'arm''s clip 'wave' "
                                         r"does not record max_surface_speed \(made by an older "
                                         r"version\): make the model again$"):
        CollisionHook(None, [ColliderPlacement("arm")], infos={"arm": old})
    with pytest.raises(ValueError, match=r"^ColliderPlacement\('arm'\): clip must be None or a "
                                         r"clip's name, got 3$"):
        ColliderPlacement("arm", clip=3)


def _arm_distance(points, clip, t):
    """Signed distance (m) of ``points`` to the generated arm skinned in ``clip`` at ``t`` s (the
    engine's exact kind, asked directly: independent of the hook)."""
    from collider_contract import SkeletonPose
    from collider_server.making.skinned import skinned_arm, skinned_collider

    collider = _arm_distance.collider = getattr(_arm_distance, "collider", None) or skinned_collider(
        skinned_arm(), "arm")
    distance, _, _ = collider.evaluate_at(np.asarray(points, dtype=np.float64), False, t,
                                          SkeletonPose(clip=clip))
    return np.asarray(distance)


def test_the_hook_asks_a_skinned_collider_in_the_placements_clip(models_dir):
    """Points 2 mm inside the arm as "reach" poses it at 0.9 s (elbow bent 60 degrees up, not so
    in "wave") are all caught and put eps outside that pose: the hook asked in "reach"."""
    import collider_client as cc
    from collider_server.making.skinned import skinned_arm

    skin = skinned_arm()
    from collider_server.engine.skinning import pose_at, skin_vertices

    posed = skin_vertices(skin, pose_at(skin, "reach", 0.9)[0])
    rng = np.random.default_rng(3)
    forearm = posed[posed[:, 0] > 0.3]
    picked = forearm[rng.choice(len(forearm), 100, replace=False)]
    # 2 mm inward: towards the bone's axis, approximately; keep those the exact kind has inside.
    inside = picked - 0.002 * (picked - picked.mean(axis=0)) / np.linalg.norm(
        picked - picked.mean(axis=0), axis=1, keepdims=True)
    inside = inside[_arm_distance(inside, "reach", 0.9) < -5e-4]
    assert len(inside) > 20
    with cc.Client(models=models_dir, device="cpu") as client:
        hook = CollisionHook(client, [ColliderPlacement("arm", clip="reach")], eps=1e-3)
        pos, _, mask = hook.apply(inside, np.zeros_like(inside), t=0.9, dt=1e-3)
    assert mask.all()
    np.testing.assert_allclose(_arm_distance(pos, "reach", 0.9), 1e-3, atol=1e-5)


def test_cloth_points_on_a_waving_arm_never_go_deeper_than_a_tenth_of_a_millimetre(models_dir):
    """A ring of 300 points (a sleeve) resting around the forearm while "wave" swings the arm
    for 0.25 s at 240 steps a second: after every step no point is deeper than 0.1 mm inside the
    exact surface at that pose, and the arm pushed them (they moved)."""
    import collider_client as cc

    angle = np.linspace(0.0, 2.0 * np.pi, 30, endpoint=False)
    x = np.linspace(0.28, 0.46, 10)
    points = np.array([[xi, 0.0415 * np.cos(a), 0.0415 * np.sin(a)] for xi in x for a in angle])
    start = points.copy()
    velocities = np.zeros_like(points)
    dt, deepest = 1.0 / 240.0, 0.0
    with cc.Client(models=models_dir, device="cpu") as client:
        hook = CollisionHook(client, [ColliderPlacement("arm")], eps=1e-3)
        for step in range(1, 61):
            t = step * dt
            points = points + velocities * dt
            points, velocities, _ = hook.apply(points, velocities, t, dt)
            deepest = min(deepest, float(_arm_distance(points, "wave", t).min()))
    assert deepest > -1e-4, f"a point {-1e3 * deepest:.3f} mm inside"
    assert np.linalg.norm(points - start, axis=1).max() > 0.02  # the arm carried them along


def test_a_false_contact_held_through_a_step_s_checks_is_no_contact_at_any(exact_client):
    """A floor rising 10 mm in the step (1 m/s, dt = 10 ms) is checked several times (eps = 1 mm),
    and a point the caller put 20 mm into it while saying it did not move is answered deep at
    each: deeper than eps plus its approach (the floor's rise so far) at every check, so a false
    contact at every check: never pushed (until stop 49 each check pushed it by the whole reach,
    and it ended out of the floor), counted once."""
    rising = ColliderPlacement("floor", lambda t: _translation(0.0, 0.0, t))
    hook = CollisionHook(exact_client, [rising], eps=1e-3)
    hook.apply(np.array([[0.1, 0.0, 0.05]]), np.zeros((1, 3)), 0.0, 1e-2)  # the first call: no bound
    pos, vel, mask = hook.apply(np.array([[0.1, 0.0, -0.02]]), np.zeros((1, 3)), 1e-2, 1e-2)
    assert not mask.any() and hook.stats.queries > 3 and hook.stats.false_contacts == 1
    np.testing.assert_allclose(pos, [[0.1, 0.0, -0.02]], atol=1e-12)
    np.testing.assert_allclose(vel, 0.0, atol=1e-12)


def test_the_reach_bounds_a_step_s_pushes_where_the_collider_s_velocity_is_false(exact_client):
    """The approach along the normal is measured against the surface velocity the collider
    answers; where that is false (20 m/s up, on a floor rising at 1 mm/s), the approach allows
    a push as deep as the reach at each check. The reach (eps + its step, 5 mm for a point
    falling at 4 m/s) still bounds the step's pushes all together: 3.5 mm at the first check,
    0.9 mm at the next, and the third's 0.9 mm, over what is left, is a false contact. Without
    the step's budget the third was pushed too."""
    client = FalseContacts(exact_client, 0.0, _everywhere_up, velocity=[0.0, 0.0, 20.0])
    rising = ColliderPlacement("floor", lambda t: _translation(0.0, 0.0, 1e-3 * t))
    hook = CollisionHook(client, [rising], eps=1e-3)
    hook.apply(np.array([[0.1, 0.0, 0.05]]), np.zeros((1, 3)), 0.0, 1e-3)  # the first call: no bound
    client.depths = [2.5e-3, -0.1e-3]  # the next call's checks: the first, then every later one
    hook.apply(np.array([[0.1, 0.0, 0.05]]), np.array([[0.0, 0.0, -4.0]]), 1e-3, 1e-3)
    assert hook.stats.queries == 1 + 5  # the first call, then 4 mm / eps + 1 checks
    assert hook.stats.false_contacts == 1
