"""The skeleton pose of a skinned collider's query (collider_contract.skeleton): a clip at a time
or joint transforms (J, 4, 4) with optional velocities, checked and refused in one line; whether
a pose fits a model's skeleton; a clip as a timeline (Timeline.of_clip, ModelInfo.clip_timeline).
Collider frame and units, seconds; no torch."""

from __future__ import annotations

import numpy as np
import pytest

from collider_contract import (
    ModelInfo,
    ModelQuery,
    QueryError,
    SceneCollider,
    SceneQuery,
    SkeletonPose,
    Timeline,
    check_skeleton_pose,
    skeleton,
    wire,
)
from collider_contract.skeleton import MAX_CLIP_NAME, require_skeleton_pose


def joints(count: int = 3) -> np.ndarray:
    """(count, 4, 4) float64: rigid joint transforms, joint j turned j * 0.3 rad about z and
    moved j * 0.1 along x, collider frame."""
    out = np.tile(np.eye(4), (count, 1, 1))
    for j in range(count):
        c, s = np.cos(0.3 * j), np.sin(0.3 * j)
        out[j, :2, :2] = [[c, -s], [s, c]]
        out[j, 0, 3] = 0.1 * j
    return out


SKELETON = {"joints": ["hip", "knee", "foot"], "parents": [-1, 0, 1], "loop": True,
            "clips": [{"name": "walk", "duration_s": 1.2, "max_surface_speed": 0.8},
                      {"name": "wave", "duration_s": 2.5, "max_surface_speed": 0.3}]}


def test_a_pose_is_a_clip_or_joint_transforms_with_their_velocities():
    assert check_skeleton_pose() is None
    assert check_skeleton_pose(clip="walk") == SkeletonPose(clip="walk")
    name = "w" * MAX_CLIP_NAME  # the longest name is accepted
    assert check_skeleton_pose(clip=name).clip == name
    velocities = np.zeros((3, 4, 4))
    velocities[1, 0, 3] = 0.5  # joint 1 moves along x at 0.5 units/s
    pose = check_skeleton_pose(joint_transforms=joints().tolist(), joint_velocities=velocities.tolist())
    assert pose.clip is None
    for given, got in ((joints(), pose.joint_transforms), (velocities, pose.joint_velocities)):
        assert isinstance(got, np.ndarray) and got.dtype == np.float64 and got.shape == (3, 4, 4)
        np.testing.assert_array_equal(got, given)
    assert check_skeleton_pose(joint_transforms=joints(1)).joint_velocities is None


def test_a_pose_has_at_most_max_joints(monkeypatch):
    # MAX_JOINTS lowered: 4,096 joints' rigidity checks take seconds, the bound is the same rule
    monkeypatch.setattr(skeleton, "MAX_JOINTS", 4)
    assert len(check_skeleton_pose(joint_transforms=joints(4)).joint_transforms) == 4
    with pytest.raises(QueryError, match=r"^joint_transforms must have shape \(J, 4, 4\) with "
                                         r"1 <= J <= 4, got \[5, 4, 4\]$"):
        check_skeleton_pose(joint_transforms=joints(5))


def test_poses_that_break_a_rule_are_refused_in_one_line_naming_the_key():
    sheared = joints()
    sheared[1, 0, 1] += 0.3
    far = joints()
    far[2, 1, 3] = 1e9
    moving_bottom = np.zeros((3, 4, 4))
    moving_bottom[0, 3, 3] = 1.0
    where = "colliders[1]."
    cases = [
        ({"clip": ""}, "bad-clip", ("colliders[1].clip must be a clip's name (a string of 1 to 256 "
         "characters), got ''")),
        ({"clip": "w" * (MAX_CLIP_NAME + 1)}, "bad-clip", "colliders[1].clip must be a clip's name"),
        ({"clip": 3}, "bad-clip", "got 3"),
        ({"joint_transforms": "hip"}, "bad-joint-transforms",
         "colliders[1].joint_transforms must be a (J, 4, 4) array of numbers: could not convert"),
        ({"joint_transforms": joints()[:, :3]}, "bad-joint-transforms",
         "colliders[1].joint_transforms must have shape (J, 4, 4) with 1 <= J <= 4096, got [3, 3, 4]"),
        ({"joint_transforms": joints()[0]}, "bad-joint-transforms", "got [4, 4]"),
        ({"joint_transforms": np.zeros((0, 4, 4))}, "bad-joint-transforms", "got [0, 4, 4]"),
        ({"joint_transforms": sheared}, "bad-joint-transforms",
         "colliders[1].joint_transforms[1] is not rigid: its 3x3 block is not a rotation"),
        ({"joint_transforms": far}, "bad-joint-transforms",
         "colliders[1].joint_transforms[2] translation [0.2, 1000000000.0, 0.0] is outside"),
        ({"joint_transforms": joints(), "joint_velocities": [[1, 2]]}, "bad-joint-velocities",
         "colliders[1].joint_velocities must have shape (J, 4, 4) with 1 <= J <= 4096, got [1, 2]"),
        ({"joint_transforms": joints(), "joint_velocities": moving_bottom}, "bad-joint-velocities",
         "colliders[1].joint_velocities[0] bottom row must be [0, 0, 0, 0]"),
        ({"joint_velocities": np.zeros((3, 4, 4))}, "bad-joint-velocities",
         "colliders[1].joint_velocities needs colliders[1].joint_transforms"),
        ({"joint_transforms": joints(), "joint_velocities": np.zeros((2, 4, 4))},
         "bad-joint-velocities", ("colliders[1].joint_velocities has shape [2, 4, 4], "
         "colliders[1].joint_transforms [3, 4, 4]: they must match")),
        ({"clip": "walk", "joint_transforms": joints()}, "bad-joint-transforms",
         "give colliders[1].clip (with a time) or colliders[1].joint_transforms, not both"),
    ]
    for kwargs, code, message in cases:
        with pytest.raises(QueryError) as caught:
            check_skeleton_pose(**kwargs, where=where)
        assert (caught.value.code, caught.value.status) == (code, 422), kwargs
        assert message in str(caught.value), (kwargs, str(caught.value))
        assert "\n" not in str(caught.value)
    # without a prefix, the keys' own names
    with pytest.raises(QueryError, match=r"^joint_transforms\[1\] is not rigid"):
        check_skeleton_pose(joint_transforms=sheared)
    with pytest.raises(QueryError, match=r"^joint_velocities needs joint_transforms$"):
        check_skeleton_pose(joint_velocities=np.zeros((3, 4, 4)))


def test_equal_poses_share_a_key_and_the_wire_form_holds_only_what_is_given():
    velocities = np.full((3, 4, 4), 0.25)
    velocities[:, 3] = 0.0
    a = SkeletonPose(joint_transforms=joints(), joint_velocities=velocities)
    b = SkeletonPose(joint_transforms=joints(), joint_velocities=velocities.copy())
    assert a.key() == b.key() and hash(a.key()) == hash(b.key())
    other = [SkeletonPose(joint_transforms=joints()),
             SkeletonPose(joint_transforms=joints(), joint_velocities=2 * velocities),
             SkeletonPose(joint_transforms=joints(4)[1:], joint_velocities=velocities),
             SkeletonPose(clip="walk"), SkeletonPose()]
    keys = {a.key()} | {pose.key() for pose in other}
    assert len(keys) == 1 + len(other)
    assert SkeletonPose(clip="walk").key() == SkeletonPose(clip="walk").key() != SkeletonPose("wave").key()

    assert SkeletonPose().to_body() == {}
    assert SkeletonPose(clip="walk").to_body() == {"clip": "walk"}
    assert SkeletonPose(clip="walk").to_body(nested=True) == {"clip": "walk"}
    body = a.to_body()
    assert sorted(body) == ["joint_transforms", "joint_velocities"]
    assert body["joint_transforms"] is a.joint_transforms and body["joint_velocities"] is velocities
    nested = a.to_body(nested=True)
    assert nested == {"joint_transforms": joints().tolist(), "joint_velocities": velocities.tolist()}
    assert type(nested["joint_transforms"]) is list
    assert SkeletonPose(joint_transforms=joints()).to_body(nested=True) == {
        "joint_transforms": joints().tolist()}
    # the wire form reads back to the same pose
    assert check_skeleton_pose(**nested).key() == a.key()


def test_a_pose_must_fit_the_model_it_asks():
    def refused(pose, time, skeleton) -> QueryError:
        with pytest.raises(QueryError) as caught:
            require_skeleton_pose(pose, time, skeleton, "model 'leg'")
        assert caught.value.status == 422 and "\n" not in str(caught.value)
        return caught.value

    # a model without a skeleton: any skeleton pose is refused, no pose is fine
    for bare in ({}, None):
        require_skeleton_pose(None, 0.5, bare, "model 'leg'")
        require_skeleton_pose(None, None, bare, "model 'leg'")
    error = refused(SkeletonPose(clip="walk"), 0.5, {})
    assert (error.code, str(error)) == (
        "not-skinned", "model 'leg' has no skeleton: clip is for skinned models only")
    error = refused(SkeletonPose(joint_transforms=joints(), joint_velocities=np.zeros((3, 4, 4))),
                    None, None)
    assert (error.code, str(error)) == (
        "not-skinned", ("model 'leg' has no skeleton: joint_transforms and joint_velocities are for "
        "skinned models only"))
    # a skinned model: joint transforms of its joint count, at any time or none
    require_skeleton_pose(SkeletonPose(joint_transforms=joints()), None, SKELETON, "model 'leg'")
    error = refused(SkeletonPose(joint_transforms=joints(2)), 0.5, SKELETON)
    assert (error.code, str(error)) == (
        "bad-joint-transforms", "model 'leg' has 3 joints, joint_transforms has 2")
    error = refused(SkeletonPose(joint_transforms=joints(1)), None, {"clips": SKELETON["clips"]})
    assert str(error) == "model 'leg' has 0 joints, joint_transforms has 1"
    # ... or a clip it has (none: its first) at a time
    for pose in (None, SkeletonPose(clip="walk"), SkeletonPose(clip="wave")):
        require_skeleton_pose(pose, 0.0, SKELETON, "model 'leg'")
    for pose in (None, SkeletonPose(clip="walk")):
        error = refused(pose, None, SKELETON)
        assert (error.code, str(error)) == (
            "missing-time", ("model 'leg' is skinned: give the time (seconds) to ask its clip at, "
            "or joint_transforms"))
    error = refused(SkeletonPose(clip="run"), 0.5, SKELETON)
    assert (error.code, str(error)) == (
        "unknown-clip", "model 'leg' has no clip 'run'; its clips are ['walk', 'wave']")
    without_clips = {"joints": SKELETON["joints"], "parents": SKELETON["parents"]}
    for clipless in (without_clips, {**without_clips, "clips": []}):
        error = refused(None, 0.5, clipless)
        assert (error.code, str(error)) == (
            "unknown-clip", "model 'leg' has no clips: give joint_transforms")


def test_a_clip_is_a_timeline_of_two_frames_over_its_duration():
    clip = Timeline.of_clip(2.5, True, 0.3)
    assert (clip.frames, clip.loop, clip.max_surface_speed) == (2, True, 0.3)
    assert clip.frame_rate_hz == pytest.approx(0.4) and clip.duration_s == pytest.approx(2.5)
    k, u, rate = clip.locate(3.5)  # looped: 1 s into the clip
    assert k == 0 and u == pytest.approx(0.4) and rate == pytest.approx(0.4)
    assert Timeline.of_clip(0.5, True).frame_rate_hz == 2.0  # under a second
    held = Timeline.of_clip(2, False)
    assert (held.frames, held.loop, held.max_surface_speed) == (2, False, 0.0)
    assert held.duration_s == 2.0 and held.locate(3.0) == (0, 1.0, 0.0)
    for duration in (0, 0.0, -1.0, float("nan"), float("inf"), True, "2", None):
        with pytest.raises(ValueError) as caught:
            Timeline.of_clip(duration, True)
        assert str(caught.value) == f"a clip's duration must be a number of seconds > 0, got {duration!r}"


def test_a_skinned_model_gives_each_clip_as_a_timeline():
    info = ModelInfo("leg", "skinned", skeleton=SKELETON)
    assert info.skinned and not ModelInfo("ball", "mesh").skinned
    walk = info.clip_timeline(None)  # the first clip
    assert (walk.frames, walk.loop, walk.max_surface_speed) == (2, True, 0.8)
    assert walk.duration_s == pytest.approx(1.2)
    wave = info.clip_timeline("wave")
    assert (wave.duration_s, wave.loop, wave.max_surface_speed) == (pytest.approx(2.5), True, 0.3)
    clamped = ModelInfo("leg", "skinned", skeleton={**SKELETON, "loop": False})
    assert clamped.clip_timeline("wave").loop is False
    unsaid = {k: v for k, v in SKELETON.items() if k != "loop"}  # looped unless it says
    assert ModelInfo("leg", "skinned", skeleton=unsaid).clip_timeline("walk").loop is True

    def message(info: ModelInfo, clip) -> str:
        with pytest.raises(ValueError) as caught:
            info.clip_timeline(clip)
        return str(caught.value)

    assert message(ModelInfo("ball", "mesh"), None) == (
        "model 'ball' has no skeleton: clip applies to skinned models")
    assert message(info, "run") == "model 'leg' has no clip 'run'; its clips: ['walk', 'wave']"
    for clipless in ({"joints": ["hip"], "clips": []}, {"joints": ["hip"]}):
        assert message(ModelInfo("leg", "skinned", skeleton=clipless), None) == (
            "model 'leg' has no clip None; its clips: []")
    old = {**SKELETON, "clips": [{"name": "walk", "duration_s": 1.2}]}
    assert message(ModelInfo("leg", "skinned", skeleton=old), "walk") == (
        "model 'leg''s clip 'walk' does not record max_surface_speed (made by an older version): "
        "make the model again")
    still = {**SKELETON, "clips": [SKELETON["clips"][0], {"name": "pose", "duration_s": 0.0,
                                                          "max_surface_speed": 0.0}]}
    assert message(ModelInfo("leg", "skinned", skeleton=still), "pose") == (
        "model 'leg''s clip 'pose': a clip's duration must be a number of seconds > 0, got 0.0")


def test_a_skeleton_pose_travels_in_a_model_query_and_back():
    velocities = np.zeros((3, 4, 4))
    velocities[2, 1, 3] = -0.2
    query = ModelQuery.build([[0.0, 0.0, 1.0]], "distance", time=0.5, clip="walk")
    body = query.to_body()
    assert body["clip"] == "walk" and "joint_transforms" not in body
    posed = ModelQuery.build([[0.0, 0.0, 1.0]], "velocity", joint_transforms=joints(),
                             joint_velocities=velocities)
    body = posed.to_body()
    assert body["joint_transforms"] is posed.skeleton.joint_transforms
    for media in (wire.MSGPACK, wire.JSON):
        for sent in (query, posed):
            got = ModelQuery.from_body(wire.loads(wire.dumps(sent.to_body(), media), media))
            assert got.skeleton.key() == sent.skeleton.key() and got.time == sent.time
    assert ModelQuery.build([[0.0, 0.0, 1.0]]).skeleton is None


def test_each_scene_collider_carries_its_own_skeleton_pose():
    velocities = np.zeros((3, 4, 4))
    velocities[0, 0, 3] = 1.0
    sent = SceneQuery.build([[0.0, 0.0, 1.0]], [
        SceneCollider("leg", clip="wave"),
        SceneCollider("arm", joint_transforms=joints(), joint_velocities=velocities),
        "ball"], time=0.25)
    assert [sent.of_collider(i).skeleton for i in range(3)] == [
        SkeletonPose(clip="wave"), sent.colliders[1].skeleton, None]
    assert sent.of_collider(1).skeleton.key() == SkeletonPose(None, joints(), velocities).key()
    colliders = sent.to_body()["colliders"]
    # nested in the list of colliders, arrays travel as nested lists
    assert colliders == [{"model": "leg", "time": 0.25, "clip": "wave"},
                         {"model": "arm", "time": 0.25, "joint_transforms": joints().tolist(),
                          "joint_velocities": velocities.tolist()},
                         {"model": "ball", "time": 0.25}]
    for media in (wire.MSGPACK, wire.JSON):
        got = SceneQuery.from_body(wire.loads(wire.dumps(sent.to_body(), media), media))
        assert [None if p.skeleton is None else p.skeleton.key() for p in got.colliders] == [
            SkeletonPose("wave").key(), SkeletonPose(None, joints(), velocities).key(), None]
    with pytest.raises(QueryError) as caught:
        SceneQuery.from_body({"points": [[0.0, 0.0, 1.0]], "colliders": [
            {"model": "ball"}, {"model": "leg", "clip": "wave", "joint_transforms": joints().tolist()}]})
    assert str(caught.value) == ("give colliders[1].clip (with a time) or colliders[1].joint_transforms, "
                                 "not both")


BOOLS = [[[True] * 4] * 4]


@pytest.mark.parametrize("extra, message, code", [
    ({"joint_transforms": "hip"}, "joint_transforms: expected an array (msgpack map or JSON list), got str",
     "bad-joint-transforms"),
    ({"joint_transforms": {"dtype": "<f8", "shape": [1, 4, 4], "data": b""}},
     "joint_transforms: data has 0 bytes but dtype <f8 and shape [1, 4, 4] need 128", "bad-joint-transforms"),
    ({"joint_transforms": BOOLS}, "joint_transforms: must hold numbers, got bool", "bad-joint-transforms"),
    ({"joint_transforms": wire.encode_array(np.zeros((1, 4, 4), bool))},
     "joint_transforms: must hold numbers, got bool", "bad-joint-transforms"),
    ({"joint_transforms": [np.eye(4).tolist()], "joint_velocities": "still"},
     "joint_velocities: expected an array (msgpack map or JSON list), got str", "bad-joint-velocities"),
    ({"joint_transforms": [np.eye(4).tolist()], "joint_velocities": BOOLS},
     "joint_velocities: must hold numbers, got bool", "bad-joint-velocities"),
    ({"clip": 3}, "clip must be a clip's name (a string of 1 to 256 characters), got 3", "bad-clip"),
    ({"clip": None}, "clip must not be null (leave it out for its default)", "bad-clip"),
    ({"joint_transforms": None}, "joint_transforms must not be null (leave it out for its default)",
     "bad-joint-transforms"),
])
def test_a_bad_skeleton_pose_in_a_body_is_refused_naming_the_key(extra, message, code):
    for body, where in (({"points": [[0.0, 0.0, 1.0]], **extra}, ""),
                        ({"points": [[0.0, 0.0, 1.0]], "colliders": [{"model": "ball"},
                                                                     {"model": "leg", **extra}]},
                         "colliders[1].")):
        with pytest.raises(QueryError) as caught:
            (SceneQuery if where else ModelQuery).from_body(body)
        assert (str(caught.value), caught.value.code) == (where + message, code)
