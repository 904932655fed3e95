"""``collider view NAME`` in process (collider_cli.views.collider): the page is built on a real
viser server and driven as the browser would (its controls' callbacks), and what it shows is
compared with values computed here by other means.

Colliders in centimetres (``units = "cm"``, 0.01 m per unit), so that every conversion between
collider units, metres and millimetres shows: ``ball``, an icosphere of radius 10 cm (the page),
and ``brick``, a 10 cm cube centred at the origin (exact distances by hand: the probe, the
click ray). Collider frame throughout.
"""

from __future__ import annotations

import socket

import numpy as np
import pytest

from .page_driver import click, click_canvas, glb_mesh, gui_labels, node, panel_label

pytest.importorskip("viser", reason="the [view] extra (viser) is not installed")

MM_PER_CM = 10.0
EPS_CM = 0.1  # the default eps, 1 mm, in centimetres
WHITE, RED, BLUE = np.array([245, 245, 245.]), np.array([200, 30, 30.]), np.array([30, 70, 200.])


def _cm_collider(tri, name: str):
    from collider_server.engine.meshes import Mesh
    from collider_server.making.bake import bake_collider

    mesh = Mesh(np.asarray(tri.vertices, np.float64), np.asarray(tri.faces, np.int64), name)
    return mesh, bake_collider(mesh, "mesh", name, units="cm", meters_per_unit=0.01,
                               show_progress=False)


@pytest.fixture(scope="module")
def ball():
    import trimesh

    return _cm_collider(trimesh.creation.icosphere(subdivisions=2, radius=10.0), "ball")


@pytest.fixture(scope="module")
def brick():
    import trimesh

    return _cm_collider(trimesh.creation.box(extents=(10.0, 10.0, 10.0)), "brick")


def _serve(collider, mesh, port: int = 0, **options):
    from collider_cli.views.collider import serve_collider_view

    page = serve_collider_view(collider, mesh, host="127.0.0.1", port=port, **options)
    # What the page showed before anyone touched it.
    first = {"status": page.status.content, "probe_out": page.probe_out.content,
             "surface": glb_mesh(page.server, "/surface")}
    return page, first


@pytest.fixture
def ball_page(ball):
    """The ball's page with its mesh (error colours), 16^3 grid, +y up. One per test (a few
    tenths of a second): mutation testing runs a mutant against the tests that build the page
    in them, not those that found one built."""
    mesh, collider = ball
    page, first = _serve(collider, mesh, resolution=16, up="+y", show_progress=False)
    yield page, first
    page.server.stop()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def diverging(error_mm: np.ndarray, clip_mm: float) -> np.ndarray:
    """(v, 3) uint8 the documented colour map, by hand: white at 0, towards red at +clip
    (outside), towards blue at -clip (inside), clipped beyond."""
    s = np.clip(np.asarray(error_mm, np.float64) / clip_mm, -1, 1)[:, None]
    towards = np.where(s >= 0, RED, BLUE)
    return np.round(WHITE + np.abs(s) * (towards - WHITE)).astype(np.uint8)


def expected_surface(collider, resolution: int, level_cm: float):
    from collider_cli.views.collider import collider_grid
    from collider_server.making.surface import level_surface

    return level_surface(collider_grid(collider, resolution, show_progress=False), level_cm)


def exact_error_mm(mesh, vertices, level_cm: float) -> np.ndarray:
    from collider_server.engine.meshes import ExactSDF

    return (ExactSDF(mesh).signed_distance(vertices) - level_cm) * MM_PER_CM


# -- the plain functions -------------------------------------------------------------------------


def test_error_colours_by_hand():
    from collider_cli.views.collider import error_colors

    colours = error_colors(np.array([0.0, 0.5, 1.0, 3.0, -0.25, -1.0, -7.0]), clip_mm=1.0)
    assert colours.dtype == np.uint8
    # white + s (red - white), white + |s| (blue - white), rounded half to even
    assert colours.tolist() == [[245, 245, 245], [222, 138, 138], [200, 30, 30], [200, 30, 30],
                                [191, 201, 234], [30, 70, 200], [30, 70, 200]]
    np.testing.assert_array_equal(error_colors(np.array([1.0, -0.5]), clip_mm=2.0),
                                  [[222, 138, 138], [191, 201, 234]])


def test_colour_bar_shows_the_colour_map_and_its_scale():
    from collider_cli.views.collider import colour_bar_html

    html = colour_bar_html(2.5)
    stops = ", ".join(f"rgb({r}, {g}, {b})" for r, g, b in diverging(np.linspace(-1, 1, 9), 1.0))
    assert f"background:linear-gradient(to right,{stops})" in html
    assert html.startswith('<div style="padding:4px 0;font-size:12px">surface error vs exact mesh (mm)')
    assert "<span>-2.5 (inside)</span><span>0</span><span>+2.5</span>" in html
    assert "<span>-0.123 (inside)</span>" in colour_bar_html(0.123456)  # 3 significant digits
    assert html == colour_bar_html(2.5) and html.endswith("</div></div>")


def test_surface_error_in_mm(brick):
    from collider_cli.views.collider import surface_error_mm
    from collider_server.engine.meshes import ExactSDF

    mesh, _ = brick
    # The cube's faces at +-5 cm: points 2 cm out, 0.5 cm in, on a face.
    points = np.array([[7.0, 0, 0], [0, -4.5, 0], [0, 0, 5.0]])
    np.testing.assert_allclose(surface_error_mm(ExactSDF(mesh), points, 0.0, 0.01),
                               [20.0, -5.0, 0.0], atol=1e-9)
    # Against the level 0.5 cm: 5 mm less; in metres (1 m per unit), a thousand times more.
    np.testing.assert_allclose(surface_error_mm(ExactSDF(mesh), points, 0.5, 0.01),
                               [15.0, -10.0, -5.0], atol=1e-9)
    np.testing.assert_allclose(surface_error_mm(ExactSDF(mesh), points, 0.5, 1.0),
                               [1500.0, -1000.0, -500.0], atol=1e-9)


def test_collider_grid_and_its_limits(ball, capsys):
    from collider_cli.views.collider import collider_grid

    _, collider = ball
    grid = collider_grid(collider, 8, show_progress=False)
    assert grid.values.shape == (8, 8, 8)
    np.testing.assert_allclose(grid.lo, collider.domain_min)
    np.testing.assert_allclose(grid.hi, collider.domain_max)
    axis = np.linspace(collider.domain_min[0], collider.domain_max[0], 8)
    corner = np.array([axis[0], axis[0], axis[0]])  # the grid's first sample
    assert grid.values[0, 0, 0] == pytest.approx(
        float(collider.query(corner[None], ["distance"]).distance[0]))
    assert capsys.readouterr().err == ""
    collider_grid(collider, 8)
    assert "ball grid" in capsys.readouterr().err  # by default, the progress bar, named
    for bad in (7, 513, 0):
        with pytest.raises(ValueError, match=rf"^--resolution must be between 8 and 512, got {bad}$"):
            collider_grid(collider, bad)


def test_sphere_trace_marches_to_the_surface(brick):
    """The click ray, against the cube's exact distance: the march lands exactly on a face."""
    from collider_cli.views.collider import sphere_trace

    _, collider = brick  # faces at +-5 cm; domain +-6 cm
    hit = sphere_trace(collider, np.array([20.0, 0.3, -0.2]), np.array([-3.0, 0.0, 0.0]))
    np.testing.assert_allclose(hit, [5.0, 0.3, -0.2], atol=1e-9)
    # From inside the domain, outside the cube; and along a diagonal (not normalised).
    np.testing.assert_allclose(sphere_trace(collider, np.array([5.5, 1.0, 1.0]),
                                            np.array([-1.0, 0.0, 0.0])), [5.0, 1.0, 1.0], atol=1e-9)
    diagonal = sphere_trace(collider, np.array([0.0, -20.0, 20.0]), np.array([0.0, 1.0, -1.0]))
    np.testing.assert_allclose(diagonal, [0.0, -5.0, 5.0], atol=2e-4)
    # Two steps from the domain's edge: 1 cm to the face, then 0.
    assert sphere_trace(collider, np.array([20.0, 0.0, 0.0]), np.array([-1.0, 0, 0]), max_steps=1) is None
    np.testing.assert_allclose(sphere_trace(collider, np.array([20.0, 0, 0]), np.array([-1.0, 0, 0]),
                                            max_steps=2), [5.0, 0, 0], atol=1e-9)
    # Misses: the ray misses the domain, points away from it, or crosses it beside the cube.
    assert sphere_trace(collider, np.array([20.0, 20.0, 0.0]), np.array([-1.0, 0, 0])) is None
    assert sphere_trace(collider, np.array([20.0, 0.0, 0.0]), np.array([1.0, 0, 0])) is None
    assert sphere_trace(collider, np.array([20.0, 5.5, 0.0]), np.array([-1.0, 0, 0])) is None
    assert sphere_trace(collider, np.array([-20.0, 5.5, 5.5]), np.array([1.0, 0, 0])) is None


def first_hit(mesh, origin, direction) -> np.ndarray:
    """The ray's first intersection with the mesh's triangles (Moller-Trumbore, by hand)."""
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    t_vec = origin - a
    u = np.einsum("ij,ij->i", t_vec, p) * inv
    q = np.cross(t_vec, e1)
    v = (q @ direction) * inv
    s = np.einsum("ij,ij->i", e2, q) * inv
    hits = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 0)
    return origin + s[hits].min() * direction


def test_sphere_trace_stops_at_the_first_step_within_tolerance(brick):
    """Marching at 60 degrees to the cube's top face: each step halves the distance (by hand:
    d_k = 0.9 / 2^k from 0.9 cm above it), and the march stops at the first point closer than
    1e-5 of the domain's size (12 cm): d_13 = 1.1e-4 cm < 1.2e-4 cm < d_12."""
    import warnings

    from collider_cli.views.collider import sphere_trace

    _, collider = brick
    origin = np.array([-4.0, 0.0, 5.9])  # inside the domain, above the top face (z = 5)
    direction = np.array([np.sin(np.pi / 3), 0.0, -0.5])
    travelled = 0.9 * (2 - 2.0 ** -12)  # d_0 + ... + d_12
    expected = origin + travelled * direction
    assert expected[2] - 5.0 == pytest.approx(0.9 / 2 ** 13)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an axis-parallel ray divides by zero quietly
        np.testing.assert_allclose(sphere_trace(collider, origin, direction), expected, atol=1e-5)
        # 14 distance queries: d_0 .. d_13.
        np.testing.assert_allclose(sphere_trace(collider, origin, direction, max_steps=14),
                                   expected, atol=1e-5)
        assert sphere_trace(collider, origin, direction, max_steps=13) is None


def test_sphere_trace_stops_within_its_tolerance(ball):
    """On a curved surface the march stops within 1e-5 of the domain's size before it."""
    from collider_cli.views.collider import sphere_trace

    mesh, collider = ball
    origin, direction = np.array([1.0, 2.0, 40.0]), np.array([0.0, 0.0, -1.0])
    exact = first_hit(mesh, origin, direction)
    hit = sphere_trace(collider, origin, direction)
    tolerance = 1e-5 * 24.0  # the domain is 24 cm wide
    assert 0.0 <= hit[2] - exact[2] < tolerance
    np.testing.assert_allclose(hit[:2], origin[:2])


def test_probe_text(brick):
    from collider_cli.views.collider import probe_text

    _, collider = brick
    text, fields = probe_text(collider, np.array([7.0, 0.0, 0.0]), eps=EPS_CM)
    assert text == ("**probe** (7, 0, 0) cm  \n"
                    "distance **20 mm**  \n"
                    "normal (1, 0, 0)  \n"
                    "contact (5.1, 0, 0)  \n"
                    "collides **False** (eps 1 mm)")
    assert fields["distance"] == pytest.approx(2.0) and fields["collides"] is False
    np.testing.assert_allclose(fields["normal"], [1, 0, 0])
    np.testing.assert_allclose(fields["contact"], [5.1, 0, 0], atol=1e-6)
    # Half a millimetre above the top face, eps 1 mm: it collides, pushed out to the eps surface.
    text, fields = probe_text(collider, np.array([1.0, -2.0, 5.05]), eps=EPS_CM)
    assert "distance **0.5 mm**" in text and "collides **True** (eps 1 mm)" in text
    assert fields["collides"] is True
    np.testing.assert_allclose(fields["contact"], [1.0, -2.0, 5.1], atol=1e-6)
    assert fields["normal"].dtype == np.float64 and fields["contact"].dtype == np.float64
    text, _ = probe_text(collider, np.array([0.0, 0.0, 6.0]), eps=0.25)
    assert text.endswith("collides **False** (eps 2.5 mm)")
    # 2 mm above the face: outside the default eps (1 mm), inside 2.5 mm.
    text, fields = probe_text(collider, np.array([0.0, 0.0, 5.2]), eps=0.25)
    assert fields["collides"] is True and text.endswith("collides **True** (eps 2.5 mm)")
    np.testing.assert_allclose(fields["contact"], [0.0, 0.0, 5.25], atol=1e-6)


# -- the page ------------------------------------------------------------------------------------


def test_page_title_label_controls_and_camera(ball, ball_page):
    _, collider = ball
    page, first = ball_page
    server = page.server
    assert panel_label(server) == "collider ball (mesh)"
    assert page.title.content == ("**ball**: mesh collider, cm (0.01 m per unit), collider "
                                  "frame; grid 16^3 over the domain box")
    level = page.level
    assert (level.label, level.min, level.max) == ("level (mm)", -10.0, 10.0)
    assert level.step == pytest.approx(0.05) and level.value == 0.0
    assert level.hint == ("show the surface distance == level; eps = 1 mm is the offset surface "
                          "contacts are projected to")
    assert page.eps_button.label == "level = eps (1 mm)"
    assert page.probe_point.label == "probe point" and page.probe_point.step == 1e-4
    assert page.probe_point.hint == "collider frame, cm; or click the surface"
    assert page.probe_button.label == "query probe"
    assert first["probe_out"] == "click the surface or type a point"
    assert page.show_wire.label == "exact mesh wireframe" and page.show_wire.value is False
    assert node(server, "/exact_mesh").visible is False
    # A static collider: no time slider, no play (what a browser receives).
    assert gui_labels(server) == ["level (mm)", "level = eps (1 mm)", "exact mesh wireframe",
                                  "probe point", "query probe"]
    assert (page.time, page.play, page.time_label, page.grids) == (None, None, None, None)
    # The domain box (collider frame), and the camera framing it with +y up.
    lo, hi = collider.domain_min, collider.domain_max
    np.testing.assert_allclose([lo, hi], [[-12.0] * 3, [12.0] * 3])
    domain = node(server, "/domain")
    from collider_cli.views.page import box_edges

    np.testing.assert_array_equal(domain.points, box_edges(lo, hi).astype(np.float32))
    assert np.all(domain.colors == 60)
    assert (domain.thickness, domain.thickness_units) == (1.5, "screen")
    camera = server.initial_camera
    np.testing.assert_allclose(camera.look_at, [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(camera.up, [0, 1, 0])
    np.testing.assert_allclose(camera.position, [-24.0, 14.4, 18.0])  # 24 (0.75 z - x + 0.6 y)


def test_page_shows_the_surface_coloured_by_its_error(ball, ball_page):
    """The first surface: the zero level set, each vertex coloured by its exact distance to the
    mesh in mm on a scale fixed by the 95th percentile of |error|; its figures in the status."""
    mesh, collider = ball
    page, first = ball_page
    verts, faces = expected_surface(collider, 16, 0.0)
    shown = first["surface"]
    np.testing.assert_allclose(shown.vertices, verts, atol=1e-5)
    np.testing.assert_array_equal(shown.faces, faces)
    error = exact_error_mm(mesh, verts, 0.0)
    clip = float(np.percentile(np.abs(error), 95))
    assert 0.1 < clip < 10  # a coarse grid: a fraction of a millimetre to millimetres
    colours = shown.visual.vertex_colors
    np.testing.assert_array_equal(colours[:, :3], diverging(error, clip))
    assert np.all(colours[:, 3] == 255)
    assert (colours[:, 0] > colours[:, 2] + 50).any() and (colours[:, 2] > colours[:, 0] + 50).any()
    assert first["status"] == (f"surface at level 0 mm: {len(faces):,} triangles  \n"
                               f"error vs exact mesh: mean |e| {np.abs(error).mean():.3g} mm, "
                               f"max {np.abs(error).max():.3g} mm")
    from collider_cli.views.collider import colour_bar_html

    assert page.bar.content == colour_bar_html(clip)


def test_level_slider_and_the_eps_button(ball, ball_page):
    """Moving the level slider redraws the level set at that many mm, its colours on the first
    surface's scale; "level = eps" moves the slider to eps (1 mm) and redraws."""
    from collider_cli.views.collider import colour_bar_html

    mesh, collider = ball
    page, _ = ball_page
    clip = float(np.percentile(np.abs(exact_error_mm(mesh, expected_surface(collider, 16, 0.0)[0],
                                                     0.0)), 95))
    page.level.value = -2.5  # mm: 0.25 cm inside
    verts, faces = expected_surface(collider, 16, -0.25)
    shown = glb_mesh(page.server, "/surface")
    np.testing.assert_allclose(shown.vertices, verts, atol=1e-5)
    error = exact_error_mm(mesh, verts, -0.25)
    np.testing.assert_array_equal(shown.visual.vertex_colors[:, :3], diverging(error, clip))
    assert page.status.content.startswith(f"surface at level -2.5 mm: {len(faces):,} triangles  \n")
    assert page.bar.content == colour_bar_html(clip)  # the scale stays
    click(page.eps_button)
    assert page.level.value == pytest.approx(1.0)
    verts, faces = expected_surface(collider, 16, EPS_CM)
    radius = np.linalg.norm(glb_mesh(page.server, "/surface").vertices, axis=1)
    np.testing.assert_allclose(radius, np.linalg.norm(verts, axis=1), atol=1e-5)
    assert page.status.content.startswith(f"surface at level 1 mm: {len(faces):,} triangles")
    # Deeper than the ball's centre: no such level set in the domain; the last surface stays.
    page.level.value = -150.0
    assert page.status.content == "no surface at level -150 mm in the domain"
    np.testing.assert_allclose(np.linalg.norm(glb_mesh(page.server, "/surface").vertices, axis=1),
                               radius, atol=1e-5)


def test_wireframe_checkbox(ball, ball_page):
    mesh, _ = ball
    page, _ = ball_page
    wire = node(page.server, "/exact_mesh")
    np.testing.assert_array_equal(wire.vertices, mesh.vertices.astype(np.float32))
    np.testing.assert_array_equal(wire.faces, mesh.faces)
    assert wire.wireframe and wire.opacity == pytest.approx(0.35) and tuple(wire.color) == (40, 40, 40)
    page.show_wire.value = True
    assert wire.visible
    page.show_wire.value = False
    assert not wire.visible


def _assert_probe_drawn(page, collider, point):
    from collider_cli.views.collider import probe_text

    answer = collider.query(point[None], ["normal", "contact"], eps=EPS_CM)
    normal, contact = answer.normal[0].astype(float), answer.contact[0].astype(float)
    assert page.probe_out.content == probe_text(collider, point, EPS_CM)[0]
    arrow = node(page.server, "/probe/normal")
    # The normal as an arrow 15 % of the domain's size (24 cm) long, from the point.
    np.testing.assert_allclose(arrow.points, [[point, point + 3.6 * normal]], atol=1e-5)
    assert np.all(arrow.colors == [250, 140, 0]) and arrow.thickness == 3.0
    dots = node(page.server, "/probe/points")
    np.testing.assert_allclose(dots.points.astype(np.float64), [point, contact], atol=1e-2)
    assert dots.colors.tolist() == [[250, 140, 0], [20, 160, 60]]
    assert dots.point_size == pytest.approx(0.24) and dots.point_shape == "circle"


def test_probe_a_typed_point(ball, ball_page):
    _, collider = ball
    page, _ = ball_page
    point = np.array([3.0, 4.0, 12.0])
    page.probe_point.value = tuple(point)
    click(page.probe_button)
    _assert_probe_drawn(page, collider, point)
    assert "collides **False**" in page.probe_out.content


def test_click_the_surface_probes_where_the_ray_hits(ball, ball_page):
    from collider_cli.views.collider import sphere_trace

    _, collider = ball
    page, _ = ball_page
    origin, direction = np.array([2.0, -1.0, 30.0]), np.array([0.1, 0.0, -1.0])
    click_canvas(page.server, origin, direction)
    hit = sphere_trace(collider, origin, direction)
    unit = direction / np.linalg.norm(direction)
    exact = first_hit(ball[0], origin, unit)
    assert 0.0 <= np.dot(hit - exact, -unit) < 1e-3  # on the ball, from above, just before it
    assert 0.0 <= collider.query(hit[None], ["distance"]).distance[0] < 1e-5 * 24.0
    np.testing.assert_allclose(page.probe_point.value, hit)
    _assert_probe_drawn(page, collider, hit)
    assert "collides **True**" in page.probe_out.content  # on the surface: within eps
    before = node(page.server, "/probe/points").points.copy()
    click_canvas(page.server, [40.0, 40.0, 40.0], [1.0, 0.0, 0.0])  # into the void
    assert page.probe_out.content == "the click missed the collider"
    np.testing.assert_allclose(page.probe_point.value, hit)  # the last probe stays
    np.testing.assert_array_equal(node(page.server, "/probe/points").points, before)


def test_page_without_mesh_is_plain(ball, capsys):
    """Without the exact mesh: one plain colour, no error figures, no colour bar, no wireframe.
    On the address and port asked for, quietly (a loopback address)."""
    _, collider = ball
    port = free_port()
    page, first = _serve(collider, None, port=port, resolution=8, show_progress=False)
    try:
        assert (page.server.get_host(), page.server.get_port()) == ("127.0.0.1", port)
        assert capsys.readouterr().err == ""  # no warning, no progress bar
        verts, faces = expected_surface(collider, 8, 0.0)
        assert first["status"] == f"surface at level 0 mm: {len(faces):,} triangles"
        colours = first["surface"].visual.vertex_colors
        assert len(colours) == len(verts) and np.all(colours == [170, 190, 210, 255])
        assert page.bar is None and page.show_wire is None
        assert page.server.scene.get_handle_by_name("/exact_mesh") is None
        np.testing.assert_allclose(page.server.initial_camera.up, [0, 0, 1])  # +z by default
        page.level.value = 3.0
        assert page.status.content == (f"surface at level 3 mm: "
                                       f"{len(expected_surface(collider, 8, 0.3)[1]):,} triangles")
    finally:
        page.server.stop()


def test_page_with_a_given_colour_scale(ball, capsys):
    from collider_cli.views.collider import colour_bar_html

    mesh, collider = ball
    page, first = _serve(collider, mesh, resolution=8, clip_mm=0.5)
    try:
        assert "ball grid" in capsys.readouterr().err  # by default, the grid's progress
        verts, _ = expected_surface(collider, 8, 0.0)
        np.testing.assert_array_equal(first["surface"].visual.vertex_colors[:, :3],
                                      diverging(exact_error_mm(mesh, verts, 0.0), 0.5))
        assert page.bar.content == colour_bar_html(0.5)
    finally:
        page.server.stop()
