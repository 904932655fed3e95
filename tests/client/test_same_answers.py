"""Embedded and remote give the same outcome for every input: bit-identical answers, or the same
error type with the same message. The inputs are those of the hard-case suite
(tests/hard_cases/test_engine_hard_cases.py) and of the service's bad-input regression tests
(tests/service/test_queries.py, test_hardening.py, test_only_colliding.py) that the SDK can express;
both backends answer them through the query contract (collider_contract). Voxel sphere of radius
0.1 m and box at the origin (tests/client/conftest.py); world frame, metres."""

from __future__ import annotations

import json
import shutil

import httpx
import numpy as np
import pytest

import collider_client as cc
from collider_contract import MAX_COORDINATE_M, wire

ALL = ["distance", "normal", "contact", "collides"]
rng = np.random.default_rng(11)
NEAR = rng.uniform(-0.15, 0.15, size=(64, 3))


def pose(translation=(0.0, 0.0, 0.0), scale=1.0, angle_deg=0.0, block=None, bottom=(0, 0, 0, 1)):
    """A 4x4 collider -> world: rotation about z by ``angle_deg``, uniform ``scale``."""
    a = np.radians(angle_deg)
    m = np.eye(4)
    m[:3, :3] = scale * np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    if block is not None:
        m[:3, :3] = block
    m[:3, 3] = translation
    m[3] = bottom
    return m


def with_row(values, row, value, column=0, n=5):
    points = np.full((n, 3), 0.05) if values is None else np.array(values, dtype=float)
    points[row, column] = value
    return points


#: A pose velocity: spinning about z at 2 rad/s while moving at 0.5 m/s along x.
RATE = np.array([[0.0, -2.0, 0.0, 0.5], [2.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])


def _arm_pose():
    """The skinned arm's pose in clip "wave" at 0.3 s, each joint turned a little more: (3, 4, 4)
    joint transforms and their velocities, collider frame."""
    from collider_server.engine.skinning import pose_at
    from collider_server.making.skinned import skinned_arm

    transforms, rates = pose_at(skinned_arm(), "wave", 0.3)
    turn = pose(angle_deg=7.0)
    transforms[1:] = turn @ transforms[1:]
    sheared = transforms.copy()
    sheared[2, 0, 1] += 0.4
    return transforms, rates, sheared


ARM_POSE, ARM_RATES, ARM_SHEARED = _arm_pose()
#: Points around the skinned arm (0.5 m along +x, radius 0.04 m).
ARM_POINTS = rng.uniform([-0.1, -0.15, -0.1], [0.6, 0.15, 0.4], size=(300, 3))


def nan_pose():
    m = np.eye(4)
    m[1, 3] = np.nan
    return m


#: name -> (method, positional args after the model or colliders, keyword args)
CASES = {
    # answers: the hard cases
    "near-surface, every field": ("query", (NEAR,), {"fields": ALL}),
    "float32 points": ("query", (NEAR.astype(np.float32),), {"fields": ALL}),
    "integer points": ("query", ([[0, 0, 0], [1, 0, 0]],), {"fields": ALL}),
    "medial axis (the centre)": ("query", ([[0.0, 0.0, 0.0]],), {"fields": ALL}),
    "far, up to the coordinate range": ("query", ([[MAX_COORDINATE_M, -MAX_COORDINATE_M, 0.0],
                                                   [5e5, 0.0, 0.0], [0.0, 0.0, -1e4]],), {"fields": ALL}),
    "denormals and -0.0": ("query", ([[5e-324, -0.0, 0.0], [-0.0, -0.0, -0.0], [1e-310, 0.05, 0.0]],),
                           {"fields": ALL}),
    "empty (0, 3)": ("query", (np.zeros((0, 3)),), {"fields": ALL}),
    "empty list": ("query", ([],), {"fields": ALL}),
    "rotated, scaled pose": ("query", (NEAR,), {"fields": ALL, "pose": pose((0.3, -0.1, 2.0), 2.5, 30)}),
    "pose far away (1e4 m)": ("query", (NEAR + 1e4,), {"fields": ALL, "pose": pose((1e4, 1e4, 1e4))}),
    "largest translation": ("query", ([[MAX_COORDINATE_M * (1 - 1e-6), 0, 0]],),
                            {"fields": ALL, "pose": pose((MAX_COORDINATE_M * (1 - 1e-6), 0, 0))}),
    "eps 0": ("query", (NEAR,), {"fields": ALL, "eps": 0.0}),
    "eps at the coordinate range": ("query", (NEAR,), {"fields": ALL, "eps": MAX_COORDINATE_M}),
    "collide-only": ("query", (NEAR,), {"fields": ALL, "eps": 0.01, "only_colliding": True}),
    "one field by name": ("query", (NEAR,), {"fields": "collides"}),
    "velocity of a still collider": ("query", (NEAR,), {"fields": ["velocity", "contact"]}),
    "velocity of a moving frame": ("query", (NEAR,), {"fields": ALL + ["velocity"], "pose": pose((0.1, 0, 0), 2.0, 30),
                                                      "pose_velocity": RATE}),
    "collide-only velocity": ("query", (NEAR,), {"fields": ["velocity"], "eps": 0.01,
                                                 "only_colliding": True, "pose_velocity": RATE}),
    "a time, for a static collider": ("query", (NEAR,), {"fields": ALL, "time": 12.5}),
    "scene, times and pose velocities": ("scene", (NEAR,), {
        "colliders": [cc.SceneCollider("sphere", pose((0.02, 0, 0)), 1.0, RATE), "box"],
        "fields": ALL + ["velocity"], "time": 3.0}),
    # animated colliders: the exact kind and keyframe grids, at times between frames and beyond
    "animated exact, between frames": ("query", (NEAR,), {"model": "pulse", "fields": ALL + ["velocity"],
                                                          "time": 0.37}),
    "animated voxel, between keyframes": ("query", (NEAR,), {"model": "pulse-voxel",
                                                             "fields": ALL + ["velocity"], "time": 0.37}),
    "animated, looping past the end": ("query", (NEAR,), {"model": "pulse", "fields": ["distance", "velocity"],
                                                          "time": 12.29}),
    "animated, a negative time": ("query", (NEAR,), {"model": "pulse-voxel", "fields": ALL + ["velocity"],
                                                     "time": -0.61}),
    "animated, posed, moving, collide-only": ("query", (NEAR,), {
        "model": "pulse", "fields": ALL + ["velocity"], "time": 0.8, "pose": pose((0.02, 0, 0.01), 1.5, 20),
        "pose_velocity": RATE, "eps": 0.01, "only_colliding": True}),
    "scene, an animated and a static collider": ("scene", (NEAR,), {
        "colliders": [cc.SceneCollider("pulse", pose((0.03, 0, 0)), 0.3, RATE), "box"],
        "fields": ALL + ["velocity"]}),
    "scene, animated colliders at the scene's time": ("scene", (NEAR,), {
        "colliders": [{"model": "pulse"}, {"model": "pulse-voxel", "time": 0.1}],
        "fields": ALL + ["velocity"], "time": 0.45}),
    # a skinned collider: in a clip at a time, at joint transforms with their velocities
    "skinned, a clip at a time": ("query", (ARM_POINTS,), {"model": "arm", "fields": ALL + ["velocity"],
                                                           "time": 0.37, "clip": "wave"}),
    "skinned, the first clip, looping": ("query", (ARM_POINTS,), {"model": "arm", "fields": ALL,
                                                                  "time": 7.61}),
    "skinned, joint transforms and velocities": ("query", (ARM_POINTS,), {
        "model": "arm", "fields": ALL + ["velocity"], "joint_transforms": ARM_POSE,
        "joint_velocities": ARM_RATES, "pose": pose((0.02, 0, 0.01), 1.5, 20), "pose_velocity": RATE}),
    # the arm's articulated network (kind neural-skinned): the same skeleton pose keys
    "neural-skinned, a clip at a time": ("query", (ARM_POINTS,), {"model": "arm-neural",
                                                                  "fields": ALL + ["velocity"],
                                                                  "time": 0.37, "clip": "wave"}),
    "neural-skinned, joint transforms and velocities, collide-only": ("query", (ARM_POINTS,), {
        "model": "arm-neural", "fields": ALL + ["velocity"], "joint_transforms": ARM_POSE,
        "joint_velocities": ARM_RATES, "pose": pose((0.02, 0, 0.01), 1.5, 20), "eps": 0.01,
        "only_colliding": True}),
    "scene, a skinned collider at a pose and a static one": ("scene", (ARM_POINTS,), {
        "colliders": [cc.SceneCollider("arm", pose((0.01, 0, 0)), joint_transforms=ARM_POSE,
                                       joint_velocities=ARM_RATES),
                      {"model": "arm", "clip": "reach", "time": 1.2}, "box",
                      {"model": "arm-neural", "clip": "reach", "time": 0.9}],
        "fields": ALL + ["velocity"]}),
    "scene, two colliders": ("scene", (NEAR,), {"colliders": ["sphere", ("box", pose((0.05, 0, 0)))],
                                                "fields": ALL}),
    "scene, a tie (the same collider twice)": ("scene", (NEAR,), {"colliders": ["sphere", "sphere"],
                                                                 "fields": ALL}),
    "scene, collide-only, scaled": ("scene", (NEAR,), {"colliders": [("sphere", pose(scale=0.5)),
                                                                    {"model": "box"}],
                                                       "fields": ALL, "only_colliding": True}),
    # refusals: points
    "points beyond the coordinate range": ("query", (with_row(None, 3, MAX_COORDINATE_M * 1.000001, 1),), {}),
    "points at 1e39": ("query", ([[1e39, 0, 0]],), {}),
    "points at 1e300": ("query", (with_row(None, 1, 1e300),), {"fields": ALL}),
    "points at -1e300": ("query", (with_row(None, 3, -1e300, 1),), {}),
    "NaN point": ("query", (with_row(None, 2, np.nan),), {"fields": ALL}),
    "Inf point": ("query", (with_row(None, 2, np.inf),), {}),
    "-Inf point": ("query", (with_row(None, 2, -np.inf),), {}),
    "shape (4, 2)": ("query", (np.zeros((4, 2)),), {}),
    "shape (3,)": ("query", (np.zeros(3),), {}),
    "shape (2, 3, 3)": ("query", (np.zeros((2, 3, 3)),), {}),
    "ragged": ("query", ([[0, 0, 0], [1, 2]],), {}),
    "strings": ("query", ([["a", "b", "c"]],), {}),
    "booleans": ("query", ([[True, False, True]],), {}),
    "complex": ("query", (np.array([[1 + 2j, 0, 0]]),), {}),
    # refusals: pose
    "pose translation 2e6": ("query", (NEAR[:2],), {"pose": pose((0, 2 * MAX_COORDINATE_M, 0))}),
    "pose translation 1e300": ("query", (NEAR[:2],), {"pose": pose((0, 1e300, 0))}),
    "pose scale 1e300": ("query", (NEAR[:2],), {"pose": pose(scale=1e300)}),
    "pose scale 1e-7": ("query", (NEAR[:2],), {"pose": pose(scale=1e-7)}),
    "pose NaN": ("query", (NEAR[:2],), {"pose": nan_pose()}),
    "pose shear": ("query", (NEAR[:2],), {"pose": pose(block=[[1, 0.5, 0], [0, 1, 0], [0, 0, 1]])}),
    "pose non-uniform": ("query", (NEAR[:2],), {"pose": pose(block=np.diag([1.0, 2.0, 1.0]))}),
    "pose reflection": ("query", (NEAR[:2],), {"pose": pose(block=np.diag([1.0, 1.0, -1.0]))}),
    "pose scale 0": ("query", (NEAR[:2],), {"pose": pose(block=np.zeros((3, 3)))}),
    "pose bottom row": ("query", (NEAR[:2],), {"pose": pose(bottom=(0, 0, 1, 1))}),
    "pose 3x3": ("query", (NEAR[:2],), {"pose": np.eye(3)}),
    "pose of words": ("query", (NEAR[:2],), {"pose": "identity"}),
    # refusals: eps, fields
    "eps negative": ("query", (NEAR[:2],), {"eps": -1e-3}),
    "eps 2e6": ("query", (NEAR[:2],), {"eps": 2e6}),
    "eps 1000001": ("query", (NEAR[:2],), {"eps": MAX_COORDINATE_M + 1}),
    "eps 1e300": ("query", (NEAR[:2],), {"eps": 1e300}),
    "eps NaN": ("query", (NEAR[:2],), {"eps": float("nan")}),
    "eps Inf": ("query", (NEAR[:2],), {"eps": float("inf")}),
    "eps of words": ("query", (NEAR[:2],), {"eps": "small"}),
    "eps True": ("query", (NEAR[:2],), {"eps": True}),
    "unknown field": ("query", (NEAR[:2],), {"fields": ["distance", "curvature"]}),
    "time NaN": ("query", (NEAR[:2],), {"time": float("nan")}),
    "time 1e10": ("query", (NEAR[:2],), {"time": 1e10}),
    "time of words": ("query", (NEAR[:2],), {"time": "now"}),
    "pose velocity bottom row": ("query", (NEAR[:2],), {"pose_velocity": np.ones((4, 4))}),
    "pose velocity 3x3": ("query", (NEAR[:2],), {"pose_velocity": np.eye(3)}),
    "pose velocity Inf": ("query", (NEAR[:2],), {"pose_velocity": np.full((4, 4), np.inf)}),
    "scene collider time NaN": ("scene", (NEAR[:2],), {"colliders": [{"model": "sphere", "time": float("nan")}]}),
    "animated without a time": ("query", (NEAR[:2],), {"model": "pulse"}),
    "animated voxel without a time": ("query", (NEAR[:2],), {"model": "pulse-voxel", "fields": ALL}),
    "animated, time NaN": ("query", (NEAR[:2],), {"model": "pulse", "time": float("nan")}),
    "animated, time Inf": ("query", (NEAR[:2],), {"model": "pulse", "time": float("inf")}),
    "scene, an animated collider without a time": ("scene", (NEAR[:2],), {"colliders": ["sphere", "pulse"]}),
    "no field": ("query", (NEAR[:2],), {"fields": []}),
    "skinned without a time": ("query", (NEAR[:2],), {"model": "arm"}),
    "skinned, an unknown clip": ("query", (NEAR[:2],), {"model": "arm", "time": 0.1, "clip": "run"}),
    "skinned, too few joints": ("query", (NEAR[:2],), {"model": "arm", "joint_transforms": ARM_POSE[:2]}),
    "skinned, a sheared joint": ("query", (NEAR[:2],), {"model": "arm", "joint_transforms": ARM_SHEARED}),
    "skinned, joint velocities alone": ("query", (NEAR[:2],), {"model": "arm",
                                                               "joint_velocities": ARM_RATES}),
    "a clip for a model without a skeleton": ("query", (NEAR[:2],), {"time": 0.1, "clip": "wave"}),
    "scene, joint transforms for a model without a skeleton": ("scene", (NEAR[:2],), {
        "colliders": [{"model": "sphere", "joint_transforms": ARM_POSE}]}),
    # refusals: models, scenes
    "unknown model": ("query", (NEAR[:2],), {"model": "teapot"}),
    "scene without colliders": ("scene", (NEAR[:2],), {"colliders": []}),
    "scene collider without a model": ("scene", (NEAR[:2],), {"colliders": [{"pose": np.eye(4)}]}),
    "scene collider with an extra key": ("scene", (NEAR[:2],), {"colliders": [{"model": "sphere", "x": 1}]}),
    "scene collider of a number": ("scene", (NEAR[:2],), {"colliders": [3]}),
    "scene colliders as a name": ("scene", (NEAR[:2],), {"colliders": "sphere"}),
    "scene with a bad pose second": ("scene", (NEAR[:2],), {"colliders": [
        "sphere", ("box", pose(block=np.diag([1.0, 2.0, 1.0])))]}),
    "scene with an unknown model": ("scene", (NEAR[:2],), {"colliders": ["sphere", "nope"]}),
    "scene with NaN points": ("scene", (with_row(None, 4, np.nan),), {"colliders": ["sphere"]}),
}


@pytest.fixture(scope="module")
def backends(models_dir, server_url):
    with cc.Client(models=models_dir, device="cpu") as embedded, cc.Client(server_url, timeout_s=60) as remote:
        yield embedded, remote


def outcome(client: cc.Client, method: str, args, kwargs):
    """What a call gives: ``("answer", {name: array}, model)`` or ``("error", class, problem
    code, message)``."""
    kwargs = dict(kwargs)
    try:
        if method == "query":
            result = client.query(kwargs.pop("model", "sphere"), *args, **kwargs)
        else:
            result = client.scene_query(kwargs.pop("colliders"), *args, **kwargs)
    except cc.ColliderError as exc:
        return ("error", type(exc), getattr(exc, "type", None), str(exc))
    arrays = dict(result.fields())
    if result.collider is not None:
        arrays["collider"] = result.collider
    return ("answer", {name: np.array(value) for name, value in arrays.items()}, result.model)


def raw_body(method: str, args, kwargs) -> bytes | None:
    """The wire body of the same input, unvalidated (what a client in another language might
    send), or None when the input has no wire form (strings, complex numbers, ragged lists)."""
    kwargs = dict(kwargs)
    try:
        points = np.asarray(args[0])
        if points.dtype.kind not in "fiu":  # the SDK refuses them before they have a wire form
            return None
        if points.dtype.kind in "iu":
            points = points.astype(np.float64)  # as the SDK sends them
        body = {"points": points, **{k: v for k, v in kwargs.items()
                                     if k in ("eps", "only_colliding", "time", "clip")}}
        for key in ("pose_velocity", "joint_transforms", "joint_velocities"):
            if key in kwargs:
                body[key] = np.asarray(kwargs[key], dtype=np.float64)
        fields = kwargs.get("fields", ["distance"])
        body["fields"] = [fields] if isinstance(fields, str) else list(fields)
        if "pose" in kwargs:
            body["pose"] = np.asarray(kwargs["pose"], dtype=np.float64)
        if method == "scene":
            colliders = kwargs["colliders"]
            if isinstance(colliders, list):
                colliders = [{"model": c} if isinstance(c, str)
                             else {"model": c[0], "pose": np.asarray(c[1], float).tolist()}
                             if isinstance(c, tuple)
                             else {k: np.asarray(v).tolist()
                                   if k in ("pose", "pose_velocity", "joint_transforms",
                                            "joint_velocities") else v
                                   for k, v in c.items()}
                             if isinstance(c, dict) else c for c in colliders]
            body["colliders"] = colliders
        return wire.dumps(body, wire.MSGPACK)
    except (TypeError, ValueError):
        return None


@pytest.mark.parametrize("case", list(CASES))
def test_embedded_and_remote_give_the_same_outcome(backends, server_url, case):
    assert_same_outcome(backends, server_url, *CASES[case])


def assert_same_outcome(backends, server_url, method, args, kwargs):
    """Embedded and remote give the same answer, or the same error as the service's problem."""
    embedded, remote = (outcome(client, method, args, kwargs) for client in backends)
    assert embedded[0] == remote[0], (embedded, remote)
    if embedded[0] == "error":
        assert embedded[1:] == remote[1:]
        assert issubclass(embedded[1], cc.ServerError)  # inside the documented error tree
        # The service itself, sent the same input as a raw body: the same problem.
        raw = raw_body(method, args, kwargs)
        if raw is not None:
            path = ("/v1/scene/query" if method == "scene"
                    else f"/v1/models/{kwargs.get('model', 'sphere')}/query")
            response = httpx.post(server_url + path, content=raw,
                                  headers={"content-type": wire.MSGPACK})
            problem = response.json()
            error = embedded[1]
            assert (response.status_code, problem["type"], (f"{error.status} {problem['title']}: "
                    f"{problem['detail']}")) == (error.status, embedded[2], embedded[3])
        return
    assert embedded[2] == remote[2]  # the model name (None for a scene)
    assert embedded[1].keys() == remote[1].keys()
    for name, value in embedded[1].items():
        other = remote[1][name]
        assert value.dtype == other.dtype and value.shape == other.shape, name
        np.testing.assert_array_equal(value, other, err_msg=name)  # bit-identical


@pytest.mark.parametrize("method", ["query", "scene"])
def test_a_file_path_given_as_a_model_name_is_refused_alike(backends, server_url, models_dir, method):
    """A model is a name, never a file: the path of a model file that exists is refused by
    both backends as the service refuses it (404 ``unknown-model``, listing the models served)."""
    path = str(models_dir / "sphere.safetensors")
    kwargs = {"model": path} if method == "query" else {"colliders": ["box", path]}
    assert_same_outcome(backends, server_url, method, (NEAR[:2],), kwargs)
    error = outcome(backends[0], method, (NEAR[:2],), kwargs)
    assert error[:3] == ("error", cc.ModelNotFoundError, "unknown-model"), error
    assert error[3] == (f"404 Not found: no model named {path!r} "
                        "(models: arm, arm-neural, box, pulse, pulse-voxel, sphere)")


def test_an_embedded_client_of_an_empty_folder_refuses_a_file_path(tmp_path, models_dir):
    with cc.Client(models=tmp_path, device="cpu") as client:
        assert client.list_models() == []
        for name in (str(models_dir / "sphere.safetensors"), "sphere.safetensors", "sphere"):
            with pytest.raises(cc.ModelNotFoundError) as refused:
                client.query(name, NEAR[:2])
            assert refused.value.type == "unknown-model"
            assert str(refused.value) == f"404 Not found: no model named {name!r} (models: none)"


def test_embedded_and_remote_list_the_same_models(backends):
    embedded, remote = ([m.to_dict() for m in client.list_models()] for client in backends)
    assert [m["name"] for m in embedded] == ["arm", "arm-neural", "box", "pulse", "pulse-voxel", "sphere"]
    assert json.dumps(embedded, sort_keys=True) == json.dumps(remote, sort_keys=True)


def test_a_file_that_does_not_load_is_listed_by_neither(models_dir, tmp_path):
    """The service serves the models that load; the embedded backend lists the same."""
    from collider_cli.launch import ServerProcess

    shutil.copy(models_dir / "sphere.safetensors", tmp_path / "sphere.safetensors")
    (tmp_path / "broken.safetensors").write_bytes(b"not a model")
    server = ServerProcess(tmp_path, "--device", "cpu", "--log-level", "error")
    try:
        server.wait_ready(90)
        with cc.Client(models=tmp_path, device="cpu") as embedded, cc.Client(server.url) as remote:
            listed = [[m.to_dict() for m in client.list_models()] for client in (embedded, remote)]
            assert [m["name"] for m in listed[0]] == ["sphere"]
            assert json.dumps(listed[0], sort_keys=True) == json.dumps(listed[1], sort_keys=True)
    finally:
        server.stop()


def test_the_cases_cover_answers_and_every_refusal(backends):
    """The list above holds both kinds of outcome and every refusal the contract makes of
    values the SDK can send (the problem codes of docs/service.md)."""
    kinds, codes = set(), set()
    for method, args, kwargs in CASES.values():
        result = outcome(backends[0], method, args, kwargs)
        kinds.add(result[0])
        if result[0] == "error":
            codes.add(result[2])
    assert kinds == {"answer", "error"}
    assert codes == {"bad-points", "bad-pose", "eps-out-of-range", "bad-eps", "unknown-field",
                     "unknown-model", "bad-colliders", "bad-time", "bad-pose-velocity", "missing-time",
                     "unknown-clip", "bad-joint-transforms", "bad-joint-velocities", "not-skinned"}


@pytest.mark.parametrize("backend", [0, 1], ids=["embedded", "remote"])
def test_the_velocity_of_a_moving_frame_is_its_rigid_motion_at_the_contact(backends, backend):
    """A frame spinning about z at 2 rad/s and moving at 0.5 m/s along x (``RATE``, the pose's
    time derivative): at a contact c the surface moves at ``RATE @ [c_local, 1]`` with c_local
    the contact in the collider frame (here the identity pose: c itself). Still frame: zero."""
    client = backends[backend]
    result = client.query("sphere", NEAR, fields=["contact", "velocity", "collides"], pose_velocity=RATE)
    c = result.contact.astype(np.float64)
    expected = np.stack([0.5 - 2.0 * c[:, 1], 2.0 * c[:, 0], np.zeros(len(c))], axis=1)
    np.testing.assert_allclose(result.velocity, expected, rtol=1e-6, atol=1e-7)
    assert result.velocity.dtype == np.float32 and result.velocity.shape == (len(NEAR), 3)
    still = client.query("sphere", NEAR, fields=["velocity"])
    assert not still.velocity.any()
    # Collide-only: the free points' velocity is zero.
    only = client.query("sphere", NEAR, fields=["velocity", "collides"], pose_velocity=RATE,
                        only_colliding=True)
    assert only.collides.any() and not only.collides.all()
    np.testing.assert_array_equal(only.velocity[~only.collides], 0.0)
    np.testing.assert_allclose(only.velocity[only.collides], result.velocity[only.collides], atol=1e-7)


def test_a_skinned_pose_travels_in_json_as_in_msgpack_and_the_model_says_its_skeleton(backends, server_url):
    """The service's JSON body (nested lists) and the SDK's msgpack body (array maps) of the same
    skeleton pose get the same answer; ``GET /v1/models/arm`` names the joints and clips."""
    embedded, _ = backends
    expected = embedded.query("arm", ARM_POINTS, fields=["distance", "velocity"],
                              joint_transforms=ARM_POSE, joint_velocities=ARM_RATES)
    body = {"points": ARM_POINTS.tolist(), "fields": ["distance", "velocity"],
            "joint_transforms": ARM_POSE.tolist(), "joint_velocities": ARM_RATES.tolist()}
    response = httpx.post(f"{server_url}/v1/models/arm/query", json=body)
    assert response.status_code == 200, response.text
    answer = response.json()
    np.testing.assert_array_equal(np.float32(answer["distance"]), expected.distance)
    np.testing.assert_array_equal(np.float32(answer["velocity"]), expected.velocity)
    assert np.abs(expected.velocity).max() > 0.01
    model = httpx.get(f"{server_url}/v1/models/arm").json()
    assert model["kind"] == "skinned"
    assert model["skeleton"]["joints"] == ["shoulder", "elbow", "wrist"]
    assert [c["name"] for c in model["skeleton"]["clips"]] == ["wave", "reach"]
