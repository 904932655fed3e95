"""The ``/docs`` page in a real headless Chromium without internet (issue 21, item 4): Swagger UI
renders the server's OpenAPI 3.1 document and lists every operation, with no JavaScript or
console error; with a service token the page asks for it once and then lists the same. And
(issue 35, item 1) "Try it out" then "Execute" on the query and scene operations, with the
page's own defaults, answers 200 from ``collider serve``."""

from __future__ import annotations

import time

import httpx
import pytest
from tests.views.chromium import Browser, find_browser

from .conftest import ServerThread

pytestmark = pytest.mark.slow

BROWSER = find_browser()
if BROWSER is None:
    pytest.skip("no Chromium installed (apt-get install chromium)", allow_module_level=True)

#: Every operation Swagger UI shows, as "METHOD path".
LISTED = """[...document.querySelectorAll('.opblock')].map(block =>
    block.querySelector('.opblock-summary-method').textContent + ' ' +
    block.querySelector('.opblock-summary-path').getAttribute('data-path'))"""


def operations(url: str, headers=None) -> set[str]:
    paths = httpx.get(f"{url}/openapi.json", headers=headers).json()["paths"]
    return {f"{method.upper()} {path}" for path, ops in paths.items() for method in ops}


def listed_operations(browser: Browser, url: str, want: set[str],
                      timeout_s: float = 120) -> set[str]:
    browser.open(f"{url}/docs")
    deadline = time.monotonic() + timeout_s
    while True:
        listed = set(browser.evaluate(LISTED) or [])
        if listed >= want or time.monotonic() > deadline:
            return listed
        time.sleep(0.2)


@pytest.mark.parametrize("token", [None, "docs-token"], ids=["open", "token"])
def test_docs_lists_every_operation_without_errors(repo, tmp_path, token):
    with ServerThread(models=repo, device="cpu", token=token) as server:
        headers = {"Authorization": f"Bearer {token}"} if token else None
        want = operations(server.url, headers)
        assert len(want) == 9  # docs/service.md, "API": every route but /docs and /openapi.json
        with Browser(BROWSER, tmp_path / "profile") as browser:
            browser.prompt_answer = token
            listed = listed_operations(browser, server.url, want)
            text = browser.evaluate("document.body.innerText")
            errors = list(browser.errors)
        assert listed == want, f"missing {sorted(want - listed)}; page says {text[:500]!r}"
        assert "Unable to render" not in text
        assert errors == []
        assert "neural-collider" in text
        if token:
            assert browser.dialogs == ["Service token (COLLIDER_TOKEN):"]


#: Expand an operation, press "Try it out", then "Execute", as a user does (each step waits for
#: the button the previous one shows: Swagger UI renders them as React updates).
PRESS = """(async (id) => {
  const until = async (find) => {
    for (let i = 0; i < 600; i++) {
      const found = find();
      if (found) return found;
      await new Promise(r => setTimeout(r, 100));
    }
    throw new Error("timed out waiting in " + id);
  };
  const block = await until(() => document.getElementById(id));
  if (!block.classList.contains("is-open")) block.querySelector(".opblock-summary-control").click();
  (await until(() => block.querySelector(".try-out__btn"))).click();
  (await until(() => block.querySelector(".btn.execute"))).click();
  const status = await until(() => block.querySelector(".live-responses-table tbody .response-col_status"));
  const body = block.querySelector(".live-responses-table .microlight");
  return {status: status.textContent.trim(), body: body ? body.textContent.slice(0, 400) : ""};
})(%r)"""

#: Swagger UI's element id of each operation ("operations-<tag>-<operationId>").
TRY_OUT = {"POST /v1/models/{name}/query": "operations-models-query_v1_models__name__query_post",
           "POST /v1/scene/query": "operations-scene-scene_query_v1_scene_query_post"}


@pytest.mark.parametrize("token", [None, "docs-token"], ids=["open", "token"])
def test_try_it_out_answers_200_with_the_pages_own_defaults(repo, tmp_path, token):
    """Issue 35, item 1: the query and scene operations' "Try it out" then "Execute", untouched,
    against the service under a real uvicorn answers 200 (the page sends JSON and the examples are
    valid)."""
    with ServerThread(models=repo, device="cpu", token=token) as server, \
            Browser(BROWSER, tmp_path / "profile") as browser:
        browser.prompt_answer = token
        headers = {"Authorization": f"Bearer {token}"} if token else None
        listed_operations(browser, server.url, operations(server.url, headers))
        for label, element in TRY_OUT.items():
            shown = browser.call("Runtime.evaluate", expression=PRESS % element,
                                 awaitPromise=True, returnByValue=True)
            assert "exceptionDetails" not in shown, f"{label}: {shown['exceptionDetails']}"
            answer = shown["result"]["value"]
            assert answer["status"] == "200", f"{label} answered {answer}"
            assert '"distance"' in answer["body"], f"{label} answered {answer}"
        assert browser.errors == []
