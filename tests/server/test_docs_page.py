"""The ``/docs`` page in a real headless Chromium without internet (issue 21, item 4): Swagger UI
renders the server's OpenAPI 3.1 document and lists every operation, with no JavaScript or
console error; with a service token the page asks for it once and then lists the same."""

from __future__ import annotations

import time

import httpx
import pytest
from tests.view.chromium import Browser, find_browser

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
