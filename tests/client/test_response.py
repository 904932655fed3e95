"""Collision response helpers on analytic cases: a plane, a sphere, Coulomb friction sticking
below and sliding above its threshold, restitution, moving colliders. World frame, metres, m/s."""

from __future__ import annotations

import numpy as np
import pytest

from collider_client import (
    ColliderPlacement, CollisionHook, collider_velocity, project_to_contacts, respond_velocities,
)
from collider_client.response import world_box
from collider_client._models import ModelInfo

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
