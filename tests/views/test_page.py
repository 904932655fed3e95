"""What every browser view shares (collider_cli.views.page), in process: the viser server's
start (its label, the warning when it listens beyond this machine), its URL, serving until
Ctrl-C or SIGTERM, the initial camera and the box outlines."""

from __future__ import annotations

import signal
import socket
import sys

import numpy as np
import pytest

from .page_driver import interrupt_once_printed, panel_label

pytest.importorskip("viser", reason="the [view] extra (viser) is not installed")


@pytest.fixture(scope="module")
def server():
    from collider_cli.views.page import start_server

    server = start_server("127.0.0.1", 0)
    yield server
    server.stop()


def test_start_server_on_loopback(server, capsys):
    from collider_cli.views.page import start_server, url_of

    assert panel_label(server) == "neural-collider"
    assert url_of(server) == f"http://127.0.0.1:{server.get_port()}/"
    labelled = start_server("localhost", 0, label="collider ball (mesh)")
    try:
        assert panel_label(labelled) == "collider ball (mesh)"
        assert url_of(labelled) == f"http://localhost:{labelled.get_port()}/"
        with socket.create_connection(("127.0.0.1", labelled.get_port()), timeout=10):
            pass  # it serves
    finally:
        labelled.stop()
    assert "warning" not in capsys.readouterr().err


def test_start_server_where_asked_and_quiet_when_browsers_come_and_go(capsys):
    """On the port asked for (127.0.0.1 unless told), the documented default port being 8080;
    a browser connecting and leaving prints nothing (stdout carries the URL for scripts)."""
    import inspect

    import viser
    from websockets.sync.client import connect

    from collider_cli.views.page import start_server

    assert inspect.signature(start_server).parameters["port"].default == 8080
    port = free_port()
    server = start_server(port=port)
    try:
        assert (server.get_host(), server.get_port()) == ("127.0.0.1", port)
        capsys.readouterr()
        # As viser's web client connects: its version as the websocket subprotocol.
        with connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                     open_timeout=30) as browser:
            assert browser.recv(timeout=30)  # the page's first message
    finally:
        server.stop()
    assert "Connection" not in capsys.readouterr().out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("host", ["0.0.0.0", "::"])
def test_start_server_beyond_this_machine_warns(host, capsys):
    """Listening on every interface works, warns once on stderr naming the address and port,
    and the URL printed for the user is the loopback one (the wildcard is no address to open)."""
    from collider_cli.views.page import start_server, url_of

    try:
        server = start_server(host, 0)
    except OSError as exc:  # a machine without IPv6
        pytest.skip(f"cannot listen on {host}: {exc}")
    try:
        port = server.get_port()
        err = capsys.readouterr().err
        assert err.count("warning") == 1
        assert (f"warning: the view listens on {host}: anyone who can reach port {port} can see "
                "and drive it (no authentication)") in err
        assert url_of(server) == f"http://127.0.0.1:{port}/"
    finally:
        server.stop()


def test_require_viser_says_how_to_install(monkeypatch):
    import viser

    from collider_cli.views.page import require_viser

    assert require_viser() is viser
    monkeypatch.setitem(sys.modules, "viser", None)  # as if the [view] extra were missing
    with pytest.raises(ValueError) as err:
        require_viser()
    assert str(err.value) == ("the browser view needs viser: pip install 'neural-collider[view]' "
                              "(or pip install viser scikit-image)")
    assert err.value.__cause__ is None and err.value.__suppress_context__


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_wait_until_interrupted_stops_on_ctrl_c_and_sigterm(signum, capsys):
    """Serving until a signal, in a job started in the background by a non-interactive shell
    (SIGINT ignored): Ctrl-C or SIGTERM, even right after the message, stops the server, says
    so, and returns."""
    from collider_cli.views.page import start_server, wait_until_interrupted

    server = start_server("127.0.0.1", 0)
    port = server.get_port()
    try:
        printed = interrupt_once_printed(
            lambda: wait_until_interrupted(server, "serving on the test port"),
            "serving on the test port", signum)
    finally:
        server.stop()
    assert printed.startswith("serving on the test port\n")
    assert capsys.readouterr().err.endswith("view stopped\n")
    with pytest.raises(ConnectionRefusedError):  # the port is closed
        socket.create_connection(("127.0.0.1", port), timeout=10).close()


def test_look_at_box_frames_the_box_from_above(server):
    """The initial camera looks at the box's centre from a three-quarter view above it, at a
    distance proportional to the box's largest side, ``up`` being the scene's up axis."""
    from collider_cli.views.page import look_at_box

    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([2.0, 1.0, 1.0])  # centre (1, .5, .5), size 2
    cases = {  # up: (up vector, the camera's position, by hand)
        # +z: "side" is x, "front" is y: centre + 2 (0.75 x - y + 0.6 z)
        "+z": ((0, 0, 1), (2.5, -1.5, 1.7)),
        # +y: side z, front x: centre + 2 (0.75 z - x + 0.6 y)
        "+y": ((0, 1, 0), (-1.0, 1.7, 2.0)),
        # -x: side y, front z: centre + 2 (0.75 y - z - 0.6 x)
        "-x": ((-1, 0, 0), (-0.2, 2.0, -1.5)),
    }
    for up, (up_vec, position) in cases.items():
        look_at_box(server, lo, hi, up)
        camera = server.initial_camera
        np.testing.assert_allclose(camera.look_at, [1.0, 0.5, 0.5])
        np.testing.assert_allclose(camera.up, up_vec)
        np.testing.assert_allclose(camera.position, position, atol=1e-12)
        # Above the box: the camera's height along "up" is 0.6 of the size.
        assert np.dot(camera.position - camera.look_at, up_vec) == pytest.approx(1.2)
    # A box of no size (one point): the camera stands one metre-sized unit away, not on it.
    point = np.array([0.3, -0.2, 0.1])
    look_at_box(server, point, point)
    np.testing.assert_allclose(server.initial_camera.position, point + [0.75, -1.0, 0.6])
    look_at_box(server, lo, hi)  # the default up is +z
    np.testing.assert_allclose(server.initial_camera.position, (2.5, -1.5, 1.7), atol=1e-12)


def test_box_edges():
    from collider_cli.views.collider import box_segments
    from collider_cli.views.page import box_edges

    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 0.5, 5.0])
    edges = box_edges(lo, hi)
    assert edges.shape == (12, 2, 3)
    # The 12 edges of the box, by hand: 4 along each axis, between corners differing only there.
    expected = set()
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        for u in (lo[others[0]], hi[others[0]]):
            for v in (lo[others[1]], hi[others[1]]):
                a, b = np.empty(3), np.empty(3)
                a[others], b[others] = (u, v), (u, v)
                a[axis], b[axis] = lo[axis], hi[axis]
                expected.add((tuple(a), tuple(b)))
    assert {(tuple(a), tuple(b)) for a, b in edges} == expected
    segments = box_segments(lo, hi)
    assert segments.dtype == np.float32
    np.testing.assert_array_equal(segments, edges.astype(np.float32))
