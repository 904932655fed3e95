"""Headless Chromium driven over the DevTools protocol (a websocket), for the browser tests.

Why CDP rather than ``--screenshot``: the page must first connect its websocket and receive the
scene, so the test takes screenshots until the canvas shows what it should (a condition, with a
deadline) and, meanwhile, records every JavaScript exception and console error the page raises.

WebGL: with ``--disable-gpu`` and no GPU, Chromium falls back to its software rasteriser
(SwiftShader through ANGLE) and viser's canvas renders; ``--enable-unsafe-swiftshader`` keeps
that fallback allowed in newer Chromium builds.
"""

from __future__ import annotations

import base64
import io
import itertools
import json
import shutil
import subprocess
import time
import urllib.request
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--enable-unsafe-swiftshader", "--hide-scrollbars", "--mute-audio"]


def find_browser() -> str | None:
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


class Browser:
    """One headless Chromium with a fresh profile in ``profile_dir``; use as a context manager."""

    def __init__(self, executable: str, profile_dir: Path, width: int = 1200, height: int = 800,
                 start_timeout_s: float = 60.0):
        self.profile_dir = Path(profile_dir)
        self.process = subprocess.Popen(
            [executable, *FLAGS, f"--user-data-dir={self.profile_dir}",
             "--remote-debugging-port=0", f"--window-size={width},{height}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port = self._devtools_port(start_timeout_s)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=30) as r:
            pages = [t for t in json.load(r) if t["type"] == "page"]
        from websockets.sync.client import connect

        self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=30)
        self._ids = itertools.count(1)
        self.errors: list[str] = []
        #: Text typed into every ``window.prompt`` (``None``: dialogs are left open); the
        #: messages of the dialogs answered.
        self.prompt_answer: str | None = None
        self.dialogs: list[str] = []
        for method in ("Runtime.enable", "Log.enable", "Page.enable"):
            self.call(method)

    def _devtools_port(self, timeout_s: float) -> int:
        """Chromium writes the port it chose into the profile's DevToolsActivePort file."""
        marker = self.profile_dir / "DevToolsActivePort"
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"chromium exited with status {self.process.returncode}")
            if marker.is_file():
                text = marker.read_text().split()
                if text:
                    return int(text[0])
            time.sleep(0.05)
        raise TimeoutError("chromium did not open its DevTools port")

    def call(self, method: str, **params) -> dict:
        """Send one command and return its result, recording the events that arrive meanwhile."""
        ident = next(self._ids)
        self.ws.send(json.dumps({"id": ident, "method": method, "params": params}))
        while True:
            message = json.loads(self.ws.recv(timeout=120))
            if message.get("id") == ident:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message.get("result", {})
            self._record(message)

    def _record(self, event: dict) -> None:
        method, params = event.get("method"), event.get("params", {})
        if method == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            self.errors.append("exception: " + str(details.get("exception", {}).get(
                "description", details.get("text"))))
        elif method == "Runtime.consoleAPICalled" and params.get("type") == "error":
            self.errors.append("console.error: " + " ".join(
                str(a.get("value", a.get("description", ""))) for a in params.get("args", [])))
        elif method == "Page.javascriptDialogOpening" and self.prompt_answer is not None:
            # Answered without waiting: the page's script is paused until the dialog closes.
            self.dialogs.append(params.get("message", ""))
            self.ws.send(json.dumps({"id": next(self._ids), "method": "Page.handleJavaScriptDialog",
                                     "params": {"accept": True, "promptText": self.prompt_answer}}))
        elif method == "Log.entryAdded" and params.get("entry", {}).get("level") == "error":
            entry = params["entry"]
            self.errors.append(f"log: {entry.get('text')} {entry.get('url', '')}")

    def open(self, url: str, timeout_s: float = 120.0) -> None:
        """Navigate to ``url`` and wait for its load event (screenshots before the new page has
        committed fail with 'Not attached to an active page')."""
        self.call("Page.navigate", url=url)
        deadline = time.monotonic() + timeout_s
        while True:
            message = json.loads(self.ws.recv(timeout=max(deadline - time.monotonic(), 0.001)))
            self._record(message)
            if message.get("method") == "Page.loadEventFired":
                return

    def evaluate(self, expression: str):
        """The value of a JavaScript ``expression`` in the page (JSON-serialisable)."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def screenshot(self):
        """The page as a PIL RGB image."""
        from PIL import Image

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return Image.open(io.BytesIO(data)).convert("RGB")

    def screenshot_until(self, check, timeout_s: float = 120.0):
        """Screenshots until ``check(image)`` is true; returns the last image and the verdict."""
        deadline = time.monotonic() + timeout_s
        while True:
            image = self.screenshot()
            if check(image) or time.monotonic() > deadline:
                return image, check(image)

    def close(self) -> None:
        try:
            self.ws.close()
        finally:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
