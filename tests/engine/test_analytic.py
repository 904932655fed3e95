"""Every baked kind against the analytic SDF of a sphere, a box and a torus, in the world frame,
for the identity pose, a rotated + translated pose (near the origin and ~1e4 m away) and a
uniform scale. Units: metres."""

from __future__ import annotations

import numpy as np
import pytest

from collider_contract.pose import as_pose

EPS = 1e-3
N_POINTS = 600


def rotation(axis, angle) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def pose_matrix(rot=np.eye(3), translation=(0, 0, 0), scale=1.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = scale * rot
    m[:3, 3] = translation
    return m


POSES = {
    "identity": None,
    "rotated-translated": pose_matrix(rotation([1, 2, 3], 0.7), [0.3, -0.2, 0.5]),
    "far-1e4m": pose_matrix(rotation([-1, 0.5, 2], 2.1), [1.2e4, -0.9e4, 1.1e4]),
    "scale-2": pose_matrix(rotation([0, 1, 0], -1.0), [0.05, 0.0, -0.1], scale=2.0),
}

# Bounds per (kind, shape): distance error (m), normal angle error (deg) for points more than
# 1 mm from the surface (mean, max). Measured errors are 2-3x below these.
#   mesh: the triangulation's facet error only; normals are facet normals near the surface.
#   voxel: 64^3 trilinear (cells of 3.8 / 3.9 / 4.9 mm); the box's corners are rounded by the
#   interpolation, hence the large worst-case angle there.
BOUNDS = {
    ("mesh", "sphere"): (6e-5, 1.0, 3.0),
    ("mesh", "box"): (1e-7, 0.01, 0.1),
    ("mesh", "torus"): (1.6e-4, 3.0, 6.0),
    ("voxel", "sphere"): (1.5e-4, 1.5, 4.0),
    ("voxel", "box"): (1.5e-3, 4.0, 60.0),
    ("voxel", "torus"): (4e-4, 3.0, 12.0),
}


def world_truth(shape, points, pose):
    """Analytic distance (world units) and unit normal (world frame) at world ``points``."""
    local = pose.to_local(points)
    return pose.scale * shape.sdf(local), pose.to_world_directions(shape.gradient(local))


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


def world_points(shape, pose_name, seed=3):
    pose = as_pose(POSES[pose_name])
    local = shape.sample(N_POINTS, seed)
    return local @ (pose.scale * pose.rotation).T + pose.translation, pose


@pytest.mark.parametrize("pose_name", list(POSES))
@pytest.mark.parametrize("shape_name", ["sphere", "box", "torus"])
@pytest.mark.parametrize("kind", ["mesh", "voxel"])
def test_exact_and_voxel_kinds_match_the_analytic_sdf(shape_collider, analytic_shape, kind, shape_name, pose_name):
    shape = analytic_shape(shape_name)
    collider = shape_collider(shape_name, kind)
    points, pose = world_points(shape, pose_name)
    truth_d, truth_n = world_truth(shape, points, pose)
    result = collider.query(points, ["distance", "normal", "contact", "collides"],
                            pose=POSES[pose_name], eps=EPS)
    d_tol, mean_deg, max_deg = BOUNDS[(kind, shape_name)]
    d_tol *= pose.scale
    assert result.distance.dtype == np.float32 and result.normal.dtype == np.float32
    assert result.contact.dtype == np.float64 and result.collides.dtype == bool
    error = np.abs(result.distance - truth_d)
    assert error.max() < d_tol + 1e-7, f"max distance error {error.max():.3g} m"
    np.testing.assert_allclose(np.linalg.norm(result.normal, axis=1), 1.0, atol=1e-6)
    off_surface = np.abs(truth_d) > 1e-3 * pose.scale
    angle = angle_deg(result.normal.astype(np.float64), truth_n)[off_surface]
    assert angle.mean() < mean_deg and angle.max() < max_deg, (angle.mean(), angle.max())
    # The contact is p + (eps - d) n and lies on the eps offset surface.
    expected_contact = points + (EPS - result.distance.astype(np.float64))[:, None] * result.normal
    np.testing.assert_allclose(result.contact, expected_contact, rtol=0, atol=1e-6 * pose.scale)
    contact_truth, _ = world_truth(shape, result.contact, pose)
    assert np.abs(contact_truth - EPS).max() < 2 * d_tol + 1e-7
    np.testing.assert_array_equal(result.collides, result.distance < EPS)


@pytest.mark.parametrize("pose_name", list(POSES))
@pytest.mark.parametrize("shape_name", ["sphere", "box", "torus"])
def test_mesh_kind_contact_lies_on_its_own_offset_surface(shape_collider, analytic_shape, shape_name, pose_name):
    """For the exact kind the contact is on the eps offset of the triangle mesh itself (to
    float rounding on the convex shapes), not only to within the facet error."""
    shape = analytic_shape(shape_name)
    collider = shape_collider(shape_name, "mesh")
    points, pose = world_points(shape, pose_name, seed=5)
    eps = 2e-3 * pose.scale
    contact = collider.query(points, "contact", pose=POSES[pose_name], eps=eps).contact
    again = collider.query(contact, "distance", pose=POSES[pose_name]).distance
    tolerance = 1e-9 * max(1.0, float(np.abs(pose.translation).max()))
    if shape_name == "torus":
        # Near a concave mesh edge the pushed point comes closer to the neighbouring facet, by
        # up to eps (1 - cos(dihedral angle)); 64 tube sections: 5.6 degrees.
        tolerance += eps * (1 - np.cos(np.radians(5.7)))
    np.testing.assert_allclose(again, eps, rtol=1e-6, atol=tolerance + 1e-9)


@pytest.mark.parametrize("pose_name", list(POSES))
@pytest.mark.parametrize("shape_name", ["sphere", "torus"])
def test_kdtree_kind_is_an_upper_bound_within_an_edge(shape_collider, analytic_shape, shape_name, pose_name):
    """kdtree (approximate): |distance| is the distance to the nearest vertex, so it is never
    below the exact unsigned distance and at most one edge above it; the sign is right away
    from the surface, the normal is the nearest vertex's normal."""
    shape = analytic_shape(shape_name)
    collider = shape_collider(shape_name, "kdtree")
    points, pose = world_points(shape, pose_name)
    truth_d, truth_n = world_truth(shape, points, pose)
    result = collider.query(points, ["distance", "normal", "collides"], pose=POSES[pose_name], eps=EPS)
    facet = shape.facet_error * pose.scale
    excess = np.abs(result.distance) - np.abs(truth_d)
    assert excess.min() > -facet - 1e-6
    assert excess.max() < shape.edge_length * pose.scale
    clear = np.abs(truth_d) > shape.edge_length * pose.scale
    np.testing.assert_array_equal(np.sign(result.distance[clear]), np.sign(truth_d[clear]))
    assert angle_deg(result.normal.astype(np.float64), truth_n)[clear].max() < 6.0
    np.testing.assert_array_equal(result.collides, result.distance < EPS)


def test_kdtree_kind_on_a_coarse_box_is_still_an_upper_bound(shape_collider, analytic_shape):
    """A box has 8 vertices: the nearest-vertex distance is far off but never too small."""
    shape = analytic_shape("box")
    points = shape.sample(N_POINTS, 4)
    distance = shape_collider("box", "kdtree").query(points, "distance").distance
    assert (np.abs(distance) - np.abs(shape.sdf(points))).min() > -1e-7
    assert shape_collider("box", "kdtree").info.approximate


@pytest.mark.parametrize("kind", ["mesh", "voxel", "kdtree", "neural"])
def test_pose_moves_points_normals_and_contacts(shape_collider, analytic_shape, kind):
    """For every kind (neural too, whose accuracy is not tested here) querying T p with pose T
    gives the identity answer at p: distance (times the scale), normal rotated by R, contact
    mapped by T, also 1e4 m from the origin (the transform runs in float64)."""
    shape = analytic_shape("torus")
    collider = shape_collider("torus", kind)
    local = shape.sample(300, 9)
    fields = ["distance", "normal", "contact", "collides"]
    base = collider.query(local, fields, eps=EPS)
    for name, matrix in POSES.items():
        pose = as_pose(matrix)
        world = local @ (pose.scale * pose.rotation).T + pose.translation
        moved = collider.query(world, fields, pose=matrix, eps=EPS * pose.scale)
        np.testing.assert_allclose(moved.distance, pose.scale * base.distance, rtol=1e-6, atol=1e-7,
                                   err_msg=name)
        np.testing.assert_allclose(moved.normal, base.normal @ pose.rotation.T, atol=2e-6, err_msg=name)
        expected_contact = base.contact @ (pose.scale * pose.rotation).T + pose.translation
        np.testing.assert_allclose(moved.contact, expected_contact, rtol=0,
                                   atol=1e-6 * pose.scale, err_msg=name)
        np.testing.assert_array_equal(moved.collides, base.collides, err_msg=name)


def test_default_eps_is_one_millimetre(shape_collider):
    collider = shape_collider("sphere", "mesh")
    points = np.array([[0.0, 0.0, 0.1005], [0.0, 0.0, 0.1015]])
    result = collider.query(points, ["distance", "contact", "collides"])
    np.testing.assert_array_equal(result.collides, [True, False])
    explicit = collider.query(points, ["contact"], eps=1e-3)
    np.testing.assert_array_equal(result.contact, explicit.contact)
