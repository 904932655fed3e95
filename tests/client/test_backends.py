"""The remote backend (a real ``collider serve`` subprocess) and the embedded backend give the
same answers for the same calls, sync and async. World frame, metres."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

import collider_client as cc
from collider_client.sim.motion import euler_matrix

ALL_FIELDS = ["distance", "normal", "contact", "collides"]


def _pose(rotation_deg, translation):
    m = np.eye(4)
    m[:3, :3] = euler_matrix(np.asarray(rotation_deg, float))
    m[:3, 3] = translation
    return m


@pytest.fixture(scope="module")
def points():
    rng = np.random.default_rng(7)
    return rng.uniform(-0.2, 0.2, size=(500, 3))


@pytest.fixture(scope="module")
def embedded(models_dir):
    with cc.Client(models=models_dir, device="cpu") as client:
        yield client


@pytest.fixture(scope="module")
def remote(server_url):
    with cc.Client(server_url, timeout_s=60) as client:
        yield client


def _same(a: cc.QueryResult, b: cc.QueryResult, fields):
    for name in fields:
        x, y = getattr(a, name), getattr(b, name)
        assert x is not None and y is not None, name
        assert x.shape == y.shape and x.dtype == y.dtype, name
        # Bit-identical: the same engine code, the same float64 pose transforms and assembly.
        np.testing.assert_array_equal(x, y, err_msg=name)


def test_embedded_sphere_matches_analytic_distance(embedded, points):
    result = embedded.query("sphere", points, fields=["distance", "collides"])
    exact = np.linalg.norm(points, axis=1) - 0.1
    near = np.abs(exact) < 0.05
    assert np.abs(result.distance[near] - exact[near]).max() < 2e-3
    assert result.model == "sphere"
    assert np.array_equal(result.collides, result.distance < 1e-3)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_query_same_answers(embedded, remote, points, dtype):
    pose = _pose([30, -20, 45], [0.01, -0.02, 0.03])
    p = points.astype(dtype)
    a = embedded.query("sphere", p, fields=ALL_FIELDS, pose=pose, eps=2e-3)
    b = remote.query("sphere", p, fields=ALL_FIELDS, pose=pose, eps=2e-3)
    _same(a, b, ALL_FIELDS)
    assert a.contact.dtype == dtype
    assert b.model == "sphere"


def test_query_default_fields_and_eps_same(embedded, remote, points):
    a, b = embedded.query("box", points), remote.query("box", points)
    assert a.normal is None and b.normal is None
    _same(a, b, ["distance"])


def test_scene_query_same_answers_and_nearest(embedded, remote, points):
    scene = [("sphere", _pose([0, 0, 0], [0.15, 0, 0])), {"model": "box"},
             cc.SceneCollider("sphere", _pose([0, 0, 90], [-0.15, 0, 0]))]
    a = embedded.scene_query(scene, points, fields=ALL_FIELDS)
    b = remote.scene_query(scene, points, fields=ALL_FIELDS)
    _identical(a, b, ALL_FIELDS + ["collider"])
    assert a.collider.dtype == np.int32
    assert set(np.unique(a.collider)) == {0, 1, 2}
    # Nearest really is the smallest distance among the single-collider answers.
    singles = np.stack([
        embedded.query(s[0] if isinstance(s, tuple) else (s["model"] if isinstance(s, dict) else s.model),
                       points, pose=s[1] if isinstance(s, tuple) else (None if isinstance(s, dict) else s.pose)
                       ).distance for s in scene])
    np.testing.assert_allclose(a.distance, singles.min(axis=0), atol=1e-7)


def _identical(a: cc.QueryResult, b: cc.QueryResult, fields):
    """Bit-identical fields: both backends run the engine's one scene rule."""
    for name in fields:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.mark.parametrize("apart_m", [0.0, 1e-9, 1e-3])
def test_scene_ties_and_near_ties_resolve_the_same_in_both_backends(embedded, remote, points,
                                                                    apart_m):
    # One sphere placed twice (0, 1 nm or 1 mm apart): the distances tie or nearly tie at every
    # point. The rule (smallest float64 world distance, ties to the first) is the engine's, so the
    # index and every field agree exactly, and the nearest really is the smaller distance.
    scene = [("sphere", _pose([0, 0, 0], [0, 0, 0])), ("sphere", _pose([0, 0, 0], [apart_m, 0, 0]))]
    a = embedded.scene_query(scene, points, fields=ALL_FIELDS, eps=1e-3)
    b = remote.scene_query(scene, points, fields=ALL_FIELDS, eps=1e-3)
    _identical(a, b, ALL_FIELDS + ["collider"])
    if apart_m == 0.0:
        assert not a.collider.any()  # exact ties: always the first collider
    else:
        single = np.stack([embedded.query("sphere", points, pose=p).distance for _, p in scene])
        np.testing.assert_array_equal(a.distance, single.min(axis=0))
        assert a.collider.any() and not a.collider.all()


def _scaled_pose(rotation_deg, translation, scale):
    m = _pose(rotation_deg, translation)
    m[:3, :3] *= scale
    return m


@pytest.mark.parametrize("only_colliding", [False, True])
@pytest.mark.parametrize("fields", [ALL_FIELDS, ["distance", "collides"]], ids=["all", "no-gradient"])
@pytest.mark.parametrize("backend", ["embedded", "remote"])
def test_scene_fields_are_the_nearest_colliders_own(backend, request, points, fields,
                                                    only_colliding):
    """Per point, every field of a scene query is, bit for bit, what its nearest collider gives
    alone (same pose, that collider's own default eps: 1 mm times its pose's scale). The first
    collider, 5 m away, is nearest to no point; the sphere is scaled by 1.5 (radius 0.15 m)."""
    client = request.getfixturevalue(backend)
    scene = [("box", _pose([0, 0, 0], [5.0, 0, 0])),
             ("sphere", _scaled_pose([0, 0, 30], [0.1, 0, 0], 1.5)),
             ("box", _pose([20, 0, 0], [-0.1, 0, 0]))]
    # Points 0.5 to 1.5 mm outside the sphere: some within its 1.5 mm eps, not within 1 mm.
    directions = np.array([[1.0, 0, 0], [0.6, 0.8, 0], [0.6, 0, -0.8], [0.8, -0.36, 0.48]])
    offsets = np.linspace(0.5e-3, 1.5e-3, 5)
    near_sphere = np.array([0.1, 0, 0]) + directions[:, None] * (0.15 + offsets[:, None])
    p = np.concatenate([points, near_sphere.reshape(-1, 3)])
    result = client.scene_query(scene, p, fields=fields, eps=None, only_colliding=only_colliding)
    alone = [client.query(model, p, fields=ALL_FIELDS, pose=pose, eps=None,
                          only_colliding=only_colliding) for model, pose in scene]
    nearest, rows = result.collider, np.arange(len(p))
    assert nearest.dtype == np.int32 and nearest.shape == (len(p),)
    assert set(np.unique(nearest)) == {1, 2}
    distances = np.stack([a.distance for a in alone])
    np.testing.assert_array_equal(distances[nearest, rows], distances.min(axis=0))
    assert list(result.fields()) == fields
    for name in fields:
        expected = np.stack([getattr(a, name) for a in alone])[nearest, rows]
        value = getattr(result, name)
        assert value.dtype == expected.dtype and value.shape == expected.shape, name
        np.testing.assert_array_equal(value, expected, err_msg=name)
    between = (nearest == 1) & (result.distance > 1.01e-3) & (result.distance < 1.49e-3)
    assert between.sum() >= 2 and result.collides[between].all()
    if "normal" in fields:
        free = ~result.collides
        assert not result.normal[free].any() if only_colliding else result.normal[free].any()


def test_list_models_same(embedded, remote):
    a = {m.name: m for m in embedded.list_models()}
    b = {m.name: m for m in remote.list_models()}
    assert sorted(a) == sorted(b) == ["arm", "arm-neural", "box", "pulse", "pulse-voxel", "sphere"]
    kinds = {"pulse": "mesh", "arm": "skinned", "arm-neural": "neural-skinned"}
    for name in a:
        assert a[name].kind == b[name].kind == kinds.get(name, "voxel")
        np.testing.assert_allclose(a[name].domain_min, b[name].domain_min)
        np.testing.assert_allclose(a[name].domain_max, b[name].domain_max)
        assert a[name].bytes == b[name].bytes > 0
        # The animation, over the wire as in process: frames, rate, duration, loop, speed bound.
        assert a[name].animation == b[name].animation
        assert a[name].animated == (name in ("pulse", "pulse-voxel"))
    assert b["pulse"].animation == {"frames": 13, "frame_rate_hz": 12.0, "duration_s": 1.0,
                                    "loop": True, "max_surface_speed": a["pulse"].animation["max_surface_speed"]}
    assert b["pulse-voxel"].timeline.frames == 5 and b["pulse-voxel"].timeline.duration_s == 1.0
    assert b["pulse"].source["cache_sha256"] == a["pulse"].source["cache_sha256"]
    # The skeleton, over the wire as in process: joints, parents, clips, loop.
    speeds = [c["max_surface_speed"] for c in a["arm"].skeleton["clips"]]
    assert min(speeds) > 0
    assert a["arm"].skeleton == b["arm"].skeleton == {
        "joints": ["shoulder", "elbow", "wrist"], "parents": [-1, 0, 1], "loop": True,
        "clips": [{"name": "wave", "duration_s": 1.0, "max_surface_speed": speeds[0]},
                  {"name": "reach", "duration_s": 2.0, "max_surface_speed": speeds[1]}]}
    assert b["arm"].skinned and not b["pulse"].skinned
    assert a["arm-neural"].skeleton == b["arm-neural"].skeleton == b["arm"].skeleton and b["arm-neural"].skinned


@pytest.mark.parametrize("backend", ["embedded", "remote"])
def test_same_errors(backend, request, points):
    client = request.getfixturevalue(backend)
    with pytest.raises(cc.ModelNotFoundError):
        client.query("no-such-model", points)
    with pytest.raises(cc.InvalidValueError):
        client.query("sphere", np.zeros((4, 2)))
    with pytest.raises(cc.InvalidValueError):
        client.query("sphere", points, pose=np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(cc.InvalidValueError, match="unknown field"):
        client.query("sphere", points, fields=["distnace"])


def test_async_same_answers(models_dir, server_url, points):
    async def both():
        async with cc.AsyncClient(models=models_dir, device="cpu") as e, \
                cc.AsyncClient(server_url) as r:
            qa, qb = await asyncio.gather(e.query("sphere", points, fields=ALL_FIELDS),
                                          r.query("sphere", points, fields=ALL_FIELDS))
            sa = await e.scene_query(["sphere", "box"], points, fields=["distance"])
            sb = await r.scene_query(["sphere", "box"], points, fields=["distance"])
            la, lb = await e.list_models(), await r.list_models()
            return qa, qb, sa, sb, la, lb, await r.ready()

    qa, qb, sa, sb, la, lb, ready = asyncio.run(both())
    _same(qa, qb, ALL_FIELDS)
    _same(sa, sb, ["distance"])
    assert [m.name for m in la] == [m.name for m in lb]
    assert ready is True


def test_client_defaults_use_sentinel(models_dir, points):
    with cc.Client(models=models_dir, eps=0.05, fields=["collides"]) as client:
        wide = client.query("sphere", points)              # client default eps 5 cm
        narrow = client.query("sphere", points, eps=None)  # None = the model's 1 mm
    assert wide.distance is None and wide.collides is not None
    assert wide.collides.sum() > narrow.collides.sum()


def test_backend_choice_is_exclusive(models_dir):
    with pytest.raises(ValueError, match="not both"):
        cc.Client("http://127.0.0.1:1", models=models_dir)


def test_embedded_models_are_named_by_their_file(models_dir, tmp_path):
    import shutil

    shutil.copy(models_dir / "sphere.safetensors", tmp_path / "ball.safetensors")
    with cc.Client(models=tmp_path, device="cpu") as client:
        assert [m.name for m in client.list_models()] == ["ball"]
        assert client.query("ball", np.zeros((1, 3))).distance[0] < 0
