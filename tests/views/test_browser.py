"""The browser views in a real headless Chromium: ``collider view bunny --mesh ...`` and a short
``collider simulate drape_bunny_quick --view``. Each is started as a user would (the real command, a
loopback port), opened in Chromium over the DevTools protocol, screenshotted until its canvas
shows the expected colours, and checked for JavaScript errors; Ctrl-C (SIGINT) must stop it with
status 0.

Skipped with a reason when no Chromium is installed (CI installs Debian's ``chromium``) or the
``[view]`` extra is missing. ``COLLIDER_SCREENSHOTS=DIR`` also saves the screenshots there (how
``docs/view-*.png`` were made).
"""

from __future__ import annotations

import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from tests.conftest import REPO_ROOT, shared_mesh_path

from .chromium import Browser, find_browser

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

BROWSER = find_browser()
if BROWSER is None:
    pytest.skip("no Chromium installed (apt-get install chromium)", allow_module_level=True)
pytest.importorskip("viser", reason="the [view] extra (viser) is not installed")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Command:
    """A ``collider`` command in a subprocess whose stdout lines are read by a thread."""

    def __init__(self, args: list[str], cwd: Path):
        env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1",
                   PYTHONPATH=os.pathsep.join([str(REPO_ROOT / "server"), str(REPO_ROOT / "client"),
                                               os.environ.get("PYTHONPATH", "")]))
        self.process = subprocess.Popen([sys.executable, "-m", "collider_cli", *args],
                                        cwd=cwd, env=env, stdout=subprocess.PIPE,
                                        stderr=subprocess.PIPE, text=True)
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.stderr: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()
        threading.Thread(target=lambda: self.stderr.extend(self.process.stderr), daemon=True).start()

    def _pump(self) -> None:
        for line in self.process.stdout:
            self.lines.put(line)
        self.lines.put(None)

    def wait_for(self, text: str, timeout_s: float = 600) -> str:
        """The first stdout line containing ``text`` (fails if the command ends first)."""
        while True:
            line = self.lines.get(timeout=timeout_s)
            if line is None:
                self.process.wait()
                pytest.fail(f"command ended ({self.process.returncode}) before printing {text!r}:"
                            f"\n{''.join(self.stderr)[-3000:]}")
            if text in line:
                return line

    def interrupt(self) -> int:
        """Ctrl-C, as a user stops the view; the exit status."""
        self.process.send_signal(signal.SIGINT)
        try:
            return self.process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            raise

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()


def canvas_region(image) -> np.ndarray:
    """(h, w, 3) int the part of the screenshot where the 3D canvas shows the scene: left of the
    control panel (right 30 %), below the top band (toasts) and clear of the axes gizmo drawn in
    red, green and blue at the bottom left (it would pass any colour check on its own)."""
    a = np.asarray(image).astype(int)
    h, w = a.shape[:2]
    return a[int(0.25 * h):int(0.85 * h), int(0.1 * w):int(0.7 * w)]


def coloured(region: np.ndarray, colour: str) -> int:
    """Pixels of a clearly red / blue / grey (non-white, unsaturated) hue."""
    r, g, b = region[..., 0], region[..., 1], region[..., 2]
    if colour == "red":
        return int(((r - np.maximum(g, b)) > 60).sum())
    if colour == "blue":
        return int(((b - r) > 50).sum())
    if colour == "shape":  # anything drawn: clearly darker than the white background
        return int((region.max(axis=-1) < 225).sum())
    raise ValueError(colour)


def surface_pixels(image) -> np.ndarray:
    """(h, w) bool: the canvas's shaded surface pixels: neither the white background nor the
    dark lines of the domain box."""
    region = canvas_region(image)
    return (region.max(axis=-1) < 245) & (region.min(axis=-1) > 120)


def save(image, name: str, tmp_path: Path) -> None:
    image.save(tmp_path / name)
    target = os.environ.get("COLLIDER_SCREENSHOTS")
    if target:
        image.save(Path(target) / name)


def look(url: str, tmp_path: Path, check, name: str):
    with Browser(BROWSER, tmp_path / f"profile-{name}") as browser:
        browser.open(url)
        image, ok = browser.screenshot_until(check, timeout_s=180)
        # A little more of the page's life for late errors: one more round trip to the page.
        browser.call("Runtime.evaluate", expression="1")
        errors = list(browser.errors)
    save(image, name, tmp_path)
    return image, ok, errors


def test_collider_view_in_chromium(tmp_path):
    mesh = shared_mesh_path("stanford-bunny.obj")
    port = free_port()
    command = Command(["view", "bunny", "--mesh", str(mesh), "--port", str(port),
                       "--resolution", "64", "--quiet"], REPO_ROOT)
    try:
        line = command.wait_for("Ctrl-C to stop")
        assert f"http://127.0.0.1:{port}/" in line

        def check(image) -> bool:
            region = canvas_region(image)
            # The bunny's surface (shaded, mostly white-grey where the error is small) and its
            # error patches in the colour map's red (outside) and blue (inside).
            return coloured(region, "shape") > 0.02 * region[..., 0].size and \
                coloured(region, "red") >= 20 and coloured(region, "blue") >= 20

        image, ok, errors = look(f"http://127.0.0.1:{port}/", tmp_path, check, "view-bunny.png")
        region = canvas_region(image)
        assert ok, (f"canvas shows too little: {coloured(region, 'shape')} drawn pixels, "
                    f"{coloured(region, 'red')} red, {coloured(region, 'blue')} blue; see {tmp_path / 'view-bunny.png'}")
        assert errors == [], errors
        assert command.interrupt() == 0
        assert "view stopped" in "".join(command.stderr)
    finally:
        command.kill()


def test_animated_view_time_slider_in_chromium(tmp_path):
    """The shipped animated arm: the page opens at t = 0; the time slider, moved with the
    mouse in the browser to about 0.25 s, shows that time in the panel and another picture (the
    forearm bent up)."""
    port = free_port()
    animations = REPO_ROOT / "examples" / "animations"
    command = Command(["view", "arm", "--mesh", str(animations / "arm.obj"), "--animation",
                       str(animations / "arm.pc2"), "--resolution", "48", "--port", str(port),
                       "--quiet"], REPO_ROOT)
    try:
        command.wait_for("Ctrl-C to stop")

        def drawn(image) -> bool:
            return coloured(canvas_region(image), "shape") > 0.01 * canvas_region(image)[..., 0].size

        with Browser(BROWSER, tmp_path / "profile-arm") as browser:
            browser.open(f"http://127.0.0.1:{port}/")
            start, ok = browser.screenshot_until(drawn, timeout_s=180)
            save(start, "view-arm-start.png", tmp_path)
            assert ok, f"the arm is not drawn; see {tmp_path / 'view-arm-start.png'}"
            assert "t = 0 s" in browser.evaluate("document.body.innerText")
            # A click on the time slider's track half way along (the level
            # slider's maximum is 10 mm, not 1 s); keys would also turn the camera.
            track = browser.evaluate(
                "(() => { const s = [...document.querySelectorAll('[role=slider]')]"
                ".find(e => e.getAttribute('aria-valuemax') === '1');"
                " if (!s) return null; const r = s.closest('.mantine-Slider-root')"
                ".getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; })()")
            assert track, "no time slider on the page"
            left, top, width, height = track
            x, y = left + 0.5 * width, top + 0.5 * height
            for kind in ("mousePressed", "mouseReleased"):
                browser.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left",
                             clickCount=1)
            # The pointer off the panel, so that the slider's hint does not cover the picture.
            browser.call("Input.dispatchMouseEvent", type="mouseMoved", x=100, y=700)
            def shown_time() -> float | None:
                """The time of the surface drawn, from the panel (None while computing)."""
                text = browser.evaluate("document.body.innerText")
                found = re.search(r"t = ([0-9.]+) s: frame", text)
                return float(found.group(1)) if found and "computing" not in text else None

            before = surface_pixels(start)
            deadline = time.monotonic() + 180
            while shown_time() in (None, 0.0) and time.monotonic() < deadline:
                time.sleep(0.2)
            t = shown_time()

            def moved(image) -> bool:  # the arm's own pixels, not the box's lines nor shading
                return int((surface_pixels(image) ^ before).sum()) > 2000

            later, ok = browser.screenshot_until(moved, timeout_s=60)
            save(later, "view-arm.png", tmp_path)
            errors = list(browser.errors)
        # Half way along a 0..1 s track, give or take the thumb's size.
        assert t is not None and 0.4 <= t <= 0.6, t
        changed = int((surface_pixels(later) ^ before).sum())
        assert ok, f"the picture did not change ({changed} pixels); see {tmp_path / 'view-arm.png'}"
        assert errors == [], errors
        assert command.interrupt() == 0
    finally:
        command.kill()


def test_simulate_view_in_chromium(tmp_path):
    port = free_port()
    # The quick drape: the paper's bunny and cloth square at 60 x 60 vertices, not 200 x 200 (what
    # is tested is the view of a run and its replay, not the cloth's resolution).
    command = Command(["simulate", "drape_bunny_quick", "--steps", "20", "--view", "--port", str(port),
                       "--output", str(tmp_path / "out"), "--no-preview", "--quiet"], REPO_ROOT)
    try:
        command.wait_for("view at")
        command.wait_for("run finished")  # the view stays up after the run

        def check(image) -> bool:
            region = canvas_region(image)
            # The cloth (blue) above the bunny (light grey).
            return coloured(region, "blue") > 0.01 * region[..., 0].size and \
                coloured(region, "shape") > 0.03 * region[..., 0].size

        image, ok, errors = look(f"http://127.0.0.1:{port}/", tmp_path, check, "view-simulate-start.png")
        region = canvas_region(image)
        assert ok, (f"canvas shows too little: {coloured(region, 'blue')} cloth pixels, "
                    f"{coloured(region, 'shape')} drawn; see {tmp_path / 'view-simulate-start.png'}")
        assert errors == [], errors
        assert command.interrupt() == 0
    finally:
        command.kill()
    # The same run replayed from its OBJ + PC2 (the shipped scene's bunny found by the name).
    port = free_port()
    replay = Command(["view", "--replay", str(tmp_path / "out" / "drape_bunny_quick"), "--port", str(port)],
                     REPO_ROOT)
    try:
        # Frames are written every 50 steps and at the last: the start and step 20.
        assert "replaying 2 frames" in replay.wait_for("Ctrl-C to stop")
        image, ok, errors = look(f"http://127.0.0.1:{port}/", tmp_path, check, "view-replay.png")
        assert ok, f"replay canvas shows too little; see {tmp_path / 'view-replay.png'}"
        assert errors == [], errors
        assert replay.interrupt() == 0
    finally:
        replay.kill()


def test_chromium_reports_javascript_errors(tmp_path):
    """The error check above is not vacuous: a page that throws and logs an error is caught."""
    page = ("data:text/html,<canvas></canvas><script>console.error('logged');"
            "setTimeout(() => { throw new Error('thrown'); }, 0);</script>")
    with Browser(BROWSER, tmp_path / "profile") as browser:
        browser.open(page)
        browser.call("Runtime.evaluate", expression="new Promise(r => setTimeout(r, 50))",
                     awaitPromise=True)  # lets the page's timer fire before the check
        errors = list(browser.errors)
    assert any("logged" in e for e in errors), errors
    assert any("thrown" in e for e in errors), errors
