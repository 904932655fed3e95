"""Pose validation and the float64 moves between world and collider frames."""

from __future__ import annotations

import numpy as np
import pytest

from collider_contract.pose import IDENTITY, Pose, PoseError, as_pose


def random_rotation(seed) -> np.ndarray:
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def matrix(rotation, translation, scale=1.0):
    m = np.eye(4)
    m[:3, :3] = scale * rotation
    m[:3, 3] = translation
    return m


def test_none_is_the_identity_and_a_pose_passes_through():
    assert as_pose(None) is IDENTITY and IDENTITY.is_identity
    pose = as_pose(np.eye(4))
    assert pose.is_identity and as_pose(pose) is pose


@pytest.mark.parametrize("scale", [1.0, 2.5, 1e-3])
def test_to_local_inverts_the_pose(scale):
    rotation = random_rotation(0)
    translation = np.array([1.2e4, -3.0e3, 7.5e3])
    pose = as_pose(matrix(rotation, translation, scale))
    assert pose.scale == pytest.approx(scale, rel=1e-12)
    np.testing.assert_allclose(pose.rotation, rotation, atol=1e-12)
    local = np.random.default_rng(1).uniform(-0.2, 0.2, (100, 3))
    world = local @ (scale * rotation).T + translation
    # float64 throughout: 1e4 m away the round trip is good to ~1e-12 m.
    np.testing.assert_allclose(pose.to_local(world), local, rtol=0, atol=1e-11 / min(scale, 1.0))
    np.testing.assert_allclose(pose.matrix(), matrix(rotation, translation, scale), atol=1e-12)
    # Directions are rotated only (row i of the result is R e_i): no translation, no scale.
    np.testing.assert_allclose(pose.to_world_directions(np.eye(3)), rotation.T, atol=1e-12)


@pytest.mark.parametrize("pose", [None, "moved"])
def test_to_local_gives_a_float64_copy_whatever_the_input(pose):
    pose = IDENTITY if pose is None else as_pose(matrix(random_rotation(3), [0.5, 0, 0]))
    points = np.random.default_rng(4).uniform(-0.2, 0.2, (10, 3))
    assert pose.to_local(points.astype(np.float32)).dtype == np.float64
    local = pose.to_local(points)
    local[:] = 7.0  # a copy: the caller's points are not touched
    assert (points != 7.0).all()


def test_float32_rotations_are_accepted_and_reorthonormalised():
    rotation = random_rotation(2).astype(np.float32)
    pose = as_pose(matrix(rotation.astype(np.float64), [0, 0, 0]).astype(np.float32))
    assert pose.scale == 1.0
    np.testing.assert_allclose(pose.rotation.T @ pose.rotation, np.eye(3), atol=1e-14)
    assert isinstance(pose, Pose)


@pytest.mark.parametrize("block, message", [
    (np.diag([1.0, 1.0, 1.001]), "not rigid"),
    (np.diag([-1.0, -1.0, -1.0]), "reflection"),
    ([[0, 1, 0], [1, 0, 0], [0, 0, 1]], "reflection"),
])
def test_near_misses_are_rejected(block, message):
    with pytest.raises(PoseError, match=message):
        as_pose(matrix(np.asarray(block, float), [0, 0, 0]))


def _refusal(pose) -> str:
    with pytest.raises(PoseError) as caught:
        as_pose(pose)
    return str(caught.value)


def test_each_refusal_says_exactly_what_is_wrong_and_where():
    far = matrix(np.eye(3), [0.0, 0.0, -2e6])
    assert _refusal(far) == ("pose translation [0.0, 0.0, -2000000.0] is outside the coordinate "
                             "range +-1e+06 (world units; row 2, column 3)")
    nan = np.eye(4)
    nan[1, 2] = np.nan
    assert _refusal(nan) == "pose contains NaN or Inf (first at row 1, column 2)"
    assert _refusal(np.eye(3)) == "pose must be a 4x4 matrix, got shape (3, 3)"
    assert _refusal([["a"] * 4] * 4).startswith("pose must be a 4x4 matrix of numbers: ")
    bottom = np.eye(4)
    bottom[3, 3] = 2e6  # a bad bottom row, not a far translation
    assert _refusal(bottom) == "pose bottom row must be [0, 0, 0, 1], got [0.0, 0.0, 0.0, 2000000.0]"
    assert _refusal(matrix(np.zeros((3, 3)), [0, 0, 0])) == "pose rotation block is zero (scale 0)"
    assert _refusal(matrix(np.diag([1.0, 1.0, 1.001]), [0, 0, 0])) == (
        "pose is not rigid: its 3x3 block is not a rotation times a uniform scale "
        "(shear or non-uniform scale)")
    assert _refusal(matrix(-np.eye(3), [0, 0, 0])) == (
        "pose is a reflection (negative determinant); only rotations are allowed")
    assert _refusal(matrix(np.eye(3), [0, 0, 0], 2e6)) == "pose scale 2e+06 is outside [1e-06, 1e+06]"
    assert _refusal(matrix(np.eye(3), [0, 0, 0], 5e-7)) == "pose scale 5e-07 is outside [1e-06, 1e+06]"


def test_the_limits_themselves_are_accepted():
    assert as_pose(matrix(np.eye(3), [1e6, -1e6, 0.0])).translation.tolist() == [1e6, -1e6, 0.0]
    assert as_pose(matrix(np.eye(3), [0, 0, 0], 1e6)).scale == pytest.approx(1e6, rel=1e-12)
    assert as_pose(matrix(np.eye(3), [0, 0, 0], 1e-6)).scale == pytest.approx(1e-6, rel=1e-9)
    # The bottom row is checked to 1e-9: 5e-10 off passes, 5e-9 off does not.
    nearly = np.eye(4)
    nearly[3, 0] = 5e-10
    as_pose(nearly)
    nearly[3, 0] = 5e-9
    assert _refusal(nearly).startswith("pose bottom row must be [0, 0, 0, 1]")


@pytest.mark.parametrize("scale, kept", [(1.0 + 5e-6, 1.0), (1.0 + 2e-5, 1.0 + 2e-5), (2.0, 2.0)])
def test_a_scale_within_the_tolerance_of_one_is_one_and_others_divide(scale, kept):
    pose = as_pose(matrix(np.eye(3), [0.1, 0, 0], scale))
    assert pose.scale == pytest.approx(kept, rel=1e-12, abs=0)
    world = np.array([[0.1 + kept * 0.3, 0.0, 0.0]])
    np.testing.assert_allclose(pose.to_local(world), [[0.3, 0.0, 0.0]], rtol=0, atol=1e-12)
