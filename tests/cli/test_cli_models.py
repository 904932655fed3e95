"""``collider bake``, ``collider query`` and ``collider info`` as a new user would try them:
success, and for every bad input one clear error line, exit code 2, no traceback."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from collider_cli import main


@pytest.fixture(scope="module")
def sphere_obj(tmp_path_factory):
    """A 0.1 m icosphere as an OBJ file (metres)."""
    import trimesh

    path = tmp_path_factory.mktemp("meshes") / "ball.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=0.1).export(path)
    return path


@pytest.fixture
def models(small_sphere_model):
    """A model repository holding ``sphere`` (voxel 32^3, radius 0.1 m)."""
    return small_sphere_model.parent


def run(capsys, *argv):
    """``collider *argv`` in-process: (exit code, stdout, stderr)."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exit_:  # argparse's own usage errors
        code = exit_.code
    out, err = capsys.readouterr()
    return code, out, err


def assert_user_error(capsys, argv, message):
    code, out, err = run(capsys, *argv)
    assert code == 2, (code, out, err)
    assert "Traceback" not in err and "usage:" not in err
    assert len(err.strip().splitlines()) == 1, err  # one line, argparse's refusals too
    last = err.strip().splitlines()[-1]
    assert last.startswith("collider"), err
    assert message in last, last
    return last


@pytest.mark.parametrize("kind", ["voxel", "mesh", "kdtree"])
def test_bake_each_kind_then_query_and_info(capsys, tmp_path, sphere_obj, kind):
    code, out, err = run(capsys, "bake", sphere_obj, "--kind", kind, "--name", "ball",
                         "--resolution", 24, "--models", tmp_path, "--quiet")
    assert code == 0, err
    path = tmp_path / "ball.safetensors"
    assert path.is_file() and f"wrote {path}" in out and f"kind {kind}" in out
    code, out, err = run(capsys, "query", "ball", 0, 0, 0.2, 0, 0, -0.095, "--models", tmp_path)
    assert code == 0, err
    lines = out.strip().splitlines()
    assert len(lines) == 2
    distance = float(lines[0].split("distance=")[1].split()[0])
    assert abs(distance - 0.1) < (1e-3 if kind != "voxel" else 3e-3)
    assert "normal=" in lines[0] and "contact=" in lines[0] and "collides=False" in lines[0]
    assert "collides=True" in lines[1]  # inside the sphere
    code, out, err = run(capsys, "info", "ball", "--models", tmp_path)
    assert code == 0, err
    assert f"kind        {kind}" in out and f"{path.stat().st_size:,} bytes" in out
    assert "domain" in out and "accuracy" in out
    assert ("(approximate)" in out) == (kind == "kdtree")


def test_query_from_a_points_file_with_fields_pose_and_output(capsys, tmp_path, models):
    points = np.array([[0.0, 0.0, 0.3], [1.0, 0.0, 0.0]])
    np.save(tmp_path / "points.npy", points)
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 0.2]
    (tmp_path / "pose.json").write_text(json.dumps(pose.tolist()))
    code, _out, err = run(capsys, "query", "sphere", "--points", tmp_path / "points.npy",
                         "--fields", "distance,collides", "--pose", tmp_path / "pose.json",
                         "--eps", 0.002, "--output", tmp_path / "out.npz", "--models", models)
    assert code == 0, err
    saved = np.load(tmp_path / "out.npz")
    assert sorted(saved.files) == ["collides", "distance"]
    assert abs(saved["distance"][0] - 0.0) < 3e-3  # (0, 0, 0.3) is on the moved sphere
    assert saved["distance"][1] > 0.9 and not saved["collides"][1]


def test_query_accepts_a_model_path_and_negative_coordinates(capsys, models):
    code, out, err = run(capsys, "query", models / "sphere.safetensors", -0.2, 0, 0, "--fields", "distance")
    assert code == 0, err
    assert out.startswith("point [-0.2, 0.0, 0.0]  distance=0.1")


def test_info_lists_the_repository_and_prints_json(capsys, models):
    (models / "broken.safetensors").write_bytes(b"not a model at all")
    code, out, err = run(capsys, "info", "--models", models)
    assert code == 0, err
    assert "2 model(s)" in out and "sphere" in out and "voxel" in out
    assert "broken" in out and "unreadable" in out
    code, out, err = run(capsys, "info", "sphere", "--json", "--models", models)
    assert code == 0, err
    data = json.loads(out)
    assert data["kind"] == "voxel" and data["bytes"] == (models / "sphere.safetensors").stat().st_size
    assert data["settings"]["resolution"] == 32


@pytest.mark.parametrize("argv, message", [
    (["bake", "{tmp}/missing.obj", "--name", "x"], "no such mesh file"),
    (["bake", "{tmp}/blob.obj", "--name", "x"], "cannot read mesh"),
    (["bake", "{tmp}/empty.obj", "--name", "x"], "mesh is empty"),
    (["bake", "{tmp}/text.obj", "--name", "x"],
     "text.obj: not an OBJ file: no vertex (v) or face (f) line (it starts with 'hello world')"),
    (["bake", "{ball}", "--name", "x", "--bogus"],
     "collider bake: error: unrecognized arguments: --bogus (`collider bake --help` lists the options)"),
    (["eval", "sphere", "--mesh", "{ball}", "--units", "mm", "--models", "{models}"],
     "--units mm (0.001 m per unit) is not the unit sphere was made in (m, 1 m per unit)"),
    (["bake", "{tmp}/flat.obj", "--name", "x"], "mesh is flat"),
    (["bake", "{tmp}", "--name", "x"], "is a directory"),
    (["bake", "{ball}", "--name", "../evil"], "invalid model name"),
    (["bake", "{ball}", "--name", "x", "--resolution", "4"], "resolution must be in 8..1024"),
    (["bake", "{ball}", "--name", "x", "--scale", "0"], "--scale must be a finite number > 0"),
    (["bake", "{ball}", "--name", "x", "--units", "parsec"], "unknown --units 'parsec'"),
    (["bake", "{ball}", "--name", "x", "--padding", "-1"], "padding must be a finite number >= 0"),
    (["bake", "{ball}", "--name", "x", "--kind", "neural"], "invalid choice: 'neural'"),
    (["bake", "{ball}", "--name", "x", "--resolution", "many"], "invalid int value: 'many'"),
    (["bake", "{ball}"], "collider bake: error: the following arguments are required: --name (`collider bake --help`"),
    (["query", "nosuch", "0", "0", "0", "--models", "{models}"], "no model named 'nosuch'"),
    (["query", "sphere", "0", "0", "--models", "{models}"], "give x y z triples (got 2 numbers)"),
    (["query", "sphere", "--models", "{models}"], "give x y z triples (got 0 numbers)"),
    (["query", "sphere", "0", "0", "0", "--points", "{tmp}/p.npy", "--models", "{models}"], "not both"),
    (["query", "sphere", "--points", "{tmp}/missing.npy", "--models", "{models}"], "cannot read points"),
    (["query", "sphere", "--points", "{tmp}/flat.npy", "--models", "{models}"], "points must have shape (n, 3)"),
    (["query", "sphere", "nan", "0", "0", "--models", "{models}"], "'nan' is not a finite number"),
    (["query", "sphere", "0", "0", "0", "--fields", "distance,speed", "--models", "{models}"], "unknown field(s) ['speed']"),
    (["query", "sphere", "0", "0", "0", "--eps", "nan", "--models", "{models}"], "'nan' is not a finite number"),
    (["query", "sphere", "0", "0", "0", "--pose", "{tmp}/mirror.json", "--models", "{models}"], "reflection"),
    (["query", "sphere", "0", "0", "0", "--pose", "{tmp}/missing.json", "--models", "{models}"], "cannot read pose"),
    (["query", "sphere", "0", "0", "0", "--device", "tpu", "--models", "{models}"], "unknown device 'tpu'"),
    (["query", "sphere", "x", "0", "0", "--models", "{models}"], "'x' is not a number"),
    (["info", "nosuch", "--models", "{models}"], "no model named 'nosuch'"),
    (["info", "{tmp}/blob.safetensors"], "not a readable safetensors file"),
    (["info", "bad name!", "--models", "{models}"], "invalid model name"),
])
def test_bad_input_gives_one_clear_line_and_exit_2(capsys, tmp_path, sphere_obj, models, argv, message):
    (tmp_path / "blob.obj").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "empty.obj").write_text("# nothing\n")
    (tmp_path / "text.obj").write_text("hello world\nthis is not a mesh\n")
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "blob.safetensors").write_bytes(b"\x00" * 5)
    (tmp_path / "mirror.json").write_text(json.dumps(np.diag([1.0, 1.0, -1.0, 1.0]).tolist()))
    np.save(tmp_path / "p.npy", np.zeros((1, 3)))
    np.save(tmp_path / "flat.npy", np.zeros(6))
    argv = [a.format(tmp=tmp_path, ball=sphere_obj, models=models) for a in argv]
    assert_user_error(capsys, argv, message)


def test_the_installed_entry_point_runs_without_traceback(tmp_path):
    """Through a real process: ``python -m collider_cli`` (what ``collider`` runs)."""
    ok = subprocess.run([sys.executable, "-m", "collider_cli", "info", "--models", str(tmp_path)],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and "0 model(s)" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "collider_cli", "query", "ghost", "0", "0", "0",
                          "--models", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip() == f"collider query: error: no model named 'ghost' in {tmp_path} (models: none)"


def test_query_output_names_the_file_it_writes(capsys, models, tmp_path):
    code, out, err = run(capsys, "query", "sphere", 0, 0, 0, "--output", tmp_path / "result",
                         "--models", models)
    assert code == 0, err
    assert out.strip() == f"wrote {tmp_path / 'result.npz'} (1 points)"
    assert np.load(tmp_path / "result.npz")["distance"][0] < 0


def test_bake_says_what_the_mesh_is_its_sign_errors_and_what_to_run_next(capsys, tmp_path, sphere_obj):
    models = tmp_path / "my models"
    code, out, err = run(capsys, "bake", sphere_obj, "--name", "ball", "--resolution", "16", "--models", models,
                         "--quiet")
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0] == "mesh: 1,280 faces, watertight, 1 piece, no self-intersections"
    assert re.fullmatch(r"sign errors: \d+\.\d\d % of 20,000 points in the \+-1 mm band \(those farther than 0\.2 mm "
                        r"from the surface; against the exact winding-number sign\), mean distance error \d\.\d{4} mm",
                        lines[-2]), lines[-2]
    assert lines[-1] == f"next: collider eval ball --mesh {sphere_obj} --models '{models}'"
    code, out, err = run(capsys, "info", "ball", "--models", models)
    assert code == 0, err
    assert "  mesh: 1,280 faces, watertight, 1 piece, no self-intersections" in out.splitlines()
    assert f"`collider eval ball --mesh {sphere_obj.resolve()} --models '{models}'` measures it" in out
    code, out, err = run(capsys, "eval", "ball", "--mesh", sphere_obj, "--units", "m", "--models", models,
                         "--points", "1000", "--no-reconstruction", "--no-save", "--quiet")
    assert code == 0, err  # the model's own unit is accepted


def test_query_a_skinned_model_in_a_clip_or_at_joint_transforms(capsys, tmp_path, models):
    from collider_server.engine.modelfile import save_collider
    from collider_server.engine.skinning import pose_at
    from collider_server.making.skinned import skinned_arm, skinned_collider

    skin = skinned_arm()
    collider = skinned_collider(skin, "arm")
    save_collider(collider, tmp_path / "arm")
    transforms, rates = pose_at(skin, "reach", 1.3)
    (tmp_path / "joints.json").write_text(json.dumps(transforms.tolist()))
    np.save(tmp_path / "rates.npy", rates)
    point = [0.45, 0.0, 0.1]
    expected = collider.query([point], ["distance", "velocity"], time=1.3, clip="reach")
    for extra in (["--time", "1.3", "--clip", "reach"],
                  ["--joint-transforms", tmp_path / "joints.json", "--joint-velocities",
                   tmp_path / "rates.npy"]):
        code, out, _ = run(capsys, "query", "arm", *point, "--fields", "distance,velocity",
                           "--models", tmp_path, *extra)
        assert code == 0
        distance = float(re.search(r"distance=(\S+) m", out).group(1))
        assert distance == pytest.approx(float(expected.distance[0]), abs=1e-7)
        velocity = json.loads(re.search(r"velocity=(\[[^\]]*\])", out).group(1))
        np.testing.assert_allclose(velocity, expected.velocity[0], atol=1e-6)
    assert np.abs(expected.velocity).max() > 0.01
    for argv, message in (
            (["query", "arm", *point, "--time", "0.1", "--clip", "run", "--models", tmp_path],
             "model 'arm' has no clip 'run'; its clips are ['wave', 'reach']"),
            (["query", "arm", *point, "--models", tmp_path], "model 'arm' is skinned: give the time"),
            (["query", "arm", *point, "--joint-transforms", tmp_path / "none.json", "--models",
              tmp_path], "cannot read joint transforms"),
            (["query", "sphere", "0", "0", "0", "--time", "0.1", "--clip", "wave", "--models", models],
             "model 'sphere' has no skeleton: clip is for skinned models only")):
        assert_user_error(capsys, argv, message)
