"""``collider view`` on an animated collider, in process: the time slider, play, the time label,
the surface and its error colours at a time, the probe at a time (collider_cli.views.collider).

The pulsing sphere of :func:`~collider_server.making.animations.pulsing_sphere` (13 frames at
12 fps, 1 s, looping; radius 0.1 m (1 + 0.2 sin phase), centre at x = 0.1 m sin phase), baked
as a voxel collider (one 24^3 grid per frame), metres, collider frame = its own frame. Its
analytic reference says where the exact surface is at any time. The times used lie between
frames: 0.125 s (frame 1.5) and 0.3125 s (frame 3.75), on the slider's steps (1/48 s).
"""

from __future__ import annotations

import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from .page_driver import click, click_canvas, glb_mesh, gui_labels, node
from .test_collider_page import diverging

pytest.importorskip("viser", reason="the [view] extra (viser) is not installed")

T1, T2 = 0.125, 0.3125
RESOLUTION = 24  # the page's grid


@pytest.fixture(scope="module")
def pulse():
    from collider_server.making.animations import pulsing_sphere
    from collider_server.making.bake import bake_animated_collider

    animation, reference = pulsing_sphere(subdivisions=3)
    collider = bake_animated_collider(animation, "voxel", "pulse", resolution=24,
                                      show_progress=False)
    return animation, reference, collider


@pytest.fixture
def page(pulse):
    from collider_cli.views.collider import serve_collider_view

    animation, _, collider = pulse
    page = serve_collider_view(collider, animation, host="127.0.0.1", port=0,
                               resolution=RESOLUTION, show_progress=False)
    yield page
    page.play.value = False
    page.server.stop()


def expected_surface(collider, t: float):
    from collider_cli.views.collider import collider_grid
    from collider_server.making.surface import level_surface

    return level_surface(collider_grid(collider, RESOLUTION, show_progress=False, time=t), 0.0)


def test_time_step_and_label_by_hand(pulse):
    from collider_cli.views.collider import time_step_s, time_text
    from collider_contract import Timeline

    _, _, collider = pulse
    assert time_step_s(collider) == pytest.approx(1 / 48)  # a quarter of a 12 fps frame
    # A model whose source names no frame rate (made from no animation file): its own frames'.
    source = {k: v for k, v in collider.info.source.items() if k != "frame_rate_hz"}
    assert time_step_s(SimpleNamespace(info=replace(collider.info, source=source))) == pytest.approx(1 / 48)
    loop = Timeline(13, 12.0, loop=True)
    assert time_text(loop, 0.3125) == "**t = 0.3125 s**: frame 3.75 of 0..12 (12 fps, 1 s, loops)"
    assert time_text(loop, 1.0) == "**t = 1 s**: frame 0.00 of 0..12 (12 fps, 1 s, loops)"
    clamp = Timeline(5, 4.0, loop=False)
    assert time_text(clamp, 1.0) == "**t = 1 s**: frame 4.00 of 0..4 (4 fps, 1 s, clamps)"


def test_animated_page_has_a_time_slider_and_play(page):
    slider = page.time
    assert (slider.label, slider.min, slider.max, slider.value) == ("time (s)", 0.0, 1.0, 0.0)
    assert slider.step == pytest.approx(1 / 48)
    assert page.play.label == "play" and page.play.value is False
    assert page.time_label.content == "**t = 0 s**: frame 0.00 of 0..12 (12 fps, 1 s, loops)"
    # What a browser receives: the time controls above the level's.
    labels = gui_labels(page.server)
    assert labels.index("time (s)") < labels.index("play") < labels.index("level (mm)")


def test_time_slider_redraws_the_surface_at_that_time(pulse, page):
    """At two times between frames: the page shows the collider's own level set at that time,
    which lies on the exact (analytic) sphere of that time and not on the other's; coloured by
    its error against the exact mesh interpolated at that time; the wireframe follows."""
    from collider_server.engine.meshes import ExactSDF

    animation, reference, collider = pulse
    clip = None
    shown = {}
    for t in (T1, T2):
        page.time.value = t
        verts, faces = expected_surface(collider, t)
        surface = glb_mesh(page.server, "/surface")
        np.testing.assert_allclose(surface.vertices, verts, atol=1e-6)
        np.testing.assert_array_equal(surface.faces, faces)
        assert np.abs(reference.signed_distance(verts, t)).max() < 4e-3  # on the sphere of t (mm: a 24^3 grid)
        error = ExactSDF(animation.mesh_at(t)).signed_distance(verts) * 1e3
        if clip is None:  # the scale, fixed by the first surface (t = 0)
            first = expected_surface(collider, 0.0)[0]
            clip = float(np.percentile(np.abs(ExactSDF(animation.mesh_at(0.0)).signed_distance(
                first) * 1e3), 95))
        np.testing.assert_array_equal(surface.visual.vertex_colors[:, :3], diverging(error, clip))
        assert page.status.content == (f"surface at level 0 mm: {len(faces):,} triangles  \n"
                                       f"error vs exact mesh: mean |e| {np.abs(error).mean():.3g} "
                                       f"mm, max {np.abs(error).max():.3g} mm")
        page.show_wire.value = True
        wire = node(page.server, "/exact_mesh")
        np.testing.assert_allclose(wire.vertices, animation.vertices_at(t), atol=1e-6)
        assert wire.visible
        page.show_wire.value = False
        shown[t] = verts
    assert page.time_label.content == "**t = 0.3125 s**: frame 3.75 of 0..12 (12 fps, 1 s, loops)"
    # The two surfaces differ: each lies a centimetre off the other time's sphere (on average;
    # within 4 mm of its own everywhere).
    assert np.abs(reference.signed_distance(shown[T1], T2)).mean() > 8e-3
    assert np.abs(reference.signed_distance(shown[T2], T1)).mean() > 8e-3
    # The level slider draws the level set at the time shown.
    page.level.value = 5.0
    verts, _ = level_surface_at(collider, T2, 0.005)
    np.testing.assert_allclose(glb_mesh(page.server, "/surface").vertices, verts, atol=1e-6)


def level_surface_at(collider, t, level):
    from collider_cli.views.collider import collider_grid
    from collider_server.making.surface import level_surface

    return level_surface(collider_grid(collider, RESOLUTION, show_progress=False, time=t), level)


def test_each_time_step_is_computed_once(page):
    grids = page.grids
    assert grids.computed == 1  # t = 0
    page.time.value = T1
    page.time.value = 0.0
    page.time.value = T1 + 0.001  # the browser's rounding: the same step, shown on it
    assert grids.computed == 2 and grids.compute_s > 0
    assert page.time_label.content.startswith("**t = 0.125 s**")
    assert grids.at(T1) is grids.at(6 / 48)


def test_probe_answers_at_the_time_shown(pulse, page):
    from collider_cli.views.collider import probe_text, sphere_trace

    _, _, collider = pulse
    point = np.array([0.2, 0.03, -0.01])
    page.probe_point.value = tuple(point)
    page.time.value = T1
    click(page.probe_button)
    fields = ["distance", "normal", "contact", "collides", "velocity"]
    for t in (T1, T2):
        if t == T2:
            page.time.value = T2  # the probe shown is asked again at the new time
        answer = collider.query(point[None], fields, time=t)
        assert page.probe_out.content == probe_text(collider, point, 1e-3, t)[0]
        assert page.probe_out.content.startswith(f"**probe** (0.2, 0.03, -0.01) m at t = {t:g} s")
        assert f"distance **{answer.distance[0] * 1e3:.4g} mm**" in page.probe_out.content
        speed = np.linalg.norm(answer.velocity[0]) * 1e3
        assert speed > 10  # the sphere moves and pulses: a surface speed of centimetres a second
        assert page.probe_out.content.endswith(f" m/s ({speed:.4g} mm/s)")
        dots = node(page.server, "/probe/points")
        np.testing.assert_allclose(dots.points[1], answer.contact[0], atol=2e-4)  # float16
    # A click traces the ray against the surface of the time shown.
    origin, direction = np.array([0.5, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])
    click_canvas(page.server, origin, direction)
    hit = sphere_trace(collider, origin, direction, time=T2)
    np.testing.assert_allclose(page.probe_point.value, hit)
    _, radius, _, _ = pulse[1].at(T2)
    centre = pulse[1].at(T2)[0]
    assert hit[0] == pytest.approx(centre[0] + radius, abs=2e-3)


def test_play_runs_the_time_on_and_stops(page):
    page.time.value = T1  # computed here, so that play starts from a drawn time
    page.play.value = True
    deadline = time.monotonic() + 30
    while page.time.value == T1 and time.monotonic() < deadline:
        time.sleep(0.05)
    page.play.value = False
    assert page.time.value != T1, "play did not move the time"
    player = page.players[-1]
    player.join(30)  # its last step, however slow the machine: then nothing moves the time
    assert not player.is_alive(), "play did not stop"
    stopped = page.time.value
    assert page.time_label.content.startswith(f"**t = {stopped:.4g} s**")


def test_an_animated_collider_and_a_still_mesh_are_refused_either_way_round(pulse):
    """The view measures a collider against the exact surface of its own kind: an animated
    collider with a still mesh, or a still collider with an animation, is refused by name before
    any server starts."""
    from collider_cli.views.collider import serve_collider_view
    from collider_server.making.bake import bake_collider

    animation, _, collider = pulse
    still = animation.mesh_at(0.0)
    with pytest.raises(ValueError, match=r"^pulse is animated: the exact mesh must be animated too$"):
        serve_collider_view(collider, still, host="127.0.0.1", port=0, resolution=RESOLUTION, show_progress=False)
    ball = bake_collider(still, "voxel", "ball", resolution=16, show_progress=False, device="cpu")
    with pytest.raises(ValueError, match=r"^ball is static: the exact mesh must be static too$"):
        serve_collider_view(ball, animation, host="127.0.0.1", port=0, resolution=RESOLUTION, show_progress=False)
