"""The OpenAPI schema against the real server: a schema fuzzer (schemathesis) sends generated
bodies, valid and invalid, to every route of a uvicorn on loopback with all its checks on (no
5xx, every status and content type declared, responses matching their schemas, valid data
accepted, invalid data rejected, auth not ignored, 405 with a true Allow). Also the /docs page
served offline, and the schema and page behind the token."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from .conftest import ServerThread

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, settings

TOKEN = "fuzz-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: Examples per operation and phase: bounded so the suite stays quick; the fuzzer is seeded.
EXAMPLES = 25


@pytest.fixture(scope="module")
def fuzzed_server(repo):
    with ServerThread(models=repo, device="cpu", token=TOKEN, max_request_points=2000,
                      max_scene_colliders=4) as server:
        yield server


@pytest.fixture(scope="module")
def api_schema(fuzzed_server):
    schema = schemathesis.openapi.from_url(f"{fuzzed_server.url}/openapi.json", headers=AUTH)
    schema.config.update(base_url=fuzzed_server.url)
    return schema


def rigid(matrix) -> list:
    """A generated 4x4 matrix as a pose the server accepts: JSON Schema cannot say "rotation", so
    valid bodies keep the generated translation with an identity rotation."""
    m = np.eye(4)
    try:
        m[:3, 3] = np.asarray(matrix, dtype=np.float64)[:3, 3]
    except (TypeError, ValueError, IndexError):
        return matrix  # an invalid body stays invalid
    return m.tolist()


def rate(matrix) -> list:
    """A generated 4x4 matrix as a pose velocity the server accepts: its bottom row zero (a pose's
    bottom row does not change; JSON Schema cannot say so)."""
    try:
        m = np.array(matrix, dtype=np.float64)
        m[3] = 0.0
    except (TypeError, ValueError, IndexError):
        return matrix  # an invalid body stays invalid
    return m.tolist()


def adapt(case) -> None:
    """Aim generated requests where they test something: models that exist, poses that are
    rigid in valid bodies, and deadlines long enough that a 504 would be a real failure."""
    if "name" in (case.path_parameters or {}) and "/admin/" not in case.path:
        case.path_parameters["name"] = "sphere"
    body = case.body
    if not isinstance(body, dict):
        return
    positive = case.meta is not None and case.meta.generation.mode.is_positive
    # The fuzzed models have no skeleton: a skeleton pose is valid only for a skinned model, which
    # JSON Schema cannot say (such a pose is 422 not-skinned, tested in test_queries).
    for target in [body, *(c for c in body.get("colliders", []) if isinstance(c, dict))] \
            if isinstance(body.get("colliders", []), list) else [body]:
        for key in ("clip", "joint_transforms", "joint_velocities"):
            if positive:
                target.pop(key, None)
    if positive and "pose" in body:
        body["pose"] = rigid(body["pose"])
    if positive and "pose_velocity" in body:
        body["pose_velocity"] = rate(body["pose_velocity"])
    for collider in body.get("colliders", []) if isinstance(body.get("colliders"), list) else []:
        if positive and isinstance(collider, dict):
            collider["model"] = "small"
            if "pose" in collider:
                collider["pose"] = rigid(collider["pose"])
            if "pose_velocity" in collider:
                collider["pose_velocity"] = rate(collider["pose_velocity"])
    deadline = body.get("deadline_ms")
    if isinstance(deadline, (int, float)) and not isinstance(deadline, bool) and 0 < deadline:
        body["deadline_ms"] = max(float(deadline), 60_000.0)


#: Every operation of the schema (a test below keeps this list complete).
OPERATIONS = ("GET /livez", "GET /readyz", "GET /metrics", "GET /v1/models", "GET /v1/models/{name}",
              "POST /v1/models/{name}/query", "POST /v1/scene/query",
              "PUT /v1/admin/models/{name}", "DELETE /v1/admin/models/{name}")


def test_the_operations_list_is_complete(api_schema):
    labels = {result.ok().label for result in api_schema.get_all_operations()}
    assert labels == set(OPERATIONS)


@pytest.mark.parametrize("mode", ["positive", "negative"])
@pytest.mark.parametrize("label", OPERATIONS)
def test_the_server_matches_its_schema(api_schema, label, mode):
    from hypothesis import given
    from hypothesis.errors import Unsatisfiable

    operation = api_schema[label.split(" ", 1)[1]][label.split(" ", 1)[0]]
    strategy = operation.as_strategy(schemathesis.GenerationMode(mode))

    # (schemathesis' own pytest plugin does not run under this pytest; its strategies and checks
    # are used directly)
    @given(case=strategy)
    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    def check(case):
        adapt(case)
        case.call_and_validate(headers=AUTH, timeout=30)

    try:
        check()
    except Unsatisfiable:
        assert mode == "negative"
        pytest.skip(f"{label} takes no input, so no invalid input exists")


def test_docs_page_is_served_offline_and_the_schema_needs_the_token(fuzzed_server):
    url = fuzzed_server.url
    page = httpx.get(f"{url}/docs")
    assert page.status_code == 200 and "swagger-ui-bundle.js" in page.text
    assert "http://" not in page.text and "https://" not in page.text  # nothing from a CDN
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css"):
        served = httpx.get(f"{url}/docs/assets/{asset}")
        assert served.status_code == 200 and len(served.content) > 10_000
    assert httpx.get(f"{url}/docs/assets/..%2Fsecret").status_code == 404
    assert httpx.get(f"{url}/openapi.json").status_code == 401
    schema = httpx.get(f"{url}/openapi.json", headers=AUTH).json()
    query = schema["paths"]["/v1/models/{name}/query"]["post"]
    assert query["security"] == [{"token": []}]
    assert "security" not in schema["paths"]["/livez"]["get"]
    points = query["requestBody"]["content"]["application/json"]["schema"]["properties"]["points"]
    assert points["maxItems"] == 2000  # sized by the server's settings


def test_405_names_every_method_of_the_path(fuzzed_server):
    response = httpx.post(f"{fuzzed_server.url}/v1/admin/models/sphere")
    assert response.status_code == 405
    assert set(response.headers["allow"].split(", ")) == {"PUT", "DELETE"}
    get = httpx.delete(f"{fuzzed_server.url}/v1/models/sphere")
    assert get.status_code == 405 and set(get.headers["allow"].split(", ")) == {"GET"}
    assert response.json()["type"] == "method-not-allowed"


def test_metrics_are_declared_and_served_as_text(fuzzed_server):
    response = httpx.get(f"{fuzzed_server.url}/metrics", headers=AUTH)
    assert response.headers["content-type"].startswith("text/plain")


def test_the_query_operations_offer_json_first_with_examples_that_are_answered(fuzzed_server):
    """Issue 35, item 1: the /docs page sends the first media type and the examples as they are;
    both must be JSON and valid (test_docs_page presses the buttons in Chromium)."""
    schema = httpx.get(f"{fuzzed_server.url}/openapi.json", headers=AUTH).json()
    (parameter,) = schema["paths"]["/v1/models/{name}/query"]["post"]["parameters"]
    assert parameter["example"] == "small"  # the first model served
    for path in ("/v1/models/{name}/query", "/v1/scene/query"):
        content = schema["paths"][path]["post"]["requestBody"]["content"]
        assert list(content) == ["application/json", "application/msgpack"]
        url = fuzzed_server.url + path.replace("{name}", parameter["example"])
        answer = httpx.post(url, json=content["application/json"]["example"], headers=AUTH)
        assert answer.status_code == 200, answer.text


def test_the_body_schemas_hold_the_contracts_keys():
    from collider_contract.queries import COLLIDER_KEYS, QUERY_KEYS, SCENE_KEYS
    from collider_server.service.openapi import query_body, scene_body

    for body, keys in ((query_body(10), QUERY_KEYS), (scene_body(10, 2), SCENE_KEYS)):
        for media in body["requestBody"]["content"].values():
            assert list(media["schema"]["properties"]) == [*keys, "deadline_ms"]
    collider = scene_body(10, 2)["requestBody"]["content"]["application/json"]["schema"]
    assert list(collider["properties"]["colliders"]["items"]["properties"]) == list(COLLIDER_KEYS)


def test_the_model_info_schema_is_what_the_server_answers(fuzzed_server):
    """Issue 35, item 4: ``animation`` (and every other key of ModelInfo) is in the schema of
    ``GET /v1/models/{name}``; the fuzzer checks the answers against it."""
    import dataclasses

    from collider_contract import ModelInfo
    from collider_contract.animation import Timeline

    schema = httpx.get(f"{fuzzed_server.url}/openapi.json", headers=AUTH).json()
    info = schema["paths"]["/v1/models/{name}"]["get"]["responses"]["200"]["content"][
        "application/json"]["schema"]
    fields = [f.name for f in dataclasses.fields(ModelInfo) if f.name != "extra"]
    assert list(info["properties"]) == fields
    assert list(info["properties"]["animation"]["properties"]) == list(Timeline(2, 1.0, False).to_dict())
    answer = httpx.get(f"{fuzzed_server.url}/v1/models/sphere", headers=AUTH).json()
    assert list(answer) == fields and answer["animation"] == {} and answer["skeleton"] == {}
