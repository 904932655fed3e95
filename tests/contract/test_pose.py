"""Pose validation and the float64 moves between world and collider frames (collider frame ->
world frame, world units), checked against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from collider_contract.pose import (
    IDENTITY,
    MAX_COORDINATE_M,
    MAX_SCALE,
    ORTHONORMAL_TOLERANCE,
    Pose,
    PoseError,
    as_pose,
    box_corners,
    rotate_rows,
    transform_points,
)


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


@pytest.mark.parametrize("scale", [1.0, 2.0, 2.5, 1e-3])
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


def test_the_limits_are_a_million():
    assert (MAX_COORDINATE_M, MAX_SCALE, ORTHONORMAL_TOLERANCE) == (1e6, 1e6, 1e-5)


def test_identity_is_the_unit_matrix_without_a_source():
    assert IDENTITY.rotation.tolist() == np.eye(3).tolist()
    assert IDENTITY.translation.tolist() == [0.0, 0.0, 0.0]
    assert IDENTITY.scale == 1.0 and IDENTITY.source is None
    assert IDENTITY.matrix().tolist() == np.eye(4).tolist()


@pytest.mark.parametrize("rotation, translation, scale", [
    (np.eye(3), [0.0, 0.0, 0.0], 2.0),          # scale alone
    (np.eye(3), [0.0, 0.0, 1e-9], 1.0),         # translation alone
    (random_rotation(5), [0.0, 0.0, 0.0], 1.0),  # rotation alone
])
def test_any_one_part_makes_a_pose_other_than_the_identity(rotation, translation, scale):
    pose = as_pose(matrix(rotation, translation, scale))
    assert not pose.is_identity
    # and it moves points: to_local is T^-1 p, to_world is T p
    points = np.array([[0.1, 0.2, 0.3], [-1.0, 2.0, 0.5]])
    expected = (points - translation) @ rotation / scale
    np.testing.assert_allclose(pose.to_local(points), expected, rtol=0, atol=1e-15)
    np.testing.assert_allclose(pose.to_world(expected), points, rtol=0, atol=1e-15)


def test_to_world_is_scale_rotate_then_translate():
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # +90 deg about z
    pose = as_pose(matrix(rotation, [10.0, 20.0, 30.0], 2.0))
    local = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 2.0, 3.0]], dtype=np.float32)
    world = pose.to_world(local)
    assert world.dtype == np.float64
    np.testing.assert_allclose(world, [[10.0, 22.0, 30.0], [8.0, 20.0, 30.0], [6.0, 22.0, 36.0]],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(pose.to_local(world), local, rtol=0, atol=1e-12)
    # Directions: rotated only (no scale, no translation), lists accepted.
    np.testing.assert_allclose(pose.to_world_directions([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                               [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], rtol=0, atol=1e-15)


def test_float32_points_are_moved_in_float64():
    pose = as_pose(matrix(np.eye(3), [0.25, 0.0, 0.0], 0.1))
    local = np.array([[0.1, 0.2, 0.3], [1.0 / 3.0, 5.0, -7.0]], np.float32)
    expected = local.astype(np.float64) * pose.scale + [0.25, 0.0, 0.0]
    np.testing.assert_allclose(pose.to_world(local), expected, rtol=1e-15, atol=0)
    world = np.array([[0.1, 0.2, 0.3]], np.float32)
    expected = (world.astype(np.float64) - [0.25, 0.0, 0.0]) / pose.scale
    np.testing.assert_allclose(pose.to_local(world), expected, rtol=1e-15, atol=0)


def test_the_identity_copies_points_to_float64_and_passes_directions_through():
    points = np.array([[1.0, 2.0, 3.0]], dtype=np.float32)
    for move in (IDENTITY.to_local, IDENTITY.to_world):
        moved = move(points)
        assert moved.dtype == np.float64 and moved.tolist() == [[1.0, 2.0, 3.0]]
        moved[:] = 0.0
        assert points.tolist() == [[1.0, 2.0, 3.0]]
    directions = np.array([[0.0, 0.6, 0.8]], dtype=np.float32)
    assert IDENTITY.to_world_directions(directions) is directions
    assert IDENTITY.to_world_directions([[0.0, 0.6, 0.8]]).tolist() == [[0.0, 0.6, 0.8]]


def test_rotate_rows_is_the_matrix_product_and_each_row_is_independent_of_its_batch():
    rotation = random_rotation(7)
    vectors = np.random.default_rng(8).normal(size=(33, 3))
    rotated = rotate_rows(vectors, rotation)
    np.testing.assert_allclose(rotated, vectors @ rotation.T, rtol=0, atol=1e-14)
    for i in (0, 17, 32):
        assert rotate_rows(vectors[i:i + 1], rotation).tolist() == rotated[i:i + 1].tolist()
    # an exact case: each column of the matrix picked by a unit row
    m = np.arange(9.0).reshape(3, 3)
    assert rotate_rows([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], m).tolist() == [
        [0.0, 3.0, 6.0], [1.0, 4.0, 7.0], [2.0, 5.0, 8.0], [3.0, 12.0, 21.0]]


def test_box_corners_take_hi_by_the_bits_of_their_index():
    corners = box_corners([0, 1, 2], (10, 11, 12))
    assert corners.dtype == np.float64 and corners.shape == (8, 3)
    assert corners.tolist() == [
        [0.0, 1.0, 2.0], [10.0, 1.0, 2.0], [0.0, 11.0, 2.0], [10.0, 11.0, 2.0],
        [0.0, 1.0, 12.0], [10.0, 1.0, 12.0], [0.0, 11.0, 12.0], [10.0, 11.0, 12.0]]


def test_transform_points_applies_any_affine_map_unvalidated():
    affine = [[2, 0, 0, 1], [0, 3, 0, 2], [1, 0, 1, 3], [9, 9, 9, 9]]  # shear, non-uniform, junk row
    moved = transform_points(affine, [[1, 1, 1], [0, 0, 0], [1, 2, 3]])
    assert moved.dtype == np.float64
    assert moved.tolist() == [[3.0, 5.0, 5.0], [1.0, 2.0, 3.0], [3.0, 8.0, 7.0]]
    assert transform_points(np.eye(4, dtype=np.float32),
                            np.array([[0.1, 0.2, 0.3]], np.float32)).dtype == np.float64


def test_the_source_is_the_callers_matrix_bit_for_bit_and_a_copy():
    given = matrix(random_rotation(9), [1e5 / 3, -2.0 / 7, 0.1], 1.0 + 1e-6)
    pose = as_pose(given)
    assert pose.scale == 1.0  # snapped: within the tolerance of one
    assert pose.source.dtype == np.float64 and pose.source.tobytes() == given.tobytes()
    assert pose.translation.tolist() == given[:3, 3].tolist()
    kept = given.copy()
    given[:] = 0.0  # the caller reuses its array: the pose keeps what it was given
    assert pose.source.tobytes() == kept.tobytes()
    assert pose.translation.tolist() == kept[:3, 3].tolist()
    # validating the source again gives the very same pose (what a server does with it)
    again = as_pose(pose.source)
    assert again.rotation.tobytes() == pose.rotation.tobytes() and again.scale == pose.scale
    # integer and nested-list poses are numbers too
    assert as_pose([[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]).source.dtype == np.float64


def test_the_first_non_finite_entry_in_row_major_order_is_named():
    m = np.eye(4)
    m[2, 0] = np.inf
    m[1, 3] = np.nan
    assert _refusal(m) == "pose contains NaN or Inf (first at row 1, column 3)"


def test_the_first_far_translation_row_is_named():
    assert _refusal(matrix(np.eye(3), [0.0, -2e6, 3e6])) == (
        "pose translation [0.0, -2000000.0, 3000000.0] is outside the coordinate range +-1e+06 "
        "(world units; row 1, column 3)")
    assert _refusal(matrix(np.eye(3), [np.nextafter(1e6, 2e6), 0.0, 0.0])).endswith("(world units; row 0, column 3)")


def test_the_checks_run_in_the_documented_order():
    # shape before finiteness; finiteness before range; range before the bottom row; the bottom
    # row before the block; a zero block before rigidity; rigidity before reflection; reflection
    # before the scale range.
    assert _refusal(np.full((3, 4), np.nan)).startswith("pose must be a 4x4 matrix, got shape")
    both = matrix(np.eye(3), [3e6, 0.0, np.nan])
    assert _refusal(both).startswith("pose contains NaN or Inf")
    far_bottom = matrix(np.zeros((3, 3)), [3e6, 0.0, 0.0])
    far_bottom[3] = [1.0, 0.0, 0.0, 1.0]
    assert _refusal(far_bottom).startswith("pose translation")
    bad_bottom = matrix(np.zeros((3, 3)), [0.0, 0.0, 0.0])
    bad_bottom[3, 0] = 1.0
    assert _refusal(bad_bottom).startswith("pose bottom row")
    assert _refusal(matrix(-np.diag([1.0, 1.0, 2.0]), [0, 0, 0])).startswith("pose is not rigid")
    assert _refusal(matrix(-np.eye(3), [0, 0, 0], 1e7)).startswith("pose is a reflection")


@pytest.mark.parametrize("block, entry", [(np.diag([1e200] * 3), "1e+200"),
                                          (np.diag([-1e300, 1.0, 1.0]), "1e+300"),
                                          (np.diag([1.0, 1.0, 2e154]), "2e+154")])
def test_a_block_whose_squares_overflow_is_refused_as_out_of_the_scale_range(block, entry):
    with np.errstate(all="raise"):  # quietly: no overflow warning escapes
        assert _refusal(matrix(block, [0, 0, 0])) == (
            f"pose scale is outside [1e-06, 1e+06]: its 3x3 block has an entry of {entry}")


def test_a_block_of_scale_squared_1e24_is_zero_and_one_above_is_out_of_range():
    assert _refusal(np.diag([1e-12, 1e-12, 1e-12, 1.0])) == "pose rotation block is zero (scale 0)"
    assert _refusal(np.diag([1.1e-12, 1.1e-12, 1.1e-12, 1.0])) == (
        "pose scale 1.1e-12 is outside [1e-06, 1e+06]")


def test_a_pose_within_the_rigidity_tolerance_is_accepted_and_one_beyond_is_not():
    # off-diagonal entries of the normalised Gram matrix: accepted up to ~1e-5, refused beyond
    shear = np.eye(3)
    shear[0, 1] = 4e-6  # Gram off-diagonal ~4e-6
    assert as_pose(matrix(shear, [0, 0, 0])).scale == 1.0
    shear[0, 1] = 4e-5
    assert _refusal(matrix(shear, [0, 0, 0])).startswith("pose is not rigid")


def test_the_rotation_is_reorthonormalised_and_the_scale_divided_out():
    rotation = random_rotation(11)
    noisy = rotation + 1e-7 * np.random.default_rng(12).normal(size=(3, 3))
    pose = as_pose(matrix(noisy, [0, 0, 0], 3.0))
    assert pose.scale == pytest.approx(3.0, rel=1e-6)
    np.testing.assert_allclose(pose.rotation @ pose.rotation.T, np.eye(3), rtol=0, atol=4e-15)
    np.testing.assert_allclose(pose.rotation, rotation, rtol=0, atol=1e-6)
    assert np.linalg.det(pose.rotation) == pytest.approx(1.0, abs=1e-14)
