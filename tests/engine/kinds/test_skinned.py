"""The exact skinned kind against an independent evaluation: the test skins the mesh with its own
few lines of numpy and asks libigl (exact winding number) for the signed distance."""

import math

import igl
import numpy as np
import pytest

from collider_contract import QueryError, SkeletonPose
from collider_server.engine.kinds.skinned import SPEED_SAFETY
from collider_server.engine.meshes import Mesh
from collider_server.engine.modelfile import ModelFileError, load_collider, save_collider
from collider_server.engine.skinning import pose_at
from collider_server.making.bake import bake_collider
from collider_server.making.skinned import skinned_arm, skinned_collider


@pytest.fixture(scope="module")
def arm():
    skin = skinned_arm()
    return skin, skinned_collider(skin, "arm")


def own_skinning(skin, transforms):
    """Linear blend skinning written out: sum_k w_k (T_jk @ inverse_bind_jk) [v, 1]."""
    v = np.concatenate([skin.vertices, np.ones((len(skin.vertices), 1))], axis=1)
    out = np.zeros((len(v), 4))
    for k in range(skin.joints.shape[1]):
        m = transforms[skin.joints[:, k]] @ skin.skeleton.inverse_bind[skin.joints[:, k]]
        out += skin.weights[:, k, None] * np.einsum("vij,vj->vi", m, v)
    return out[:, :3]


def random_rotation(rng, max_deg):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = math.radians(rng.uniform(-max_deg, max_deg))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    return m


def perturbed(skin, transforms, rng, max_deg=15.0):
    """Each joint's local transform turned by a random rotation of up to ``max_deg`` about its
    own origin, the change carried down to its children."""
    parents = skin.skeleton.parents
    local = [transforms[j] if p < 0 else np.linalg.inv(transforms[p]) @ transforms[j]
             for j, p in enumerate(parents)]
    out = np.empty_like(transforms)
    for j, p in enumerate(parents):
        turned = local[j] @ random_rotation(rng, max_deg)
        out[j] = turned if p < 0 else out[p] @ turned
    return out


def test_distances_equal_libigl_on_the_skinned_mesh_at_20_random_poses(arm):
    skin, collider = arm
    rng = np.random.default_rng(7)
    worst, compared = 0.0, 0
    for i in range(20):
        clip = skin.clips[i % 2]
        base, _ = pose_at(skin, clip.name, rng.uniform(0, clip.duration_s))
        pose = perturbed(skin, base, rng)
        vertices = own_skinning(skin, pose)
        lo, hi = vertices.min(axis=0) - 0.05, vertices.max(axis=0) + 0.05
        surface = vertices[rng.integers(0, len(vertices), 300)]
        points = np.concatenate([rng.uniform(lo, hi, (300, 3)),
                                 surface + rng.normal(scale=0.003, size=surface.shape)])
        expected, _, _, _ = igl.signed_distance(points, vertices, skin.faces,
                                                igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER)
        winding = igl.winding_number(vertices, skin.faces, points)
        clear = (np.abs(winding) < 0.25) | (np.abs(winding - 1.0) < 0.25)
        got = collider.query(points, "distance", joint_transforms=pose).distance
        # float32 on the wire: compare the float64 evaluation itself, then the answer
        local, _, _ = collider.query_local(points, False, None, None,
                                           SkeletonPose(joint_transforms=pose))
        worst = max(worst, float(np.abs(local - expected)[clear].max()))
        np.testing.assert_allclose(got, expected, atol=1e-6)
        compared += int(clear.sum())
    assert worst <= 1e-6, worst
    assert compared > 20 * 500


def test_velocity_is_the_skinning_derivative_at_the_closest_point(arm):
    """For a fixed point, d(distance)/dt = -n . v_surface: the normal part of the answered
    velocity against a finite difference of the answered distances over the clip's time."""
    skin, collider = arm
    rng = np.random.default_rng(3)
    t, h = 0.37, 1e-5
    base, _ = pose_at(skin, "wave", t)
    surface = own_skinning(skin, base)[rng.integers(0, len(skin.vertices), 400)]
    points = surface + rng.normal(scale=0.01, size=surface.shape)
    at = collider.query(points, ["distance", "normal", "velocity"], time=t, clip="wave")
    ahead = collider.query(points, "distance", time=t + h, clip="wave").distance
    behind = collider.query(points, "distance", time=t - h, clip="wave").distance
    rate = (ahead.astype(np.float64) - behind) / (2 * h)
    normal_speed = -(at.normal * at.velocity).sum(axis=1)
    # the answers travel as float32: distances resolve ~1e-8 m, over 2e-5 s that is 1e-3 m/s
    np.testing.assert_allclose(normal_speed, rate, atol=5e-3)
    assert np.abs(at.velocity).max() > 0.1  # the arm moves: the comparison is not 0 == 0
    # the same pose as joint transforms with their velocities answers the same velocity
    transforms, velocities = pose_at(skin, "wave", t)
    by_joints = collider.query(points, "velocity", joint_transforms=transforms,
                               joint_velocities=velocities).velocity
    np.testing.assert_array_equal(by_joints, at.velocity)
    # without joint velocities the skeleton is still
    still = collider.query(points, "velocity", joint_transforms=transforms).velocity
    assert not still.any()


def test_a_repeated_pose_builds_nothing_and_the_last_poses_are_kept(arm):
    skin, _ = arm
    collider = skinned_collider(skin, "arm")
    points = np.zeros((5, 3))
    collider.query(points, time=0.1)
    collider.query(points, time=0.1)
    assert collider.builds == 1
    for t in (0.2, 0.3, 0.4):
        collider.query(points, time=t)
    collider.query(points, time=0.1)  # still among the last 4
    assert collider.builds == 4
    collider.query(points, time=0.5)
    collider.query(points, time=0.2)  # evicted by 0.5: built again
    assert collider.builds == 6
    collider.query(points, time=0.1, clip="reach")  # another clip is another pose
    assert collider.builds == 7


def test_a_clip_loops_or_clamps_as_the_model_says(arm):
    skin, looping = arm
    clamped = skinned_collider(skin, "arm", loop=False)
    points = np.random.default_rng(0).uniform(looping.domain_min, looping.domain_max, (200, 3))
    np.testing.assert_array_equal(looping.query(points, time=2.3).distance,
                                  looping.query(points, time=0.3).distance)
    np.testing.assert_array_equal(clamped.query(points, time=2.3).distance,
                                  clamped.query(points, time=1.0).distance)
    assert not clamped.query(points, "velocity", time=2.3).velocity.any()
    assert looping.query(points, "velocity", time=2.3).velocity.any()


def test_the_model_file_round_trips_and_refuses_what_does_not_fit(arm, tmp_path):
    skin, collider = arm
    path = save_collider(collider, tmp_path / "arm")
    loaded = load_collider(path)
    assert loaded.info.skeleton == collider.info.skeleton
    points = np.random.default_rng(1).uniform(collider.domain_min, collider.domain_max, (300, 3))
    for t, clip in ((0.3, "wave"), (1.3, "reach"), (0.9, None)):
        a = collider.query(points, ["distance", "normal", "velocity"], time=t, clip=clip)
        b = loaded.query(points, ["distance", "normal", "velocity"], time=t, clip=clip)
        for name in ("distance", "normal", "velocity"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    # a layout that names a channel the file does not hold
    broken = skinned_collider(skin, "arm")
    broken.info.settings["channels"] = broken.info.settings["channels"][:-1]
    with pytest.raises(ModelFileError, match="unexpected \\['channel.5.times'"):
        load_collider(save_collider(broken, tmp_path / "broken"))


def test_skeleton_poses_that_do_not_fit_are_refused_in_one_line(arm):
    skin, collider = arm
    points = np.zeros((3, 3))
    pose, _ = pose_at(skin, "wave", 0.2)
    sheared = pose.copy()
    sheared[1, 0, 1] += 0.3
    cases = [
        ({}, "missing-time", "model 'arm' is skinned: give the time"),
        ({"time": 0.1, "clip": "run"}, "unknown-clip", "has no clip 'run'; its clips are"),
        ({"joint_transforms": pose[:2]}, "bad-joint-transforms", "has 3 joints, joint_transforms has 2"),
        ({"joint_transforms": sheared}, "bad-joint-transforms", "joint_transforms[1] is not rigid"),
        ({"joint_transforms": pose[:, :3]}, "bad-joint-transforms", "must have shape (J, 4, 4)"),
        ({"joint_transforms": np.where(np.isnan(pose), 0, pose) * np.nan},
         "bad-joint-transforms", "joint_transforms[0] contains NaN"),
        ({"joint_velocities": np.zeros((3, 4, 4))}, "bad-joint-velocities",
         "joint_velocities needs joint_transforms"),
        ({"joint_transforms": pose, "joint_velocities": np.ones((3, 4, 4))}, "bad-joint-velocities",
         "joint_velocities[0] bottom row must be [0, 0, 0, 0]"),
        ({"time": 0.1, "clip": "wave", "joint_transforms": pose}, "bad-joint-transforms", "not both"),
        ({"time": 0.1, "clip": ""}, "bad-clip", "clip must be a clip's name"),
    ]
    for kwargs, code, message in cases:
        with pytest.raises(QueryError) as caught:
            collider.query(points, **kwargs)
        assert caught.value.code == code and message in str(caught.value), (kwargs, caught.value)
        assert "\n" not in str(caught.value)
    mesh = bake_collider(Mesh(skin.vertices, skin.faces, "rest"), "mesh", "rest")
    for kwargs in ({"clip": "wave", "time": 0.1}, {"joint_transforms": pose}):
        with pytest.raises(QueryError, match="model 'rest' has no skeleton: (clip|joint_transforms) is "
                                             "for skinned models only") as caught:
            mesh.query(points, **kwargs)
        assert caught.value.code == "not-skinned"


def test_each_clip_records_a_speed_no_vertex_exceeds(arm):
    """``max_surface_speed`` of each clip bounds every vertex's speed measured independently: the
    skin's own positions (own_skinning) differenced over 2,001 times across the clip (the 64x
    denser than sampled), the STEP wrist's jumps in "reach" (at 0.5 s and 1.5 s) left out: they
    have no speed. And it is not loose: within the safety factor of the fastest measured."""
    skin, collider = arm
    clips = {c["name"]: c for c in collider.info.skeleton["clips"]}
    assert set(clips) == {"wave", "reach"}
    for clip in skin.clips:
        recorded = clips[clip.name]["max_surface_speed"]
        times = np.linspace(0.0, clip.duration_s, 2001)
        positions = np.stack([own_skinning(skin, pose_at(skin, clip.name, t, "clamp")[0])
                              for t in times])
        speeds = np.linalg.norm(np.diff(positions, axis=0), axis=2).max(axis=1) / np.diff(times)
        jumps = np.zeros(len(speeds), bool)
        if clip.name == "reach":
            for key in (0.5, 1.5):
                jumps |= (times[:-1] <= key) & (times[1:] >= key)
        fastest = float(speeds[~jumps].max())
        assert 0.0 < fastest <= recorded <= SPEED_SAFETY * fastest * 1.02, clip.name
