"""``collider animate walker``, ``collider bake CHARACTER --kind skinned`` and ``collider info`` of
a skinned model, as a user runs them: the files and models they make, what they print, and one
line, exit 2, no traceback for each bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from collider_contract.point_cache import read_pc2
from collider_server.engine.modelfile import load_collider
from collider_server.engine.skinning import pose_at, skin_vertices
from collider_server.making.placement import Y_UP_TO_Z_UP
from collider_server.making.walker import make_walker

from .test_cli_models import assert_user_error, run

SAMPLE = Path(__file__).parents[1] / "data" / "gltf" / "RiggedSimple.gltf"


@pytest.fixture(scope="module")
def walker_run(tmp_path_factory):
    from collider_cli import main

    folder = tmp_path_factory.mktemp("walker")
    code = main(["animate", "walker", "--output", str(folder / "out"), "--bake", "skinned",
                 "--models", str(folder / "models"), "--quiet"])
    assert code == 0
    return folder


def test_animate_walker_writes_the_character_and_its_walk(walker_run):
    out = walker_run / "out"
    assert {p.name for p in out.iterdir()} == {"walker.obj", "walker.pc2", "walker.glb"}
    assert (out / "walker.glb").stat().st_size < 2_000_000
    collider = load_collider(walker_run / "models" / "walker-skinned.safetensors")
    skin = collider.skin
    assert skin.skeleton.joint_count == 20 and [c.name for c in skin.clips] == ["walk", "wave"]
    assert 1.70 < np.ptp(skin.vertices[:, 2]) < 1.76  # z up, about 1.73 m tall
    # The skinned model (from the .glb, placed z up) at frame k's time is the PC2's frame k; the
    # file's seam put its vertices in another order: matched by rest position.
    where = {tuple(v): i for i, v in enumerate(skin.vertices)}
    order = [where[tuple(v)] for v in make_walker().vertices @ Y_UP_TO_Z_UP[:3, :3].T]
    frames = read_pc2(out / "walker.pc2")
    assert frames.shape == (31, len(skin.vertices), 3)
    for k in (0, 7, 16, 30):
        posed = skin_vertices(skin, pose_at(skin, "walk", k / 30.0)[0])
        np.testing.assert_allclose(posed[order], frames[k], atol=1e-6)  # PC2 stores float32
    assert np.abs(frames[7] - frames[0]).max() > 0.1  # the legs swing


def test_bake_skinned_then_info_shows_the_skeleton_and_clips(capsys, tmp_path):
    code, out, err = run(capsys, "bake", SAMPLE, "--kind", "skinned", "--name", "cylinder",
                         "--fit-size", 1.0, "--models", tmp_path)
    assert code == 0, err
    assert "kind skinned: 2 joints, 1 clip(s): animation 0 2.08333 s; they clamp" in out
    code, out, _ = run(capsys, "info", "cylinder", "--models", tmp_path)
    assert code == 0
    assert "clips       1 clip(s): animation 0 2.08333 s (6 channels)" in out
    assert "skeleton    2 joints" in out and "\n                node 2\n                  node 3\n" in out
    assert "channels" not in out.replace("(6 channels)", "")
    code, out, _ = run(capsys, "info", "cylinder", "--models", tmp_path, "--json")
    info = json.loads(out)
    assert info["skeleton"]["parents"] == [-1, 0]
    assert info["source"]["transform"][0][0] == pytest.approx(1.0 / 9.150154113769531)


def test_bad_characters_are_one_line_errors(capsys, tmp_path):
    broken = tmp_path / "broken.gltf"
    broken.write_text('{"asset": {"version": "2.0"}, "nodes": [], "meshes": []}')
    assert_user_error(capsys, ["bake", broken, "--kind", "skinned", "--name", "x", "--models", tmp_path],
                      "broken.gltf: no skinned mesh: 0 mesh(es)")
    assert_user_error(capsys, ["bake", tmp_path / "none.glb", "--kind", "skinned", "--name", "x",
                               "--models", tmp_path], "none.glb: no such glTF file")
    obj = tmp_path / "a.obj"
    obj.write_text("v 0 0 0\n")
    assert_user_error(capsys, ["bake", obj, "--kind", "skinned", "--name", "x", "--models", tmp_path],
                      "a skinned character is a glTF 2.0 file")
    assert_user_error(capsys, ["bake", SAMPLE, "--kind", "skinned", "--name", "x", "--models", tmp_path,
                               "--animation", "a.pc2", "--fps", 30],
                      "a skinned character brings its own clips")
    assert_user_error(capsys, ["animate", "arm", "--bake", "skinned", "--output", tmp_path],
                      "--bake takes some of ['mesh', 'voxel'] for arm")


def test_train_character_makes_its_articulated_network(trained_character):
    """``collider train SAMPLE`` (the shared run of ``trained_character``: 20 steps)."""
    code, out, err = trained_character["code"], trained_character["out"], trained_character["err"]
    assert code == 0, err
    assert "kind neural-skinned: 2 joints" in out and "20 steps" in out
    assert "label dilation " in out and "rows a point" in out  # the grid's choice, in one line
    collider = load_collider(trained_character["models"] / "cylinder-neural.safetensors")
    assert collider.info.kind == "neural-skinned" and collider.skin.skeleton.joint_count == 2
    answer = collider.query(np.zeros((1, 3)), "distance", clip=None, time=0.5)
    assert np.isfinite(answer.distance).all()


def test_train_character_refuses_a_mesh_preset_in_one_line(capsys, tmp_path):
    assert_user_error(capsys, ["train", SAMPLE, "--name", "c", "--preset", "grid", "--models", tmp_path],
                      "--preset is for meshes and vertex caches")


def test_eval_of_skinned_models_reports_clip_times_and_random_poses(capsys, tmp_path, trained_character):
    """`collider eval` of the exact and the articulated model of a public glTF character: each pose
    set reported apart, against the exact skin of the file at each pose; the exact kind's errors
    nil, the figures stored and shown by `collider info`. (The network: a copy of the shared
    20-step run of ``trained_character``, eval writes its figures into the file.)"""
    code, _, err = run(capsys, "bake", SAMPLE, "--kind", "skinned", "--name", "cylinder", "--fit-size", 1.0,
                       "--models", tmp_path)
    assert code == 0, err
    assert trained_character["code"] == 0, trained_character["err"]
    shutil.copy(trained_character["models"] / "cylinder-neural.safetensors", tmp_path)
    reports = {}
    for model in ("cylinder", "cylinder-neural"):
        report = tmp_path / f"{model}.json"
        code, out, err = run(capsys, "eval", model, "--mesh", SAMPLE, "--models", tmp_path, "--points", 1500,
                             "--times", 2, "--poses", 3, "--quiet", "--report", report)
        assert code == 0, err
        assert "2 random clip times (animation 0; asked by clip and time)" in out
        assert "3 random poses: random clip times (animation 0), every joint's local rotation then turned" in out
        assert f"figures written into {tmp_path / (model + '.safetensors')}" in out
        reports[model] = json.loads(report.read_text())
    for report in reports.values():
        assert [p["perturbed"] for p in report["random_poses"]["poses"]] == [True] * 3
        assert [p["perturbed"] for p in report["clip_times"]["poses"]] == [False] * 2
        for part in ("clip_times", "random_poses"):
            assert report[part]["band_1mm"]["points"] == 1500 and report[part]["box"]["points"] == 1500
    for part in ("clip_times", "random_poses"):
        assert reports["cylinder"][part]["band_1mm"]["distance_max_mm"] < 1e-4  # float32 answers
        neural = reports["cylinder-neural"][part]["band_1mm"]
        assert np.isfinite(neural["distance_max_mm"]) and neural["distance_max_mm"] > 1e-3  # 20 steps: not exact
    code, out, _ = run(capsys, "info", "cylinder-neural", "--models", tmp_path)
    assert code == 0 and "3 random poses" in out and "2 random clip times" in out


def test_eval_of_a_skinned_model_refuses_what_is_not_its_character_in_one_line(capsys, tmp_path):
    code, _, err = run(capsys, "bake", SAMPLE, "--kind", "skinned", "--name", "cylinder", "--models", tmp_path)
    assert code == 0, err
    assert_user_error(capsys, ["eval", "cylinder", "--mesh", SAMPLE, "--models", tmp_path, "--animation", "a.pc2"],
                      "cylinder is skinned: --animation and --fps are for vertex caches")
    assert_user_error(capsys, ["eval", "cylinder", "--mesh", SAMPLE, "--models", tmp_path, "--poses", 0],
                      "--poses must be a positive number of random poses, got 0")
    obj = tmp_path / "a.obj"
    obj.write_text("v 0 0 0\n")
    assert_user_error(capsys, ["eval", "cylinder", "--mesh", obj, "--models", tmp_path],
                      "a skinned character is a glTF 2.0 file")
