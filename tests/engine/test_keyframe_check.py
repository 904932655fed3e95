"""Whether a voxel collider's keyframes hold an animation's thin parts
(``collider_server.making.keyframe_check``): a 4 mm plate moving along its normal. The check
names the keyframe count that holds it, and real bakes agree: halfway between keyframes too far
apart the blended grids lose the plate, with the count it names they keep it. Metres, seconds."""

from __future__ import annotations

import re

import numpy as np
import pytest

from collider_contract import Timeline
from collider_contract.point_cache import PC2Writer, write_obj
from collider_server.engine.animated_meshes import AnimatedMesh, max_surface_speed
from collider_server.making.keyframe_check import check_keyframes, local_thickness

FPS = 24.0


def plate(step_m: float, frames: int) -> AnimatedMesh:
    """A 50 x 50 x 4 mm plate (z its normal) rising ``step_m`` a frame, clamped."""
    import trimesh

    box = trimesh.creation.box(extents=(0.05, 0.05, 0.004))
    offsets = np.array([[0.0, 0.0, step_m * k] for k in range(frames)])
    moving = np.asarray(box.vertices)[None] + offsets[:, None, :]
    return AnimatedMesh(moving, np.asarray(box.faces), Timeline(frames, FPS, False, max_surface_speed(moving, FPS)))


def test_the_thickness_of_a_plate_is_measured_across_it():
    animation = plate(0.0, 2)
    mesh = animation.frame(0)
    big = np.flatnonzero(np.abs(mesh.vertices[mesh.faces].mean(axis=1)[:, 2]) > 1.9e-3)  # top, bottom
    np.testing.assert_allclose(local_thickness(mesh, big), 0.004, rtol=0.02)


def test_a_plate_moving_5_cm_a_frame_needs_keyframes_between_frames():
    check = check_keyframes(plate(0.05, 3), 3)
    assert not check.holds and check.failing == 2
    assert check.worst.moved == pytest.approx(0.05) and check.worst.thickness == pytest.approx(0.004, rel=0.02)
    # 100 mm over 2 frames at most 1.99 mm (half the plate) a segment: 51 segments, 52 grids
    assert check.needed == 52
    assert check.warning().endswith("--keyframes 52 holds it (more grids than the 3 frames: grids at "
                                    "interpolated times), as does the exact kind (--kind mesh)")
    assert check_keyframes(plate(0.05, 3), 52).holds and not check_keyframes(plate(0.05, 3), 51).holds
    fast = check_keyframes(plate(5.0, 3), 3)  # 5 m a frame: more grids than the check suggests
    assert fast.needed is None and fast.warning().endswith(
        "not even 1024 keyframes hold it: the exact kind (--kind mesh) does")


@pytest.fixture(scope="module")
def slow_plate():
    """The plate rising 1 mm a frame over 25 frames (24 mm)."""
    return plate(0.001, 25)


def test_the_check_names_the_keyframes_that_hold_a_thin_part(slow_plate):
    check = check_keyframes(slow_plate, 5)  # 6 mm between keyframes: more than the plate
    assert check.failing == 4 and check.needed == 14  # 1.85 mm between keyframes: under half of it
    assert re.search(r"between frames \d+ and \d+ a part 3\.98 mm thin moves 6 mm along its "
                     "normal, and halfway the blended grids keep 0 mm of it", check.warning()), check.warning()
    assert check.warning().endswith("--keyframes 14 holds it")
    assert check_keyframes(slow_plate, 14).holds and check_keyframes(slow_plate, 14).warning() is None
    assert check_keyframes(plate(0.0, 5), 2).holds  # a still plate: nothing moves


def test_real_bakes_lose_the_plate_where_the_check_says_and_keep_it_with_its_count(slow_plate):
    """Halfway between keyframes 0 and 6 of 5 keyframes (frame 3, t = 0.125 s), the plate's
    middle (z = 3 mm) reads outside the blended grids: the plate is gone. With the 14 keyframes
    the check names, it reads inside (about -2 mm, the grid's trilinear share aside)."""
    from collider_server.making.bake import bake_animated_collider

    middle = np.array([[0.0, 0.0, 0.003], [0.01, -0.01, 0.003]])
    read = {}
    for keyframes in (5, 14):
        collider = bake_animated_collider(slow_plate, "voxel", "plate", resolution=48, keyframes=keyframes,
                                          show_progress=False)
        read[keyframes] = collider.query_local(middle, False, time=3 / FPS)[0]
    assert (read[5] > 0).all(), read[5]
    assert (read[14] < -1e-3).all(), read[14]


def test_collider_bake_warns_with_the_keyframes_that_hold_it(tmp_path, slow_plate, capsys):
    from collider_cli import main

    obj, pc2 = tmp_path / "plate.obj", tmp_path / "plate.pc2"
    write_obj(obj, slow_plate.frames[0], slow_plate.faces, "plate")
    with PC2Writer(pc2, slow_plate.vertex_count) as writer:
        for frame in slow_plate.frames:
            writer.write(frame)
    assert main(["bake", str(obj), "--animation", str(pc2), "--fps", "24", "--kind", "voxel", "--resolution", "16",
                 "--keyframes", "5", "--name", "plate", "--models", str(tmp_path), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "warning: 4 of 4 keyframe segments move a part more than half its thickness" in err
    assert "--keyframes 14 holds it" in err
    assert main(["bake", str(obj), "--animation", str(pc2), "--fps", "24", "--kind", "voxel", "--resolution", "16",
                 "--keyframes", "14", "--name", "plate", "--models", str(tmp_path), "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err
