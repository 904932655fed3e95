"""Skeletons, clips and linear blend skinning on small hand-made skeletons with known answers."""

import math

import numpy as np
import pytest

from collider_server.engine.skinning import (
    PERTURB_DEG,
    Channel,
    Clip,
    Skeleton,
    Skin,
    pose_at,
    random_poses,
    skin_velocities,
    skin_vertices,
    trs_matrices,
    world_transforms,
)

IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])


def z_quaternion(angle):
    """(x, y, z, w) of a rotation by ``angle`` radians about +z."""
    return np.array([0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)])


def two_joint_skeleton(root=np.eye(4)):
    """A root at the origin and a child 1 m along +x; inverse binds from the rest pose."""
    parents = np.array([-1, 0])
    translation = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    rotation = np.stack([IDENTITY_Q, IDENTITY_Q])
    scale = np.ones((2, 3))
    rest_world = world_transforms(
        Skeleton(("a", "b"), parents, translation, rotation, scale, np.tile(np.eye(4), (2, 1, 1)),
                 root), trs_matrices(translation, rotation, scale))
    return Skeleton(("a", "b"), parents, translation, rotation, scale,
                    np.linalg.inv(rest_world), root)


def two_joint_skin(clips=()):
    """Three vertices: one on the root, one half-and-half, one on the child (x = 0, 1, 2); a
    degenerate face list is enough for skinning."""
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    joints = np.array([[0, 1], [0, 1], [1, 0]])
    weights = np.array([[1.0, 0.0], [0.5, 0.5], [1.0, 0.0]])
    return Skin(vertices, np.array([[0, 1, 2]]), joints, weights, two_joint_skeleton(), clips)


def local_pose(skeleton, child_rotation=IDENTITY_Q, child_translation=(1.0, 0.0, 0.0)):
    t = skeleton.rest_translation.copy()
    t[1] = child_translation
    r = skeleton.rest_rotation.copy()
    r[1] = child_rotation
    return world_transforms(skeleton, trs_matrices(t, r, skeleton.rest_scale))


def test_the_rest_pose_gives_the_rest_vertices():
    skin = two_joint_skin()
    np.testing.assert_allclose(skin_vertices(skin, skin.skeleton.rest_world()), skin.vertices,
                               atol=1e-15)


def test_a_known_rotation_moves_the_vertices_where_expected():
    skin = two_joint_skin()
    pose = local_pose(skin.skeleton, z_quaternion(math.pi / 2))
    out = skin_vertices(skin, pose)
    # the child's vertex 1 m beyond the elbow turns to +y; the half-weighted one sits on the elbow
    # (both joints put it at (1, 0, 0)); the root's vertex stays
    np.testing.assert_allclose(out, [[0, 0, 0], [1, 0, 0], [1, 1, 0]], atol=1e-12)
    # a half-and-half vertex off the elbow: the average of where each joint takes it
    skin2 = Skin(np.array([[1.0, 0.5, 0.0]]), np.zeros((0, 3)), np.array([[0, 1]]),
                 np.array([[0.5, 0.5]]), skin.skeleton)
    np.testing.assert_allclose(skin_vertices(skin2, pose), [[0.75, 0.25, 0.0]], atol=1e-12)


def test_the_root_transform_applies_to_every_joint():
    root = np.eye(4)
    root[:3, 3] = [0.0, 0.0, 5.0]
    skeleton = two_joint_skeleton(root)
    np.testing.assert_allclose(skeleton.rest_world()[1][:3, 3], [1.0, 0.0, 5.0])
    skin = Skin(np.array([[2.0, 0.0, 5.0]]), np.zeros((0, 3)), np.array([[1]]), np.array([[1.0]]),
                skeleton)
    out = skin_vertices(skin, local_pose(skeleton, z_quaternion(math.pi)))
    np.testing.assert_allclose(out, [[0.0, 0.0, 5.0]], atol=1e-12)


def test_linear_rotation_is_slerp_along_the_shortest_arc():
    # 0 -> 90 degrees about z; the second key stored as -q (the same rotation) must not go the
    # long way round
    for sign in (1.0, -1.0):
        channel = Channel(1, "rotation", "LINEAR", [0.0, 1.0],
                          [IDENTITY_Q, sign * z_quaternion(math.pi / 2)])
        q, dq = channel.sample(0.5)
        assert abs(abs(q @ z_quaternion(math.pi / 4)) - 1.0) < 1e-12
        # the angular rate is the angle over the interval: |dq/dt| = (pi/2) / 2 per second
        assert abs(np.linalg.norm(dq) - math.pi / 4) < 1e-12
    # slerp runs at a constant angular rate: at u = 0.25 the angle is 22.5 degrees, not lerp's
    channel = Channel(0, "rotation", "LINEAR", [0.0, 2.0], [IDENTITY_Q, z_quaternion(2.0)])
    q, _ = channel.sample(0.5)
    assert abs(2 * math.atan2(q[2], q[3]) - 0.5) < 1e-12


def test_step_holds_the_key_at_or_before_the_time():
    channel = Channel(0, "translation", "STEP", [0.0, 1.0, 2.0], [[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    assert channel.sample(0.99)[0][0] == 0.0
    assert channel.sample(1.0)[0][0] == 1.0
    assert channel.sample(1.5)[0][0] == 1.0
    assert not np.any(channel.sample(1.5)[1])


def test_cubicspline_scales_the_tangents_by_the_interval():
    # p0 = 0 with out-tangent 1 /s, p1 = 1 with in-tangent 0, over 2 s: at the middle
    # h00 p0 + h10 (2 * 1) + h01 p1 + h11 (2 * 0) = 0.125 * 2 + 0.5 = 0.75
    values = np.zeros((2, 3, 3))
    values[0, 2, 0] = 1.0
    values[1, 1, 0] = 1.0
    channel = Channel(0, "translation", "CUBICSPLINE", [0.0, 2.0], values)
    assert abs(channel.sample(1.0)[0][0] - 0.75) < 1e-15
    # the rate at the first key is the out-tangent (per second), and is d/dt of the value
    assert abs(channel.sample(0.0)[1][0] - 1.0) < 1e-12
    h = 1e-6
    for t in (0.3, 1.0, 1.7):
        fd = (channel.sample(t + h)[0] - channel.sample(t - h)[0]) / (2 * h)
        np.testing.assert_allclose(channel.sample(t)[1], fd, atol=1e-8)


def test_values_outside_a_channels_range_are_clamped():
    channel = Channel(0, "translation", "LINEAR", [1.0, 2.0], [[1, 0, 0], [3, 0, 0]])
    for t, x in ((0.0, 1.0), (1.0, 1.0), (1.5, 2.0), (2.0, 3.0), (9.0, 3.0)):
        assert channel.sample(t)[0][0] == x
    assert not np.any(channel.sample(0.5)[1]) and not np.any(channel.sample(2.5)[1])
    assert channel.sample(1.5)[1][0] == 2.0


def bend_clip():
    """The elbow bends 0 -> 90 -> 0 degrees over 2 s (slerp), the child slides and grows, and
    the root turns by a cubic spline: every path and interpolation moves at once."""
    cubic = np.zeros((3, 3, 4))
    cubic[:, 1] = [IDENTITY_Q, z_quaternion(0.4), z_quaternion(0.1)]
    cubic[:, 0, 2] = [0.0, 0.3, -0.2]
    cubic[:, 2, 2] = [0.1, 0.3, 0.0]
    channels = (
        Channel(1, "rotation", "LINEAR", [0.0, 1.0, 2.0],
                [IDENTITY_Q, z_quaternion(math.pi / 2), IDENTITY_Q]),
        Channel(1, "translation", "LINEAR", [0.0, 2.0], [[1.0, 0, 0], [1.5, 0.2, 0]]),
        Channel(1, "scale", "LINEAR", [0.0, 2.0], [[1.0, 1, 1], [1.2, 0.9, 1]]),
        Channel(0, "rotation", "CUBICSPLINE", [0.0, 0.8, 2.0], cubic),
    )
    return Clip("bend", channels, 2.0)


def test_pose_velocities_are_the_time_derivative_of_the_pose():
    skin = two_joint_skin((bend_clip(),))
    h = 1e-6
    for t in (0.25, 0.5, 1.3, 1.9):
        pose, rates = pose_at(skin, "bend", t)
        fd = (pose_at(skin, "bend", t + h)[0] - pose_at(skin, "bend", t - h)[0]) / (2 * h)
        np.testing.assert_allclose(rates, fd, atol=1e-7)
        v = skin_velocities(skin, pose, rates)
        fd_v = (skin_vertices(skin, pose_at(skin, "bend", t + h)[0])
                - skin_vertices(skin, pose_at(skin, "bend", t - h)[0])) / (2 * h)
        np.testing.assert_allclose(v, fd_v, atol=1e-7)
        assert np.abs(v).max() > 0.1  # the clip moves: the comparison is not 0 == 0


def test_a_clip_loops_or_clamps_as_animations_do():
    skin = two_joint_skin((bend_clip(),))
    loop = pose_at(skin, None, 0.5 + 2.0 * 3)
    np.testing.assert_allclose(loop[0], pose_at(skin, "bend", 0.5)[0], atol=1e-12)
    np.testing.assert_allclose(loop[1], pose_at(skin, "bend", 0.5)[1], atol=1e-12)
    end, end_rates = pose_at(skin, "bend", 5.0, mode="clamp")
    np.testing.assert_allclose(end, pose_at(skin, "bend", 2.0 - 1e-12, mode="clamp")[0],
                               atol=1e-9)
    assert not np.any(end_rates)
    _, start_rates = pose_at(skin, "bend", -1.0, mode="clamp")
    assert not np.any(start_rates)


def test_bad_skeletons_skins_and_clips_are_refused_by_name():
    skeleton = two_joint_skeleton()
    with pytest.raises(ValueError, match="parent"):
        Skeleton(("a", "b"), [1, -1], skeleton.rest_translation, skeleton.rest_rotation,
                 skeleton.rest_scale, skeleton.inverse_bind)
    with pytest.raises(ValueError, match="sum to 1"):
        Skin(np.zeros((1, 3)), np.zeros((0, 3)), [[0, 1]], [[0.5, 0.6]], skeleton)
    with pytest.raises(ValueError, match="do not exist"):
        Skin(np.zeros((1, 3)), np.zeros((0, 3)), [[0, 2]], [[0.5, 0.5]], skeleton)
    with pytest.raises(ValueError, match="increase"):
        Channel(0, "translation", "LINEAR", [0.0, 0.0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"\[2, 3, 4\]"):
        Channel(0, "rotation", "CUBICSPLINE", [0.0, 1.0], np.zeros((2, 4)))
    with pytest.raises(ValueError, match="no clip 'run'; the clips are \\['bend'\\]"):
        pose_at(two_joint_skin((bend_clip(),)), "run", 0.0)
    with pytest.raises(ValueError, match=r"\[2, 4, 4\]"):
        skin_vertices(two_joint_skin(), np.zeros((3, 4, 4)))


def local_transforms(skeleton, world):
    """(J, 4, 4) each joint's local transform from its world transform (J, 4, 4): the parent's (or
    the root's) inverse times its own, independently of how the pose was made."""
    above = np.stack([skeleton.root if p < 0 else world[p] for p in skeleton.parents])
    return np.linalg.inv(above) @ world


def test_random_poses_turn_every_joint_within_the_bound_and_are_reproducible():
    from collider_server.making.skinned import skinned_arm

    skin = skinned_arm()
    poses = random_poses(skin, 40, seed=7, perturbed_share=0.5)
    assert poses.transforms.shape == (40, skin.skeleton.joint_count, 4, 4)
    assert poses.perturbed.tolist() == [False] * 20 + [True] * 20
    assert set(poses.clips) == set(skin.clip_names)
    turns = []
    for i in range(40):
        clip = skin.clip(poses.clips[i])
        assert 0.0 <= poses.times[i] <= clip.duration_s
        recorded, _ = pose_at(skin, poses.clips[i], poses.times[i])
        # The turn of each joint's local rotation away from the clip's at that time.
        clip_local, local = local_transforms(skin.skeleton, recorded), local_transforms(skin.skeleton, poses.transforms[i])
        relative = np.swapaxes(clip_local[:, :3, :3], 1, 2) @ local[:, :3, :3]
        cosine = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
        turns.append(np.degrees(np.arccos(cosine)))
        # Translations as the clip has them: every joint's origin relative to its parent.
        np.testing.assert_allclose(local[:, :3, 3], clip_local[:, :3, 3], atol=1e-12)
    turns = np.array(turns)
    assert turns[:20].max() < 1e-5  # clip poses: as recorded
    assert turns[20:].max() <= PERTURB_DEG + 1e-6  # perturbed: within the bound ...
    assert turns[20:].max() > 0.8 * PERTURB_DEG and turns[20:].mean() > 0.3 * PERTURB_DEG  # ... and up to it
    again = random_poses(skin, 40, seed=7, perturbed_share=0.5)
    np.testing.assert_array_equal(again.transforms, poses.transforms)
    assert again.clips == poses.clips
    other = random_poses(skin, 40, seed=8, perturbed_share=0.5)
    assert not np.allclose(other.transforms, poses.transforms)
    with pytest.raises(ValueError, match="perturbed_share in"):
        random_poses(skin, 4, seed=1, perturbed_share=1.5)
