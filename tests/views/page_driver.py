"""Driving a viser page in the test process, as the browser would, and reading what it shows.

A browser's click reaches viser as a GUI update; viser then calls the handle's callbacks. Setting
a handle's ``value`` from Python does the same (synchronously, in the caller's thread): that is
how these tests press buttons, move sliders and type points. A click in the 3D canvas reaches
the scene's pointer callbacks with a ray; :func:`click_canvas` calls them with one.

Two readers go below viser's public API (it has no getter for them): the panel label and the
scene's pointer callbacks. Each names what it reads, so a viser that moves them fails here
with that name rather than deep in a test.
"""

from __future__ import annotations

import io
import os
import signal
import sys
import threading

import numpy as np


def click(button) -> None:
    """Press a GUI button: viser calls its ``on_click`` callbacks."""
    button.value = True


def node(server, name: str):
    """The scene node ``name`` (fails when the page has none)."""
    handle = server.scene.get_handle_by_name(name)
    assert handle is not None, f"the page has no scene node {name}"
    return handle


def glb_mesh(server, name: str):
    """The trimesh.Trimesh the scene node ``name`` (added by ``add_mesh_trimesh``) sends: its
    vertices, faces and vertex colours as the browser receives them."""
    import trimesh

    scene = trimesh.load(io.BytesIO(node(server, name).glb_data), file_type="glb", process=False)
    (mesh,) = scene.geometry.values()
    return mesh


def click_canvas(server, origin, direction) -> None:
    """A click in the 3D canvas along the ray ``origin + s * direction`` (world frame)."""
    import viser

    entries = [e for e in server.scene._scene_pointer_cb if e.event_type == "click"]
    assert entries, "the page listens to no click in the canvas"
    for entry in entries:
        entry.callback(viser.ScenePointerEvent(
            client=None, client_id=0, event_type="click", ray_origin=tuple(map(float, origin)),
            ray_direction=tuple(map(float, direction)), screen_pos=((0.5, 0.5),), modifier=None))


def panel_label(server) -> str | None:
    """The label at the top of the GUI panel, as sent to a browser that connects now."""
    from viser import _messages

    buffer = server._websock_server._broadcast_buffer
    with buffer.buffer_lock:
        labels = [m.label for _, m in sorted(buffer.message_from_id.items())
                  if isinstance(m, _messages.SetGuiPanelLabelMessage)]
    assert labels, "the page sent no panel label"
    return labels[-1]


def pose_of(handle) -> np.ndarray:
    """(4, 4) the scene node's pose (its wxyz, position and uniform scale), world frame."""
    w, x, y, z = np.asarray(handle.wxyz, np.float64)
    rotation = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    pose = np.eye(4)
    pose[:3, :3] = rotation * float(handle.scale)
    pose[:3, 3] = handle.position
    return pose


class _Stdout(io.StringIO):
    """stdout that sets ``printed`` once ``text`` was written and flushed: what a script reading
    the command's output through a pipe sees (block-buffered until flushed)."""

    def __init__(self, text: str):
        super().__init__()
        self.text, self.printed = text, threading.Event()

    def flush(self) -> None:
        super().flush()
        if self.text in self.getvalue():
            self.printed.set()


def interrupt_once_printed(serve, text: str, signum: int = signal.SIGINT,
                           timeout_s: float = 30.0) -> str:
    """Call ``serve()`` in this thread (the main one, where Python runs signal handlers) and,
    once it printed and flushed ``text`` on stdout, send this process ``signum`` (a user's
    Ctrl-C, or a SIGTERM), as to a job started in the background by a non-interactive shell
    (SIGINT and SIGTERM ignored until the view installs its handlers). Returns what it printed;
    raises TimeoutError when ``text`` did not come, or ``serve()`` did not return, within
    ``timeout_s``."""
    out = _Stdout(text)
    watched = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)
    saved = {s: signal.getsignal(s) for s in watched}
    finished = threading.Event()  # serve() returned or raised: send nothing more
    why = []

    def stuck(signum, frame):  # the watchdog's
        raise TimeoutError(f"{text!r}: {why[0]}")

    def send():
        if not out.printed.wait(timeout_s):
            why.append(f"not printed and flushed within {timeout_s} s")
        elif finished.is_set():
            return
        else:
            os.kill(os.getpid(), signum)
            if finished.wait(timeout_s):
                return
            why.append(f"printed, but signal {signum} did not stop the view")
        if not finished.is_set():
            signal.pthread_kill(threading.main_thread().ident, signal.SIGUSR1)

    stdout, sys.stdout = sys.stdout, out
    sender = threading.Thread(target=send, daemon=True)
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGUSR1, stuck)
        sender.start()
        serve()
    finally:
        finished.set()
        out.printed.set()  # a sender still waiting for the text gives up
        sender.join(timeout=timeout_s)
        sys.stdout = stdout
        for s, handler in saved.items():
            signal.signal(s, handler)
    return out.getvalue()


def gui_labels(server) -> list[str]:
    """The labels of the GUI controls, in the order sent to a browser that connects now."""
    from viser import _messages

    buffer = server._websock_server._broadcast_buffer
    with buffer.buffer_lock:
        messages = [m for _, m in sorted(buffer.message_from_id.items())]
    return [m.props.label for m in messages
            if isinstance(m, _messages._CreateGuiComponentMessage)
            and isinstance(getattr(m.props, "label", None), str)]
