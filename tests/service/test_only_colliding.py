"""Collide-only queries through the service: the ``only_colliding`` body flag on the model and
scene queries (msgpack and JSON), the batcher joining collide-only requests with others, and the
SDK (remote and embedded) giving the same answers. Units: metres; voxel spheres (conftest)."""

from __future__ import annotations

import asyncio

import httpx
import numpy as np
import pytest

from collider_contract import FIELDS, wire

from .test_queries import decode, post, rotation_pose

ALL_FIELDS = list(FIELDS)


def shell_points(n: int, seed: int, radius=0.1, band=0.006) -> np.ndarray:
    """Points within ``band`` of a sphere of ``radius`` (metres): about half collide at 2 mm."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * (radius + rng.uniform(-band, band, n))[:, None]


def assert_documented_answer(got: dict, full: dict, points: np.ndarray):
    """Colliding points as in the full answer; the others normal 0 and contact = the point."""
    hit = np.asarray(full["collides"], bool)
    assert 0 < hit.sum() < len(hit)
    np.testing.assert_array_equal(np.asarray(got["collides"], bool), hit)
    np.testing.assert_array_equal(np.float32(got["distance"]), full["distance"])
    # Equal up to rounding: the gradient pass sees fewer points (other chunking of the sums).
    np.testing.assert_allclose(np.float32(got["normal"])[hit], full["normal"][hit], atol=1e-6)
    np.testing.assert_allclose(np.asarray(got["contact"], points.dtype)[hit], full["contact"][hit], atol=1e-9)
    assert not np.float32(got["normal"])[~hit].any()
    np.testing.assert_array_equal(np.asarray(got["contact"], points.dtype)[~hit], points[~hit])


@pytest.mark.parametrize("media", [wire.MSGPACK, wire.JSON])
def test_model_query_with_only_colliding(server, engine, media):
    pose = rotation_pose(0.4, 1, [0.02, 0.0, -0.01])
    points = shell_points(400, 2) @ pose[:3, :3].T + pose[:3, 3]
    body = {"points": points, "fields": ALL_FIELDS, "pose": pose, "eps": 0.002, "only_colliding": True}
    got = decode(post(f"{server.url}/v1/models/sphere/query", body, media))
    full = engine["sphere"].query(points, ALL_FIELDS, pose=pose, eps=0.002).fields()
    assert_documented_answer(got, full, points)


def test_scene_query_with_only_colliding(server, engine):
    poses = [rotation_pose(0.3, 0, [-0.1, 0, 0]), rotation_pose(1.1, 1, [0.12, 0.02, 0])]
    points = np.concatenate([shell_points(300, 3) + poses[0][:3, 3],
                             shell_points(300, 4, radius=0.05) + poses[1][:3, 3]])
    colliders = [{"model": "sphere", "pose": poses[0].tolist()}, {"model": "small", "pose": poses[1].tolist()}]
    body = {"points": points, "fields": ALL_FIELDS, "eps": 0.002, "colliders": colliders}
    full = decode(post(f"{server.url}/v1/scene/query", body))
    got = decode(post(f"{server.url}/v1/scene/query", {**body, "only_colliding": True}))
    np.testing.assert_array_equal(got["collider"], full["collider"])
    assert set(np.unique(full["collider"][full["collides"]])) == {0, 1}  # both colliders hit
    assert_documented_answer(got, full, points)


@pytest.mark.parametrize("value", ["yes", 1, None, [True]])
def test_only_colliding_must_be_a_boolean(server, value):
    body = {"points": np.zeros((2, 3)), "only_colliding": value}
    for media in (wire.MSGPACK, wire.JSON):
        response = post(f"{server.url}/v1/models/sphere/query", body, media)
        assert response.status_code == 422 and response.json()["type"] == "bad-only-colliding"
        assert response.json()["detail"] == (
            "only_colliding must not be null (leave it out for its default)" if value is None
            else f"only_colliding must be true or false, got {value!r}")


def test_openapi_documents_only_colliding(server):
    schema = httpx.get(f"{server.url}/openapi.json").json()
    for path in ("/v1/models/{name}/query", "/v1/scene/query"):
        body = schema["paths"][path]["post"]["requestBody"]["content"]["application/json"]["schema"]
        assert body["properties"]["only_colliding"]["type"] == "boolean"


@pytest.mark.parametrize("scene", [False, True])
def test_sdk_remote_and_embedded_agree(server, repo, scene):
    import collider_client as cc

    points = shell_points(300, 5)
    with cc.Client(server.url) as remote, cc.Client(models=repo, device="cpu") as embedded:
        answers = []
        for client in (remote, embedded):
            if scene:
                answers.append(client.scene_query(["sphere", ("small", np.eye(4))], points, ALL_FIELDS,
                                                  eps=0.002, only_colliding=True))
            else:
                answers.append(client.query("sphere", points, ALL_FIELDS, eps=0.002, only_colliding=True))
        full = (remote.scene_query(["sphere", ("small", np.eye(4))], points, ALL_FIELDS, eps=0.002) if scene
                else remote.query("sphere", points, ALL_FIELDS, eps=0.002))
    for name in ALL_FIELDS:
        np.testing.assert_array_equal(getattr(answers[0], name), getattr(answers[1], name), err_msg=name)
    assert_documented_answer({k: getattr(answers[0], k) for k in ALL_FIELDS},
                             {k: getattr(full, k) for k in ALL_FIELDS}, points)


@pytest.mark.parametrize("asynchronous", [False, True])
def test_async_client_sends_only_colliding(server, asynchronous):
    import collider_client as cc

    points = shell_points(200, 6)

    async def ask():
        async with cc.AsyncClient(server.url) as client:
            return await client.query("sphere", points, ["normal", "collides"], eps=0.002, only_colliding=True)

    if asynchronous:
        result = asyncio.run(ask())
    else:
        with cc.Client(server.url) as client:
            result = client.query("sphere", points, ["normal", "collides"], eps=0.002, only_colliding=True)
    assert not result.normal[~result.collides].any()
    np.testing.assert_allclose(np.linalg.norm(result.normal[result.collides], axis=1), 1, atol=1e-5)


def test_a_batch_joins_collide_only_jobs_with_others(repo):
    """One compute call for a batch holding a collide-only job, a job wanting every normal and
    one wanting none: each gets its own answer, the collide-only one's gradient work only for its
    colliding points."""
    from collider_contract import ModelQuery, as_pose
    from collider_server.engine.repository import ModelRepository
    from collider_server.service.batching import BatchPart
    from collider_server.service.query_jobs import QueryJob, answer_batch

    collider = ModelRepository(repo).load("sphere", "cpu")  # a fresh one: its method is wrapped
    calls = []
    query_local = collider.query_local

    def recording(local, want_gradient, below=None, time=None):
        calls.append((len(local), want_gradient, None if below is None else np.array(below)))
        return query_local(local, want_gradient, below, time)

    collider.query_local = recording
    pose = as_pose(rotation_pose(0.5, 2, [0.01, 0, 0]))
    only, full, plain = (shell_points(n, s) for n, s in ((200, 8), (150, 9), (100, 10)))
    jobs = [QueryJob(ModelQuery(only, tuple(ALL_FIELDS), pose, 0.002, only_colliding=True)),
            QueryJob(ModelQuery(full, tuple(ALL_FIELDS), pose, 0.002)),
            QueryJob(ModelQuery(plain, ("distance",), pose, 0.002))]
    answers = answer_batch(collider, "sphere", [BatchPart(j, 0, len(j.query.points)) for j in jobs])
    assert [c[:2] for c in calls] == [(450, True)]
    threshold = 0.002 + 1e-9 * 0.002
    np.testing.assert_allclose(calls[0][2], np.concatenate([np.full(200, threshold), np.full(150, np.inf),
                                                            np.full(100, -np.inf)]))
    engine = ModelRepository(repo).load("sphere", "cpu")
    for job, answer in zip(jobs, answers):
        q = job.query
        want = engine.query(q.points, q.fields, pose=pose, eps=0.002).fields()
        assert set(answer) == set(q.fields)
        if q.only_colliding:
            assert_documented_answer(answer, want, q.points)
        else:
            for name in q.fields:
                np.testing.assert_array_equal(answer[name], want[name])
