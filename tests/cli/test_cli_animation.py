"""``collider animate``, ``collider bake --animation``, ``collider info`` and ``collider query
--time`` as a user would run them: success, and for every malformed animation one clear error
line naming the file, exit 2, no traceback. Metres, seconds."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from collider_contract.point_cache import PC2Writer

from .test_cli_models import assert_user_error, run


@pytest.fixture(scope="module")
def arm_files(tmp_path_factory):
    """``collider animate arm``'s OBJ + PC2 (25 frames of 2,530 vertices)."""
    from collider_cli import main

    folder = tmp_path_factory.mktemp("anim")
    assert main(["animate", "arm", "--output", str(folder), "--quiet"]) == 0
    return folder / "arm.obj", folder / "arm.pc2"


def test_animate_frames_keeps_the_motion_and_its_duration(capsys, tmp_path, arm_files):
    """``--frames N``: N frames over the same second (the rate follows), each frame the same
    motion at its time: frame 2 of 49 is frame 1 of the default 25."""
    from collider_server.making.animation_files import load_animation

    code, out, _ = run(capsys, "animate", "arm", "--frames", 49, "--output", tmp_path, "--quiet")
    assert code == 0 and "49 frames at 48 fps (1 s, looping)" in out
    fine = load_animation(tmp_path / "arm.obj", tmp_path / "arm.pc2", 48.0, True)
    default = load_animation(*arm_files, 24.0, True)
    np.testing.assert_allclose(fine.frames[2], default.frames[1], atol=1e-6)
    assert_user_error(capsys, ["animate", "arm", "--frames", 1, "--output", tmp_path],
                      "--frames must be an integer >= 2, got 1")


def test_animate_spot_bend_bends_the_shipped_cow_once_and_bakes_it_clamped(capsys, tmp_path):
    """The spot cow (examples/meshes/spot.obj, Y up in the file) written Z up, its feet at z = 0:
    still at the start, its tail swung 30 degrees about the vertical axis and the whole cow moved
    5 cm along x at the end (the head, which does not bend, only moved); clamped, and baked so."""
    from collider_server.making.animation_files import load_animation, read_obj

    code, out, err = run(capsys, "animate", "spot-bend", "--output", tmp_path, "--bake", "mesh", "--models",
                         tmp_path / "models", "--quiet")
    assert code == 0, err
    assert "25 frames at 12 fps (2 s, clamped)" in out and "--fps 12 --clamp --kind mesh" in out
    spot = load_animation(tmp_path / "spot-bend.obj", tmp_path / "spot-bend.pc2", 12.0, False)
    assert not spot.timeline.loop
    first, last = spot.frames[0], spot.frames[-1]
    rest = read_obj("examples/meshes/spot.obj").vertices
    # Z up: the file's y is z, its z is -y; the feet at z = 0.
    np.testing.assert_allclose(first[:, 0], rest[:, 0], atol=1e-6)
    np.testing.assert_allclose(first[:, 1], -rest[:, 2], atol=1e-6)
    np.testing.assert_allclose(first[:, 2] - first[:, 2].min(), rest[:, 1] - rest[:, 1].min(), atol=1e-6)
    assert abs(first[:, 2].min()) < 1e-6
    head, tail = rest[:, 2] < -0.1, rest[:, 2] > 0.5  # the file's z: head at -z, tail at +z
    moved = last - first
    np.testing.assert_allclose(moved[head], np.tile([0.05, 0.0, 0.0], (head.sum(), 1)), atol=1e-6)
    assert np.abs(moved[:, 2]).max() < 1e-6  # turned about the vertical axis: no vertex rises or falls
    # The tail turned 30 degrees about the vertical axis (through the pivot 0.2 m along the body).
    before, after = first[tail][:, :2] - [0.0, -0.2], last[tail][:, :2] - [0.05, -0.2]
    turn = np.degrees(np.arctan2(np.cross(before, after), (before * after).sum(axis=1)))
    np.testing.assert_allclose(np.abs(turn), 30.0, atol=1e-3)
    code, out, err = run(capsys, "info", "spot-bend", "--models", tmp_path / "models")
    assert code == 0 and "clamps" in out, (out, err)


def test_animate_spot_bend_finds_the_shipped_cow_from_another_folder(capsys, tmp_path, monkeypatch):
    """Run from a folder that holds no ``examples/`` (an editable install used elsewhere), the
    generated animation of a shipped mesh reads the checkout's: the same frames as from the root."""
    from collider_server.making.animation_files import load_animation

    assert run(capsys, "animate", "spot-bend", "--output", tmp_path / "root", "--quiet")[0] == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    code, _, err = run(capsys, "animate", "spot-bend", "--output", "out", "--quiet")
    assert code == 0, err
    here = load_animation(elsewhere / "out/spot-bend.obj", elsewhere / "out/spot-bend.pc2", 12.0, False)
    there = load_animation(tmp_path / "root/spot-bend.obj", tmp_path / "root/spot-bend.pc2", 12.0, False)
    np.testing.assert_array_equal(here.frames, there.frames)


def write_pc2(path, frames):
    with PC2Writer(path, frames.shape[1]) as writer:
        for frame in frames:
            writer.write(frame)
    return path


def test_animate_bake_info_and_query(capsys, tmp_path, arm_files):
    obj, pc2 = arm_files
    code, out, err = run(capsys, "bake", obj, "--animation", pc2, "--fps", 24, "--loop", "--kind",
                         "mesh", "--name", "arm", "--models", tmp_path, "--quiet")
    assert code == 0, err
    assert "animated: 25 frames at 24 fps, 1 s, loops" in out
    assert "mesh: 5,056 faces, watertight, 1 piece, no self-intersections (every frame checked)" in out
    code, out, err = run(capsys, "info", "arm", "--models", tmp_path)
    assert code == 0, err
    assert "mesh: 5,056 faces, watertight, 1 piece, no self-intersections (every frame checked)" in out  # recorded
    assert "animation   25 frames at 24 fps, 1 s, loops (the time wraps around)" in out
    assert "cache       arm.pc2 sha256" in out
    code, out, err = run(capsys, "query", "arm", 0.45, 0.0, 0.05, "--time", 0.3, "--fields",
                         "distance,velocity", "--models", tmp_path)
    assert code == 0, err
    velocity = [float(v) for v in out.split("velocity=[")[1].split("]")[0].split(",")]
    assert velocity[2] > 0.1  # the forearm rises at 0.3 s
    assert_user_error(capsys, ["query", "arm", 0, 0, 0, "--models", tmp_path],
                      "model 'arm' is animated: give the time (seconds) to ask it at")
    # A static model of the first frame, the placement options as everywhere: --scale doubles it.
    code, out, err = run(capsys, "bake", obj, "--animation", pc2, "--fps", 24, "--kind", "voxel",
                         "--resolution", 16, "--keyframes", 3, "--scale", 2, "--name", "big",
                         "--models", tmp_path, "--quiet")
    assert code == 0, err
    code, out, err = run(capsys, "info", "big", "--models", tmp_path, "--json")
    import json

    info = json.loads(out)
    assert info["animation"]["frames"] == 3 and info["animation"]["loop"] is False
    assert info["settings"]["keyframes"] == 3 and info["source"]["transform"][0][0] == 2.0
    assert info["domain_max"][0] > 1.1  # 0.54 m doubled, padded
    assert info["animation"]["max_surface_speed"] == pytest.approx(2 * 0.9425, rel=1e-3)


def test_an_obj_sequence_is_an_animation(capsys, tmp_path, arm_files):
    from collider_contract.point_cache import read_pc2, write_obj
    from collider_server.making.animation_files import read_obj

    obj, pc2 = arm_files
    mesh = read_obj(obj)
    frames = np.asarray(read_pc2(pc2))
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in (0, 4, 8, 12):  # file names out of lexical order: 'f10' sorts before 'f2'
        write_obj(folder / f"f{k // 4 * 5}.obj", frames[k].astype(np.float64), mesh.faces, "arm")
    code, out, err = run(capsys, "bake", obj, "--animation", str(folder / "f*.obj"), "--fps", 6,
                         "--kind", "mesh", "--name", "seq", "--models", tmp_path, "--quiet")
    assert code == 0, err
    assert "4 frames at 6 fps, 0.5 s, clamps" in out
    from collider_server.engine.repository import ModelRepository

    model = ModelRepository(tmp_path).load("seq")
    np.testing.assert_allclose(model.animation.frames[3], frames[12], atol=1e-6)  # f15 last


def malformed(tmp_path, arm_files, case):
    """(argv after the command, the message) for one malformed animation."""
    obj, pc2 = arm_files
    from collider_contract.point_cache import read_pc2

    frames = np.array(read_pc2(pc2))
    base = ["bake", obj, "--kind", "mesh", "--name", "x", "--models", tmp_path, "--quiet"]
    if case == "vertex count":
        other = write_pc2(tmp_path / "short.pc2", frames[:, :100])
        return base + ["--animation", other, "--fps", 24], \
            "short.pc2: 100 points per frame, but arm.obj has 2,530 vertices"
    if case == "non-finite":
        frames[3, 17, 1] = np.nan
        return base + ["--animation", write_pc2(tmp_path / "nan.pc2", frames), "--fps", 24], \
            "nan.pc2: frame 3, vertex 17 is not finite"
    if case == "single frame":
        return base + ["--animation", write_pc2(tmp_path / "one.pc2", frames[:1]), "--fps", 24], \
            "one.pc2: 1 frame(s); an animation needs at least 2"
    if case == "zero fps":
        return base + ["--animation", pc2, "--fps", 0], "--fps must be a number of frames per second in (0, 1e+06], got 0.0"
    if case == "negative fps":
        return base + ["--animation", pc2, "--fps", -24], "--fps must be a number of frames per second in (0, 1e+06]"
    if case == "huge fps":  # issue 35: accepted, then every velocity overflowed float32
        return base + ["--animation", pc2, "--fps", 1e300], \
            "--fps must be a number of frames per second in (0, 1e+06], got 1e+300"
    if case == "no fps":
        return base + ["--animation", pc2], "--animation needs --fps"
    if case == "truncated":
        data = pc2.read_bytes()
        cut = tmp_path / "cut.pc2"
        cut.write_bytes(data[: len(data) - 1000])
        return base + ["--animation", cut, "--fps", 24], \
            "cut.pc2: truncated: the header promises 25 frames of 2530 points (759,032 bytes), the file has 758,032 bytes"
    if case == "not a pc2":
        fake = tmp_path / "fake.pc2"
        fake.write_bytes(b"hello world, not a cache at all, no" * 3)
        return base + ["--animation", fake, "--fps", 24], "fake.pc2: not a PC2 file"
    if case == "header lies":
        lies = tmp_path / "lies.pc2"
        data = bytearray(pc2.read_bytes())
        data[28:32] = struct.pack("<i", 0)  # an unfinished writer's sample count
        lies.write_bytes(bytes(data))
        return base + ["--animation", lies, "--fps", 24], "lies.pc2: longer than its header says"
    if case == "missing cache":
        return base + ["--animation", tmp_path / "nope.pc2", "--fps", 24], "nope.pc2: no such PC2 file"
    if case == "no frames match":
        return base + ["--animation", str(tmp_path / "none" / "*.obj"), "--fps", 24], "*.obj: no files match"
    if case == "faces differ":
        from collider_contract.point_cache import write_obj

        folder = tmp_path / "seq"
        folder.mkdir()
        from collider_server.making.animation_files import read_obj

        faces = read_obj(obj).faces
        write_obj(folder / "f1.obj", frames[0], faces, "a")
        write_obj(folder / "f2.obj", frames[1], faces[::-1], "a")
        return base + ["--animation", str(folder / "f*.obj"), "--fps", 24], \
            "f2.obj: its faces differ from arm.obj's"
    if case == "not an obj":
        stl = tmp_path / "arm.stl"
        stl.write_text("solid x\nendsolid x\n")
        return ["bake", stl, "--animation", pc2, "--fps", 24, "--kind", "mesh", "--name", "x",
                "--models", tmp_path], "arm.stl: an animated mesh is an OBJ file"
    if case == "kdtree":
        return ["bake", obj, "--animation", pc2, "--fps", 24, "--kind", "kdtree", "--name", "x",
                "--models", tmp_path], "--kind kdtree cannot be animated"
    if case == "fps without animation":
        return ["bake", obj, "--fps", 24, "--name", "x", "--models", tmp_path], \
            "--fps, --keyframes and --loop/--clamp need --animation"
    if case == "one keyframe":
        return ["bake", obj, "--animation", pc2, "--fps", 24, "--kind", "voxel", "--keyframes", 1,
                "--resolution", 16, "--name", "x", "--models", tmp_path, "--quiet"], \
            "--keyframes must be an integer >= 2, got 1"
    raise AssertionError(case)


CASES = ["vertex count", "non-finite", "single frame", "zero fps", "negative fps", "huge fps", "no fps",
         "truncated", "not a pc2", "header lies", "missing cache", "no frames match",
         "faces differ", "not an obj", "kdtree", "fps without animation", "one keyframe"]


@pytest.mark.parametrize("case", CASES)
def test_a_malformed_animation_is_one_line_and_exit_2(capsys, tmp_path, arm_files, case):
    argv, message = malformed(tmp_path, arm_files, case)
    code, _out, err = run(capsys, *argv)
    assert code == 2 and "Traceback" not in err, err
    assert err.strip().splitlines() == [err.strip()], err  # one line
    assert err.startswith("collider bake: error: ") and message in err, err
    assert not (tmp_path / "x.safetensors").exists()  # nothing half-written


def test_a_nan_frame_rate_is_refused_by_the_option_itself(capsys, tmp_path, arm_files):
    obj, pc2 = arm_files
    code, _out, err = run(capsys, "bake", obj, "--animation", pc2, "--fps", "nan", "--name", "x",
                         "--models", tmp_path)
    assert code == 2 and "Traceback" not in err
    assert "argument --fps: 'nan' is not a finite number" in err.strip().splitlines()[-1]


def test_a_pc2_header_timing_is_recorded_shown_and_warned_about_when_not_the_default(capsys, tmp_path, arm_files):
    """A PC2 header's start frame and sample rate are not applied (sample k plays at k / fps s):
    the bake says so in a warning when they are not 0 and 1, the model records them, and
    `collider info` shows them; the default header gives no warning."""
    import json

    obj, pc2 = arm_files
    data = bytearray(pc2.read_bytes())
    data[20:28] = struct.pack("<ff", 10.0, 2.0)  # start frame 10, a sample every 2 scene frames
    shifted = tmp_path / "shifted.pc2"
    shifted.write_bytes(bytes(data))
    code, out, err = run(capsys, "bake", obj, "--animation", shifted, "--fps", 24, "--kind", "mesh",
                         "--name", "shifted", "--models", tmp_path, "--quiet")
    assert code == 0, err
    assert ("warning: shifted.pc2: its header says start frame 10, sample rate 2; neither is applied: "
            "sample k plays at k / fps seconds from 0") in err
    assert "animated: 25 frames at 24 fps, 1 s" in out  # the frames' timing is --fps alone
    code, out, err = run(capsys, "info", "shifted", "--models", tmp_path)
    assert code == 0, err
    assert "pc2 header  start frame 10, sample rate 2 (recorded, not applied" in out
    code, out, err = run(capsys, "info", "shifted", "--models", tmp_path, "--json")
    source = json.loads(out)["source"]
    assert (source["cache_start_frame"], source["cache_sample_rate"]) == (10.0, 2.0)
    code, out, err = run(capsys, "bake", obj, "--animation", pc2, "--fps", 24, "--kind", "mesh",
                         "--name", "plain", "--models", tmp_path, "--quiet")
    assert code == 0 and "warning" not in err, err
    code, out, err = run(capsys, "info", "plain", "--models", tmp_path)
    assert "pc2 header  start frame 0, sample rate 1 (recorded, not applied" in out
