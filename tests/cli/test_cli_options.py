"""Options shared by every ``collider`` command: no number may be NaN or infinite, and one set of
mesh placement options (``--scale``, ``--fit-size``, ``--z-up``, ``--units``) for every command
that reads a mesh."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from collider_cli import build_parser, main
from collider_cli.commands.options import finite_float
from collider_server.engine.meshes import Mesh
from collider_server.making.placement import MeshPlacement


def subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def numeric_options():
    """(command, option) for every option taking a float, over every command."""
    for command, sub in subcommands().items():
        for action in sub._actions:
            if action.type is finite_float and action.option_strings:
                yield command, action.option_strings[-1]


def minimal_argv(command: str, sub: argparse.ArgumentParser) -> list[str]:
    """Placeholders for the positionals and required options of ``command``."""
    argv = [command]
    for action in sub._actions:
        if not action.option_strings and action.nargs not in ("*", "?"):
            argv.append("1" if action.type is finite_float else "x")
        elif action.option_strings and action.required:
            argv += [action.option_strings[-1], "x"]
    return argv


def test_no_command_has_a_float_option_that_accepts_nan():
    for command, sub in subcommands().items():
        for action in sub._actions:
            assert action.type is not float, (command, action.dest)
    options = set(numeric_options())
    # Spot-check that the walk sees options of several command groups.
    for expected in (("train", "--max-minutes"), ("bake", "--fit-size"), ("serve", "--max-wait-ms"),
                     ("query", "--eps"), ("eval", "--scale")):
        assert expected in options


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf", "NaN"])
def test_every_numeric_option_of_every_command_refuses_non_finite(capsys, bad):
    commands = subcommands()
    checked = 0
    for command, option in numeric_options():
        argv = minimal_argv(command, commands[command]) + [f"{option}={bad}"]  # "-inf" reads as a flag otherwise
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code == 2, argv
        err = capsys.readouterr().err
        assert f"{bad!r} is not a finite number" in err, (argv, err)
        assert "Traceback" not in err
        checked += 1
    assert checked >= 10


def test_query_coordinates_refuse_non_finite(capsys):
    with pytest.raises(SystemExit):
        main(["query", "model", "0", "nan", "0"])
    assert "'nan' is not a finite number" in capsys.readouterr().err


@pytest.fixture(scope="module")
def box_mesh() -> Mesh:
    """An axis-aligned box 2 x 4 x 1 (file units), Y its longest side."""
    import trimesh

    box = trimesh.creation.box(extents=(2.0, 4.0, 1.0))
    return Mesh(np.asarray(box.vertices), np.asarray(box.faces), "box", "0" * 64)


def test_placement_fits_the_largest_side_and_turns_y_up_to_z_up(box_mesh):
    placed, transform = MeshPlacement(fit_size=0.2, z_up=True).apply(box_mesh)
    extent = np.ptp(placed.vertices, axis=0)
    np.testing.assert_allclose(extent, [0.1, 0.05, 0.2], atol=1e-12)  # y (longest) is now z
    np.testing.assert_allclose(placed.vertices, box_mesh.transformed(transform).vertices)
    same, identity = MeshPlacement().apply(box_mesh)
    assert same is box_mesh and np.array_equal(identity, np.eye(4))
    assert MeshPlacement(scale=0.5, units="mm").meters_per_unit == 0.001


@pytest.mark.parametrize("placement, message", [
    (MeshPlacement(scale=0.0), "--scale must be a finite number > 0"),
    (MeshPlacement(scale=float("nan")), "--scale"),
    (MeshPlacement(fit_size=-1.0), "--fit-size"),
    (MeshPlacement(units="furlong"), "unknown --units 'furlong'"),
    (MeshPlacement(units="x", meters_per_unit_override=float("inf")), "--meters-per-unit"),
])
def test_bad_placement_is_refused_naming_the_option(box_mesh, placement, message):
    with pytest.raises(ValueError, match=message):
        placement.apply(box_mesh)


def test_bake_takes_fit_size_and_z_up(capsys, tmp_path, box_mesh):
    import json

    import trimesh

    mesh_file = tmp_path / "box.obj"
    trimesh.Trimesh(box_mesh.vertices, box_mesh.faces).export(mesh_file)
    code = main(["bake", str(mesh_file), "--kind", "mesh", "--name", "box", "--fit-size", "200",
                 "--z-up", "--units", "mm", "--padding", "0", "--models", str(tmp_path), "--quiet"])
    assert code == 0, capsys.readouterr().err
    capsys.readouterr()
    assert main(["info", "box", "--models", str(tmp_path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(np.subtract(info["domain_max"], info["domain_min"]), [100, 50, 200], rtol=1e-9)
    assert info["units"] == "mm" and info["meters_per_unit"] == 0.001
    np.testing.assert_allclose(info["source"]["transform"], MeshPlacement(fit_size=200, z_up=True).transform(box_mesh))
    code = main(["bake", str(mesh_file), "--kind", "mesh", "--name", "b", "--fit-size", "0",
                 "--models", str(tmp_path), "--quiet"])
    assert code == 2 and "--fit-size must be a finite number > 0, got 0.0" in capsys.readouterr().err


def test_info_json_stays_strict_json_when_a_model_holds_nan(capsys, small_sphere_model):
    import json

    from collider_server.engine.modelfile import load_collider, save_collider

    collider = load_collider(small_sphere_model, "cpu")
    # What `collider train --max-minutes nan` stored before it was refused.
    collider.info.settings["training"] = {"max_minutes": float("nan"), "steps": 10}
    save_collider(collider, small_sphere_model)
    assert main(["info", str(small_sphere_model), "--json"]) == 0
    out, err = capsys.readouterr()

    def refuse(constant):
        raise AssertionError(f"invalid JSON constant {constant}")

    data = json.loads(out, parse_constant=refuse)
    assert data["settings"]["training"] == {"max_minutes": None, "steps": 10}
    assert "settings.training.max_minutes is not a finite number" in err


def test_train_config_refuses_a_non_finite_time_budget():
    from collider_server.making.training import TrainConfig

    for bad in (float("nan"), float("inf"), 0.0):
        with pytest.raises(ValueError, match="max_minutes must be a finite number > 0"):
            TrainConfig(max_minutes=bad).check()


def test_eval_against_another_mesh_refuses_to_store_the_figures(capsys, tmp_path):
    import trimesh

    from collider_server.engine.modelfile import read_info

    ball, other = tmp_path / "ball.obj", tmp_path / "other.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=0.1).export(ball)
    trimesh.creation.icosphere(subdivisions=3, radius=0.12).export(other)
    models = tmp_path / "models"
    assert main(["bake", str(ball), "--kind", "mesh", "--name", "ball", "--models", str(models), "--quiet"]) == 0
    evaluate = ["eval", "ball", "--models", str(models), "--points", "300", "--no-reconstruction", "--quiet"]
    capsys.readouterr()

    code = main(evaluate + ["--mesh", str(other)])
    out, err = capsys.readouterr()
    assert code == 2 and "+-1mm" in out  # the figures are printed, not stored
    assert f"{other} is not the mesh ball was made from" in err.strip().splitlines()[-1]
    assert "--store-anyway" in err
    assert not read_info(models / "ball.safetensors").accuracy

    code = main(evaluate + ["--mesh", str(ball), "--scale", "2"])
    assert code == 2 and "placement differs" in capsys.readouterr().err
    assert main(evaluate + ["--mesh", str(other), "--no-save"]) == 0
    assert not read_info(models / "ball.safetensors").accuracy

    assert main(evaluate + ["--mesh", str(other), "--store-anyway"]) == 0
    assert read_info(models / "ball.safetensors").accuracy["band_1mm"]["points"] == 300
    capsys.readouterr()
    assert main(evaluate + ["--mesh", str(ball), "--points", "200"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert read_info(models / "ball.safetensors").accuracy["band_1mm"]["points"] == 200


def test_query_only_colliding_from_the_command_line(capsys, small_sphere_model):
    models = small_sphere_model.parent
    argv = ["query", "sphere", "0", "0", "0.0995", "0", "0", "0.3", "--models", str(models),
            "--fields", "normal,contact,collides", "--only-colliding"]
    assert main(argv) == 0
    inside, outside = capsys.readouterr().out.strip().splitlines()
    assert "collides=True" in inside and "normal=[0.0, 0.0, 0.0]" not in inside
    assert "collides=False" in outside and "normal=[0.0, 0.0, 0.0]" in outside
    assert "contact=[0.0, 0.0, 0.3" in outside
