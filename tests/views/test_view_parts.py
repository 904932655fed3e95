"""The browser views' geometry without a browser: the level surface of a collider, its error
colours, the probe and the click ray, and the command's errors. Sphere of radius 0.1 m (exact
``mesh`` collider), collider frame = world frame. The pages themselves: test_page.py,
test_collider_page.py, test_cloth_page.py (in process) and test_browser.py (in Chromium).
"""

from __future__ import annotations

import numpy as np
import pytest
from tests.conftest import SPHERE_RADIUS, make_sphere


@pytest.fixture(scope="module")
def sphere():
    from collider_server.making.bake import bake_collider

    shape = make_sphere()
    return shape, bake_collider(shape.mesh, "mesh", "sphere", show_progress=False)


def test_level_surface_lies_at_the_level(sphere):
    from collider_cli.views.collider import collider_grid
    from collider_server.making.surface import level_surface

    _shape, collider = sphere
    grid = collider_grid(collider, 40, show_progress=False)
    for level in (0.0, 0.005):  # the surface, and an eps offset surface 5 mm out
        verts, faces = level_surface(grid, level)
        radius = np.linalg.norm(verts, axis=1)
        # Trilinear marching cubes on a 40^3 grid (7 mm cells): within a fraction of a cell.
        assert np.abs(radius - (SPHERE_RADIUS + level)).max() < 1.5e-3
        assert faces.max() < len(verts)
    assert level_surface(grid, 10.0) is None  # no such level in the domain


def test_error_colours_and_surface_error(sphere):
    from collider_cli.views.collider import error_colors, surface_error_mm
    from collider_server.engine.meshes import ExactSDF

    shape, _collider = sphere
    colours = error_colors(np.array([-2.0, 0.0, 0.5, 1.0, 3.0]), clip_mm=1.0)
    assert colours[1].tolist() == [245, 245, 245]            # no error: white
    assert colours[3].tolist() == colours[4].tolist()        # clipped at +clip
    assert colours[3][0] > 150 > colours[3][2]               # outside: red
    assert colours[0][2] > 150 > colours[0][0]               # inside: blue
    # Points 1 mm outside the exact sphere, shown as the level-0 surface: +1 mm error.
    points = np.array([[SPHERE_RADIUS + 1e-3, 0, 0], [0, 0, -(SPHERE_RADIUS + 1e-3)]])
    error = surface_error_mm(ExactSDF(shape.mesh), points, 0.0, 1.0)
    np.testing.assert_allclose(error, 1.0, atol=0.05)


def test_probe_and_click_ray(sphere):
    from collider_cli.views.collider import probe_text, sphere_trace

    _, collider = sphere
    # A ray from outside along -x hits the sphere at x = +r.
    hit = sphere_trace(collider, np.array([0.5, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]))
    np.testing.assert_allclose(hit, [SPHERE_RADIUS, 0, 0], atol=1e-4)
    assert sphere_trace(collider, np.array([0.5, 0.5, 0.5]), np.array([1.0, 0.0, 0.0])) is None
    text, fields = probe_text(collider, np.array([0.0, 0.0, SPHERE_RADIUS + 5e-4]), eps=1e-3)
    assert fields["collides"] and abs(fields["distance"] - 5e-4) < 1e-4
    np.testing.assert_allclose(fields["normal"], [0, 0, 1], atol=1e-3)
    np.testing.assert_allclose(fields["contact"], [0, 0, SPHERE_RADIUS + 1e-3], atol=1e-4)
    assert "0.5" in text and "collides **True**" in text


def test_view_command_errors(capsys):
    from collider_cli import main

    assert main(["view"]) == 2
    assert "give a model NAME or --replay" in capsys.readouterr().err
    assert main(["view", "bunny", "--replay", "out/x"]) == 2
    pytest.importorskip("viser")
    assert main(["view", "--replay", "no/such/run"]) == 2
    assert "no/such/run.obj: no such file" in capsys.readouterr().err


@pytest.mark.parametrize("flags, up", [([], "+y"), (["--fit-size", "0.3"], "+y"),
                                       (["--scale", "2"], "+y"), (["--z-up"], "+z"),
                                       (["--z-up", "--fit-size", "0.3"], "+z")])
def test_view_up_follows_the_placements_z_up_flag(tmp_path, capsys, flags, up):
    """A Y-up mesh placed with a scale alone stays Y-up in the view (issue 21, item 10): only the
    placement's --z-up turns it."""
    import trimesh

    from collider_cli import main
    from collider_cli.commands.view import view_up
    from collider_server.engine.repository import ModelRepository

    mesh_file = tmp_path / "box.obj"
    trimesh.creation.box(extents=(0.2, 0.1, 0.05)).export(mesh_file)
    assert main(["bake", str(mesh_file), "--kind", "mesh", "--name", "box", *flags,
                 "--models", str(tmp_path), "--quiet"]) == 0, capsys.readouterr().err
    info = ModelRepository(tmp_path).load("box", "cpu").info
    assert view_up(info.source["transform"]) == up


def test_view_up_of_the_shipped_models():
    from tests.conftest import REPO_ROOT

    from collider_cli.commands.view import view_up
    from collider_server.engine.repository import ModelRepository

    repository = ModelRepository(REPO_ROOT / "models")
    # dragon: made with --z-up --fit-size (a scaled rotation); bunny: kept as is.
    assert view_up(repository.load("dragon", "cpu").info.source["transform"]) == "+z"
    assert view_up(repository.load("bunny", "cpu").info.source["transform"]) == "+y"


def test_view_command_errors_on_animated_models(capsys):
    """The exact animation of an animated model is its OBJ and vertex cache together, on the
    model's clock; each wrong combination is refused in one line before anything is served."""
    pytest.importorskip("viser")
    from tests.conftest import REPO_ROOT

    from collider_cli import main

    obj, pc2 = (str(REPO_ROOT / "examples" / "animations" / f"arm.{ext}") for ext in ("obj", "pc2"))
    models = ["--models", str(REPO_ROOT / "models")]
    cases = [
        (["arm", "--mesh", obj], ("arm is animated: give the frames it was made from, --mesh OBJ "
                                 "--animation CACHE (arm was made from arm.obj and arm.pc2, 25 "
                                 "frames at 24 fps)")),
        (["arm", "--animation", pc2], "--animation needs --mesh (the OBJ whose vertices it moves)"),
        (["arm", "--mesh", obj, "--animation", pc2, "--fps", "12"],
         (f"{pc2} at 12 fps lasts 2 s, but arm's animation lasts 1 s (arm was made from arm.obj and "
         "arm.pc2, 25 frames at 24 fps)")),
        (["bunny", "--mesh", obj, "--animation", pc2],
         "bunny is static: --animation and --fps are for animated models"),
        (["bunny", "--fps", "24"], "bunny is static: --animation and --fps are for animated models"),
    ]
    for argv, message in cases:
        assert main(["view", *argv, *models]) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
