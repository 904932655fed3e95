"""What every browser view shares: the viser server, its URL, serving until Ctrl-C, the
initial camera and box outlines (viser is the ``[view]`` extra, imported only when a view runs)."""

from __future__ import annotations

import sys
import threading
import time

import numpy as np

from collider_contract.pose import box_corners

from ..net import is_loopback

DEFAULT_PORT = 8080


def require_viser():
    """The viser module, or a ValueError saying how to install it (the CLI prints it as one line)."""
    try:
        import viser
    except ImportError:
        raise ValueError("the browser view needs viser: pip install 'neural-collider[view]' "
                         "(or pip install viser scikit-image)") from None
    return viser


def start_server(host: str = "127.0.0.1", port: int = DEFAULT_PORT, label: str = "neural-collider"):
    """A started ``viser.ViserServer`` on ``host:port`` (viser takes the next free port when
    ``port`` is taken: ``server.get_port()`` says which); warns on stderr when ``host`` is not a
    loopback address (the view has no authentication: anyone who reaches the port sees it)."""
    viser = require_viser()
    server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    if not is_loopback(host):
        print(f"warning: the view listens on {host}: anyone who can reach port "
              f"{server.get_port()} can see and drive it (no authentication)", file=sys.stderr)
    server.scene.set_up_direction("+z")
    return server


def url_of(server) -> str:
    host = server.get_host()
    return f"http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{server.get_port()}/"


def wait_until_interrupted(server, message: str) -> None:
    """Print ``message`` and serve until Ctrl-C (SIGINT) or SIGTERM, then stop the server
    cleanly. Both handlers are installed here: a job started in the background by a
    non-interactive shell (a CI script, ``cmd &``) inherits SIGINT ignored, and Python then
    never turns Ctrl-C into KeyboardInterrupt."""
    import signal

    def stop(signum, frame):
        raise KeyboardInterrupt

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, stop)
        signal.signal(signal.SIGTERM, stop)
    try:
        # Inside the try: a signal right after the message (a script that waits for it, then
        # sends Ctrl-C) still stops the server. Short sleeps, not Event.wait(): Python runs a
        # handler between bytecodes, so a signal that lands just before a blocking call waits
        # for that call's end; and a KeyboardInterrupt raised inside Condition.wait's lock
        # bookkeeping can leave it deadlocked.
        print(message, flush=True)
        while True:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    print("view stopped", file=sys.stderr)


def look_at_box(server, lo: np.ndarray, hi: np.ndarray, up: str = "+z") -> None:
    """Point the initial camera at the box ``lo``..``hi`` from a three-quarter view above it,
    ``up`` being the scene's up axis (``"+y"``, ``"+z"``, ...)."""
    axis = "xyz".index(up[1])
    up_vec = np.zeros(3)
    up_vec[axis] = 1.0 if up[0] == "+" else -1.0
    side, front = np.roll(np.eye(3), -axis - 1, axis=0)[:2]  # the two other axes
    centre = 0.5 * (lo + hi)
    size = float(np.max(hi - lo)) or 1.0
    server.initial_camera.look_at = centre
    server.initial_camera.up = up_vec
    server.initial_camera.position = centre + size * (0.75 * side - 1.0 * front + 0.6 * up_vec)


def box_edges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(12, 2, 3) the edges of the axis-aligned box ``lo``..``hi``."""
    corners = box_corners(lo, hi)
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8)
             if (a ^ b).bit_count() == 1]  # corners differing in one coordinate
    return np.stack([corners[[a, b]] for a, b in pairs])
