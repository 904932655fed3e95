"""Queries against a real server: same numbers as the engine in process, over JSON and msgpack;
the scene query; model listing; every kind of bad input answered with a problem document."""

from __future__ import annotations

import json
import math

import httpx
import msgpack
import numpy as np
import pytest

from collider_contract import FIELDS, wire

from .conftest import ServerThread

ALL_FIELDS = list(FIELDS)


def rotation_pose(angle: float, axis: int, translation) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    pose = np.eye(4)
    pose[i, i], pose[i, j], pose[j, i], pose[j, j] = c, -s, s, c
    pose[:3, 3] = translation
    return pose


def sample_points(n: int, seed: int, dtype=np.float64) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.15, 0.15, (n, 3)).astype(dtype)


def post(url: str, body: dict, media: str = wire.MSGPACK, headers=None) -> httpx.Response:
    return httpx.post(url, content=wire.dumps(body, media),
                      headers={"content-type": media, **(headers or {})}, timeout=30)


def decode(response: httpx.Response) -> dict:
    assert response.status_code == 200, response.text
    body = wire.loads(response.content, response.headers["content-type"])
    return {k: (v if k in ("model",) else wire.decode_array(v, k)) for k, v in body.items()}


def test_health_and_model_info(server, engine):
    assert httpx.get(f"{server.url}/livez").json() == {"status": "ok"}
    ready = httpx.get(f"{server.url}/readyz").json()
    assert ready["status"] == "ready" and ready["models"] == ["small", "sphere"]
    listed = httpx.get(f"{server.url}/v1/models").json()["models"]
    assert [m["name"] for m in listed] == ["small", "sphere"]
    info = httpx.get(f"{server.url}/v1/models/sphere").json()
    assert {"name", "kind", "units", "meters_per_unit", "domain_min", "domain_max", "bytes",
            "approximate", "accuracy", "source", "settings", "device"} <= set(info)
    assert info["kind"] == "voxel" and info["device"] == "cpu" and info["bytes"] > 32 ** 3 * 4
    np.testing.assert_allclose(info["domain_min"], engine["sphere"].info.domain_min)


@pytest.mark.parametrize("media", [wire.JSON, *wire.MSGPACK_TYPES])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_query_matches_the_engine(server, engine, media, dtype):
    points = sample_points(300, 1, dtype)
    pose = rotation_pose(0.7, 2, [0.01, -0.02, 0.03])
    body = {"points": points, "fields": ALL_FIELDS, "pose": pose, "eps": 0.004}
    got = decode(post(f"{server.url}/v1/models/sphere/query", body, media))
    want = engine["sphere"].query(points, ALL_FIELDS, pose=pose, eps=0.004).fields()
    assert got["model"] == "sphere"
    for name in ALL_FIELDS:
        if media == wire.JSON:
            np.testing.assert_array_equal(np.asarray(got[name], want[name].dtype), want[name])
        else:
            assert got[name].dtype == want[name].dtype
            np.testing.assert_array_equal(got[name], want[name])


def test_default_fields_and_eps(server, engine):
    points = sample_points(50, 2)
    got = decode(post(f"{server.url}/v1/models/sphere/query", {"points": points}))
    assert set(got) == {"distance", "model"}
    np.testing.assert_array_equal(got["distance"], engine["sphere"].query(points).distance)
    collides = decode(post(f"{server.url}/v1/models/sphere/query",
                           {"points": points, "fields": ["collides"]}))["collides"]
    np.testing.assert_array_equal(collides, engine["sphere"].query(points, "collides").collides)


def test_accept_header_picks_the_response_encoding(server, engine):
    points = sample_points(20, 3)
    response = httpx.post(f"{server.url}/v1/models/sphere/query",
                          content=json.dumps({"points": points.tolist()}),
                          headers={"content-type": "application/json",
                                   "accept": "application/msgpack"})
    assert response.headers["content-type"] == "application/msgpack"
    np.testing.assert_array_equal(decode(response)["distance"], engine["sphere"].query(points).distance)


def test_empty_points(server):
    got = decode(post(f"{server.url}/v1/models/sphere/query",
                      {"points": np.empty((0, 3)), "fields": ALL_FIELDS}))
    assert got["distance"].shape == (0,) and got["normal"].shape == (0, 3)


def test_scene_query_answers_the_nearest_collider(server, engine):
    points = sample_points(400, 4) * 2
    poses = [rotation_pose(0.3, 0, [-0.1, 0, 0]), rotation_pose(1.1, 1, [0.12, 0.02, 0])]
    body = {"points": points, "fields": ALL_FIELDS, "eps": 0.002,
            "colliders": [{"model": "sphere", "pose": wire.encode_array(poses[0])},
                          {"model": "small", "pose": wire.encode_array(poses[1])}]}
    got = decode(post(f"{server.url}/v1/scene/query", body))
    each = [engine[name].query(points, ALL_FIELDS, pose=pose, eps=0.002).fields()
            for name, pose in zip(["sphere", "small"], poses)]
    nearest = np.where(each[1]["distance"] < each[0]["distance"], 1, 0)
    assert got["collider"].dtype == np.int32
    np.testing.assert_array_equal(got["collider"], nearest)
    assert 50 < nearest.sum() < 350  # both colliders win somewhere
    for name in ALL_FIELDS:
        want = np.where(nearest[:, None] if each[0][name].ndim == 2 else nearest,
                        each[1][name], each[0][name])
        np.testing.assert_array_equal(got[name], want)


def test_scene_query_over_json(server, engine):
    points = sample_points(10, 5)
    body = {"points": points.tolist(), "colliders": [{"model": "small"}]}
    response = httpx.post(f"{server.url}/v1/scene/query", json=body)
    got = response.json()
    assert got["collider"] == [0] * 10
    np.testing.assert_array_equal(np.float32(got["distance"]), engine["small"].query(points).distance)


# -- bad input --------------------------------------------------------------------------------

GOOD = {"points": np.zeros((4, 3))}


def arr(dtype, shape, data=None):
    data = np.zeros(shape, dtype).tobytes() if data is None else data
    return {"dtype": np.dtype(dtype).str, "shape": list(shape), "data": data}


def pack(body) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


NAN_POINTS = np.zeros((4, 3))
NAN_POINTS[2, 1] = np.nan
INF_POSE = np.eye(4)
INF_POSE[0, 3] = np.inf
SHEAR_POSE = np.eye(4)
SHEAR_POSE[0, 1] = 0.5
REFLECT_POSE = np.diag([1.0, 1.0, -1.0, 1.0])

BAD_BODIES = {
    # name: (content type, raw body, status, problem type, words the detail must hold)
    "malformed-json": ("application/json", b'{"points": [[0, 0, 0]', 400, "malformed-body", "json"),
    "malformed-msgpack": ("application/msgpack", b"\xc1\xc1\xc1", 400, "malformed-body", "msgpack"),
    "not-a-map": ("application/json", b"[1, 2, 3]", 400, "malformed-body", "map"),
    "missing-points": ("application/json", b'{"fields": ["distance"]}', 422, "missing-points", "points"),
    "unknown-key": ("application/json", b'{"points": [[0,0,0]], "feilds": []}', 422, "unknown-key", "feilds"),
    "wrong-shape": ("application/msgpack", pack({"points": arr("<f8", (4, 2))}), 422, "bad-points", "(n, 3)"),
    "wrong-dtype": ("application/msgpack", pack({"points": arr("<i4", (4, 3))}), 422, "bad-points", "float32"),
    "bad-dtype-name": ("application/msgpack", pack({"points": arr("<f8", (4, 3)) | {"dtype": "<c16"}}),
                       422, "bad-points", "dtype"),
    "short-data": ("application/msgpack", pack({"points": arr("<f8", (4, 3), b"\0" * 10)}), 422,
                   "bad-points", "bytes"),
    "ragged-json": ("application/json", b'{"points": [[0, 0, 0], [1, 2]]}', 422, "bad-points", "ragged"),
    "nan-points": ("application/msgpack", wire.dumps({"points": NAN_POINTS}), 422, "bad-points", "row 2"),
    "nan-points-json": ("application/json", b'{"points": [[0, NaN, 0]]}', 422, "bad-points", "NaN"),
    "inf-pose": ("application/msgpack", wire.dumps({**GOOD, "pose": INF_POSE}), 422, "bad-pose", "Inf"),
    "shear-pose": ("application/msgpack", wire.dumps({**GOOD, "pose": SHEAR_POSE}), 422, "bad-pose", "rigid"),
    "reflect-pose": ("application/msgpack", wire.dumps({**GOOD, "pose": REFLECT_POSE}), 422, "bad-pose",
                     "reflection"),
    "pose-shape": ("application/msgpack", wire.dumps({**GOOD, "pose": np.eye(3)}), 422, "bad-pose", "4x4"),
    "unknown-field": ("application/json", b'{"points": [[0,0,0]], "fields": ["distance", "curvature"]}',
                      422, "unknown-field", "curvature"),
    "fields-not-list": ("application/json", b'{"points": [[0,0,0]], "fields": "distance"}', 422,
                        "bad-fields", "list"),
    "negative-eps": ("application/json", b'{"points": [[0,0,0]], "eps": -0.001}', 422,
                     "eps-out-of-range", "eps=-0.001"),
    "huge-eps": ("application/json", b'{"points": [[0,0,0]], "eps": 2e6}', 422, "eps-out-of-range", "1e+06"),
    "eps-not-number": ("application/json", b'{"points": [[0,0,0]], "eps": "small"}', 422, "bad-eps", "eps"),
    "bad-deadline": ("application/json", b'{"points": [[0,0,0]], "deadline_ms": -5}', 422,
                     "bad-deadline-ms", "deadline_ms"),
    "text-plain": ("text/plain", b"0 0 0", 415, "unsupported-media-type", "text/plain"),
    # JSON integers have no size limit; one too large for a float is still a number error.
    "huge-int-eps": ("application/json", b'{"points": [[0,0,0]], "eps": 1' + b"0" * 400 + b"}", 422,
                     "bad-eps", "finite"),
    "huge-int-deadline": ("application/json", b'{"points": [[0,0,0]], "deadline_ms": 1' + b"0" * 400
                          + b"}", 422, "bad-deadline-ms", "finite"),
}


@pytest.mark.parametrize("case", sorted(BAD_BODIES))
def test_bad_input_gets_a_problem_and_the_server_keeps_serving(server, engine, case):
    media, raw, status, code, words = BAD_BODIES[case]
    response = httpx.post(f"{server.url}/v1/models/sphere/query", content=raw,
                          headers={"content-type": media})
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/problem+json"
    problem = response.json()
    assert problem["type"] == code and problem["status"] == status and problem["title"]
    assert words.lower() in problem["detail"].lower(), problem["detail"]
    points = sample_points(5, 6)
    got = decode(post(f"{server.url}/v1/models/sphere/query", {"points": points}))
    np.testing.assert_array_equal(got["distance"], engine["sphere"].query(points).distance)


@pytest.mark.parametrize("header, words", [("soon", "number"), ("-5", "> 0"), ("inf", "finite")])
def test_bad_deadline_header_is_bad_deadline_ms(server, header, words):
    response = httpx.post(f"{server.url}/v1/models/sphere/query", content=b'{"points": [[0,0,0]]}',
                          headers={"content-type": "application/json", "X-Deadline-Ms": header})
    assert response.status_code == 422 and response.json()["type"] == "bad-deadline-ms"
    assert words in response.json()["detail"] and "X-Deadline-Ms" in response.json()["detail"]


def test_unknown_model_and_route(server):
    response = post(f"{server.url}/v1/models/teapot/query", GOOD)
    assert response.status_code == 404 and response.json()["type"] == "unknown-model"
    assert "sphere" in response.json()["detail"]  # names the models there are
    assert httpx.get(f"{server.url}/v1/models/teapot").status_code == 404
    scene = post(f"{server.url}/v1/scene/query", {**GOOD, "colliders": [{"model": "nope"}]})
    assert scene.status_code == 404 and "nope" in scene.json()["detail"]
    assert httpx.get(f"{server.url}/v2/nothing").json()["type"] == "not-found"


def test_bad_scene_colliders(server):
    for colliders in ([], [{"pose": wire.encode_array(np.eye(4))}], [{"model": "sphere", "extra": 1}], "sphere"):
        response = post(f"{server.url}/v1/scene/query", {**GOOD, "colliders": colliders})
        assert response.status_code == 422 and response.json()["type"] == "bad-colliders"
    bad_pose = post(f"{server.url}/v1/scene/query",
                    {**GOOD, "colliders": [{"model": "sphere"}, {"model": "small", "pose": wire.encode_array(SHEAR_POSE)}]})
    assert bad_pose.status_code == 422 and "colliders[1].pose" in bad_pose.json()["detail"]


def test_size_limits_answer_413(repo):
    with ServerThread(models=repo, device="cpu", max_body_bytes=4096, max_request_points=100,
                      max_scene_colliders=2) as server:
        big_body = post(f"{server.url}/v1/models/sphere/query", {"points": np.zeros((300, 3))})
        assert big_body.status_code == 413 and big_body.json()["type"] == "body-too-large"
        # The same body without a Content-Length (chunked) is cut off while reading too.
        chunked = httpx.post(f"{server.url}/v1/models/sphere/query",
                             content=iter([wire.dumps({"points": np.zeros((300, 3))})]),
                             headers={"content-type": wire.MSGPACK})
        assert chunked.status_code == 413
        many = post(f"{server.url}/v1/models/sphere/query", {"points": np.zeros((101, 3), np.float32)})
        assert many.status_code == 413 and many.json()["type"] == "too-many-points"
        assert "max_request_points=100" in many.json()["detail"]
        scene = post(f"{server.url}/v1/scene/query", {**GOOD, "colliders": [{"model": "sphere"}] * 3})
        assert scene.status_code == 413 and scene.json()["type"] == "too-many-colliders"
        ok = post(f"{server.url}/v1/models/sphere/query", {"points": np.zeros((100, 3), np.float32)})
        assert ok.status_code == 200


def test_openapi_page_documents_the_routes_and_bodies(server):
    schema = httpx.get(f"{server.url}/openapi.json").json()
    assert {"/v1/models", "/v1/models/{name}", "/v1/models/{name}/query", "/v1/scene/query",
            "/v1/admin/models/{name}", "/livez", "/readyz", "/metrics"} <= set(schema["paths"])
    body = schema["paths"]["/v1/models/{name}/query"]["post"]["requestBody"]["content"]
    assert set(body) == {"application/msgpack", "application/json"}
    assert "points" in body["application/msgpack"]["schema"]["required"]
    assert httpx.get(f"{server.url}/docs").status_code == 200


def test_a_server_on_cuda_answers_as_the_cpu_engine(cuda):
    """``collider serve --device cuda`` over the shipped models (grid networks, the exact animated
    arm): the networks on the GPU, the exact kind on the CPU (libigl), and their answers through
    the SDK those of the CPU engine."""
    import collider_client as cc
    from collider_cli.launch import ServerProcess
    from collider_server.engine.devices import device_of
    from collider_server.engine.repository import ModelRepository

    repository = ModelRepository()
    names = [n for n in ("bunny", "arm") if repository.path(n).is_file()]
    if not names:
        pytest.skip("no shipped models")
    server = ServerProcess(repository.root, "--device", cuda, "--log-level", "warning")
    try:
        server.wait_ready(120)
        with cc.Client(server.url, timeout_s=60) as remote, \
                cc.Client(models=repository.root, device="cpu") as embedded:
            served = {m.name: m.device for m in remote.list_models()}
            assert served == {m.name: device_of(m.kind, "cuda") for m in embedded.list_models()}
            with cc.Client(models=repository.root, device=cuda) as on_gpu:
                assert {m.name: m.device for m in on_gpu.list_models()} == served
            for name in names:
                info = next(m for m in embedded.list_models() if m.name == name)
                lo, hi = np.asarray(info.domain_min), np.asarray(info.domain_max)
                points = lo + np.random.default_rng(9).random((20_000, 3)) * (hi - lo)
                time = 0.37 if info.animation else None
                fields = ["distance", "normal", "contact"] + (["velocity"] if time is not None else [])
                a = embedded.query(name, points, fields, time=time)
                b = remote.query(name, points, fields, time=time)
                scale = float(np.abs(a.distance).max())
                np.testing.assert_allclose(b.distance, a.distance, rtol=0, atol=1e-5 * scale)
                np.testing.assert_allclose(b.contact, a.contact, rtol=0, atol=1e-4 * scale)  # |d| x normal's
                agree = np.einsum("ij,ij->i", a.normal, b.normal) > np.cos(np.radians(0.1))
                assert agree.mean() > 0.999, name
    finally:
        server.stop()
