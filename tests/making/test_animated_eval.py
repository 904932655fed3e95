"""``collider eval`` on animated models as a user runs it: the figures at random times between
frames against the exact interpolated mesh at each time, and one clear line for an animation that
is missing or not the model's. The voxel keyframe error shrinks with resolution and keyframes
(real bakes of the shipped arm). Metres, seconds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tests.cli.test_cli_models import assert_user_error, run

from collider_contract.point_cache import PC2Writer, read_pc2

ROOT = Path(__file__).resolve().parents[2]
ARM_OBJ, ARM_PC2 = ROOT / "examples/animations/arm.obj", ROOT / "examples/animations/arm.pc2"


@pytest.fixture(scope="module")
def arm_models(tmp_path_factory):
    """The shipped arm baked as `collider bake` does: an exact model and a coarse voxel one with 3
    keyframes (0, 0.5 and 1 s), 24 fps, looping."""
    from collider_cli import main

    models = tmp_path_factory.mktemp("models")
    for kind, extra in (("mesh", []), ("voxel", ["--resolution", "24", "--keyframes", "3"])):
        assert main(["bake", str(ARM_OBJ), "--animation", str(ARM_PC2), "--fps", "24", "--loop", "--kind", kind,
                     "--name", f"arm-{kind}", "--models", str(models), "--quiet", *extra]) == 0
    return models


def eval_report(capsys, tmp_path, model, models, *extra):
    report = tmp_path / f"{model}.json"
    code, out, err = run(capsys, "eval", model, "--mesh", ARM_OBJ, "--animation", ARM_PC2, "--models", models,
                         "--points", 3000, "--times", 6, "--quiet", "--no-save", "--report", report, *extra)
    assert code == 0, err
    return json.loads(report.read_text()), out


def test_eval_measures_an_animated_model_at_random_times_between_frames(capsys, tmp_path, arm_models):
    exact, out = eval_report(capsys, tmp_path, "arm-mesh", arm_models)
    voxel, out_voxel = eval_report(capsys, tmp_path, "arm-voxel", arm_models)
    times = np.array(exact["times_s"])
    assert len(times) == 6 and exact["duration_s"] == 1.0
    assert ((0 <= times) & (times < 1.0)).all() and len(set(times.round(6))) == 6
    # Not on a frame (k / 24 s), so not on a keyframe either: between frames, where grids are blended.
    frames = times * 24
    assert (np.abs(frames - np.round(frames)) > 1e-3).all(), times
    assert times.max() - times.min() > 0.2  # spread over the animation, not one moment
    assert "at 6 random times in [0, 1) s" in out and f"{times[0]:.4f}" in out
    assert voxel["times_s"] == exact["times_s"]  # seeded: the same times for every model
    # The truth is the mesh interpolated at each time: the exact kind meets it (a truth taken at
    # a frame instead would be millimetres off the bending arm)...
    for band in ("band_1mm", "band_10mm", "box"):
        assert exact[band]["points"] == 6 * 500 and exact[band]["distance_max_mm"] < 1e-3  # float32 answers
    # ...and the 3-keyframe grid does not: between its keyframes the elbow is far from the blend.
    assert voxel["band_1mm"]["distance_mean_mm"] > 0.5
    assert voxel["band_1mm"]["distance_p99_mm"] > 5.0
    assert "+-1mm" in out_voxel and "query (distance+normal+contact) at t =" in out_voxel


def test_eval_stores_the_figures_into_the_animated_model(capsys, arm_models):
    code, out, err = run(capsys, "eval", "arm-voxel", "--mesh", ARM_OBJ, "--animation", ARM_PC2,
                         "--models", arm_models, "--points", 1000, "--times", 2, "--quiet")
    assert code == 0, err
    assert "figures written into" in out
    code, out, err = run(capsys, "info", "arm-voxel", "--models", arm_models, "--json")
    accuracy = json.loads(out)["accuracy"]
    assert len(accuracy["times_s"]) == 2 and accuracy["band_1mm"]["points"] == 1000
    # Issue 35: the stored report's file size was the file's before the figures went in.
    assert "file_bytes" not in accuracy
    # The plain `collider info`: the stored figures as `collider eval` prints them, not raw
    # dicts, and the file's true size.
    code, out, err = run(capsys, "info", "arm-voxel", "--models", arm_models)
    assert code == 0, err
    size = (arm_models / "arm-voxel.safetensors").stat().st_size
    assert out.startswith(f"arm-voxel  ({arm_models / 'arm-voxel.safetensors'}, {size:,} bytes)")
    assert "{'" not in out and "file_bytes" not in out, out
    table = out[out.index("  accuracy    as `collider eval` measured it (20"):]
    assert "at 2 random times in [0, 1) s" in table and "    +-1mm " in table
    assert "query (distance+normal+contact) at t = " in table


def test_eval_refuses_a_missing_or_mismatched_animation_in_one_line(capsys, tmp_path, arm_models):
    models = ["--models", arm_models]
    assert_user_error(capsys, ["eval", "arm-voxel", "--mesh", ARM_OBJ, *models],
                      "arm-voxel is animated: give the frames it was made from, --mesh OBJ --animation CACHE "
                      "(arm-voxel was made from arm.obj and arm.pc2, 25 frames at 24 fps)")
    # Every other frame: 13 frames, not the model's 25.
    frames = np.asarray(read_pc2(ARM_PC2))[::2]
    short = tmp_path / "short.pc2"
    with PC2Writer(short, frames.shape[1]) as writer:
        for frame in frames:
            writer.write(frame)
    assert_user_error(capsys, ["eval", "arm-mesh", "--mesh", ARM_OBJ, "--animation", short, *models],
                      f"{short}: 13 frames, but arm-mesh was made from arm.obj and arm.pc2, 25 frames")
    # The right frames at another rate: another duration.
    assert_user_error(capsys, ["eval", "arm-voxel", "--mesh", ARM_OBJ, "--animation", ARM_PC2, "--fps", 30,
                               *models], "arm.pc2 at 30 fps lasts 0.8 s, but arm-voxel's animation lasts 1 s")
    # A cache of another mesh: the OBJ's vertex count says so.
    assert_user_error(capsys, ["eval", "arm-mesh", "--mesh", ROOT / "examples/meshes/spot.obj",
                               "--animation", ARM_PC2, *models], "spot.obj")
    assert_user_error(capsys, ["eval", "bunny", "--mesh", ROOT / "examples/meshes/stanford-bunny.obj",
                               "--animation", ARM_PC2],
                      "bunny is static: --animation, --fps and --times are for animated models")
    assert_user_error(capsys, ["eval", "arm-mesh", "--mesh", ARM_OBJ, "--animation", ARM_PC2, "--times", 0,
                               *models], "--times must be a positive number of random times, got 0")


@pytest.mark.slow
def test_the_voxel_keyframe_error_shrinks_with_resolution_and_keyframes():
    """Real bakes of the shipped arm (one grid per frame at 32^3 is 25 bakes of 33k exact
    distances): mean and p99 distance error at random times against the exact interpolated
    mesh, down with more samples per axis and with more keyframes."""
    from collider_server.making.animation_files import load_animation
    from collider_server.making.bake import bake_animated_collider
    from collider_server.making.evaluation import animated_error_figures
    from collider_server.making.sampling import random_times

    arm = load_animation(ARM_OBJ, ARM_PC2, 24.0, loop=True)
    times = random_times(arm.timeline, 4, seed=3)
    grids: dict = {}
    error = {}
    for resolution in (16, 32):
        for keyframes in (5, 25):
            collider = bake_animated_collider(arm, "voxel", "arm", resolution=resolution, keyframes=keyframes,
                                              show_progress=False, grids=grids.setdefault(resolution, {}))
            band = animated_error_figures(collider, arm, times, 2000, seed=3, sets=("band_1mm",))["band_1mm"]
            error[resolution, keyframes] = (band["distance_mean_mm"], band["distance_p99_mm"])
    assert len(grids[16]) == len(grids[32]) == 25  # 5 keyframes of 25 frames reuse 5 of the 25 grids
    for figure in (0, 1):
        assert error[32, 25][figure] < 0.6 * error[16, 25][figure], error  # resolution
        assert error[32, 25][figure] < 0.5 * error[32, 5][figure], error  # keyframes
        assert error[16, 25][figure] < error[16, 5][figure], error
