"""The point-cache files animations travel in (collider_contract.point_cache): the OBJ's vertex
order and 1-based faces, the PC2 header Blender reads, and every malformed cache refused with a
message naming the file and what is wrong."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from collider_contract.point_cache import PC2Header, PC2Writer, read_pc2, read_pc2_header, write_obj


def test_write_obj_writes_the_vertices_in_order_and_one_based_faces(tmp_path):
    vertices = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.01, 0.01, 0.5]])
    write_obj(tmp_path / "a.obj", vertices, np.array([[0, 1, 3, 2]]))
    lines = (tmp_path / "a.obj").read_text().splitlines()
    assert lines[0] == "# neural-collider cloth, metres, world frame"
    assert lines[1] == "o cloth"  # the default object name
    assert lines[2:] == ["v 0 0 0", "v 0.01 0 0", "v 0 0.01 0", "v 0.01 0.01 0.5", "f 1 2 4 3"]
    write_obj(tmp_path / "b.obj", vertices[:3], np.array([[0, 1, 2]]), name="arm", comment="c")
    assert (tmp_path / "b.obj").read_text().splitlines()[:2] == ["# c", "o arm"]


def _write(path, frames):
    with PC2Writer(path, frames.shape[1]) as pc2:
        for frame in frames:
            pc2.write(frame)
    return path


def test_pc2_header_and_frames_round_trip(tmp_path):
    """The 32-byte header Blender reads: magic, version 1, points, start frame 0, sample rate 1
    (one sample a frame), samples; then float32 x, y, z per point per frame."""
    path = tmp_path / "a.pc2"
    frames = np.array([np.arange(6, dtype=np.float64).reshape(2, 3) * k / 3 for k in range(3)])
    with PC2Writer(path, 2) as pc2:
        for f in frames:
            pc2.write(f)  # float64 in, float32 on disk
        with pytest.raises(ValueError, match=r"frame must be \(2, 3\), got \(3, 3\)"):
            pc2.write(np.zeros((3, 3)))
        assert pc2.samples == 3
    pc2.close()  # a second close is harmless
    data = path.read_bytes()
    assert len(data) == 32 + 3 * 2 * 3 * 4
    assert struct.unpack("<12siiffi", data[:32]) == (b"POINTCACHE2\0", 1, 2, 0.0, 1.0, 3)
    assert read_pc2_header(path) == PC2Header(points=2, samples=3, start_frame=0.0, sample_rate=1.0)
    read = read_pc2(path)
    assert read.dtype == np.float32 and read.shape == (3, 2, 3)
    np.testing.assert_array_equal(read, frames.astype(np.float32))
    empty = tmp_path / "empty.pc2"
    PC2Writer(empty, 4).close()
    assert read_pc2(empty).shape == (0, 4, 3)


def _header(version=1, points=2, samples=3):
    return struct.pack("<12siiffi", b"POINTCACHE2\0", version, points, 0.0, 1.0, samples)


@pytest.mark.parametrize("case, message", [
    ("missing", "{path}: no such PC2 file"),
    ("directory", "{path}: is a directory, not a PC2 file"),
    ("text", "{path}: not a PC2 file (no POINTCACHE2 header)"),
    ("short header", "{path}: not a PC2 file (no POINTCACHE2 header)"),
    ("version", "{path}: PC2 header is malformed (version 2, 2 points, 3 samples)"),
    ("no points", "{path}: PC2 header is malformed (version 1, 0 points, 3 samples)"),
    ("negative samples", "{path}: PC2 header is malformed (version 1, 2 points, -1 samples)"),
    ("truncated", ("{path}: truncated: the header promises 3 frames of 2 points (104 bytes), the "
                  "file has 92 bytes (2.5 frames: the file is 12 bytes short of 3)")),
    ("longer", ("{path}: longer than its header says: the header promises 3 frames of 2 points "
               "(104 bytes), the file has 116 bytes (3.5 frames: the file is 12 bytes short of 4)")),
    ("whole frames longer", ("{path}: longer than its header says: the header promises 3 frames "
                            "of 2 points (104 bytes), the file has 128 bytes (4 frames)")),
    ("a byte longer", ("{path}: longer than its header says: the header promises 3 frames of 2 "
                      "points (104 bytes), the file has 105 bytes (3.04 frames: the file is 23 "
                      "bytes short of 4)")),
])
def test_a_malformed_cache_is_refused_naming_the_file_and_the_fault(tmp_path, case, message):
    path = tmp_path / "c.pc2"
    body = np.zeros(3 * 2 * 3, dtype="<f4").tobytes()
    if case == "directory":
        path.mkdir()
    elif case == "text":
        path.write_text("hello world, not a cache at all")
    elif case == "short header":
        path.write_bytes(b"POINTCACHE2\0\1\0")
    elif case == "version":
        path.write_bytes(_header(version=2) + body)
    elif case == "no points":
        path.write_bytes(_header(points=0))
    elif case == "negative samples":
        path.write_bytes(_header(samples=-1))
    elif case == "truncated":
        path.write_bytes(_header() + body[:-12])
    elif case == "longer":
        path.write_bytes(_header() + body + bytes(12))
    elif case == "whole frames longer":
        path.write_bytes(_header() + body + bytes(24))
    elif case == "a byte longer":  # 3.04 frames: two digits tell it from 3
        path.write_bytes(_header() + body + bytes(1))
    with pytest.raises(ValueError) as info:
        read_pc2(path)
    assert str(info.value) == message.format(path=path)


def test_a_single_frame_of_a_single_point_reads_back_read_only(tmp_path):
    path = _write(tmp_path / "one.pc2", np.array([[[0.5, -1.0, 2.0]]]))
    read = read_pc2(path)
    assert read.shape == (1, 1, 3) and read.dtype == np.float32
    np.testing.assert_array_equal(read, [[[0.5, -1.0, 2.0]]])
    assert not read.flags.writeable  # a reader never changes the cache
    empty = tmp_path / "empty.pc2"
    PC2Writer(empty, 1).close()
    assert read_pc2(empty).dtype == np.float32


def test_a_cache_a_few_bytes_short_shows_the_part_of_a_frame_it_holds(tmp_path):
    """100 bytes short of 62 frames of 2,530 points is not "62 frames" (nor 61): the message shows
    the fraction with the digits that tell it from a whole frame, and the bytes missing."""
    path = tmp_path / "short.pc2"
    frame_bytes = 2530 * 12
    path.write_bytes(_header(points=2530, samples=62) + bytes(62 * frame_bytes - 100))
    with pytest.raises(ValueError) as info:
        read_pc2(path)
    assert str(info.value).endswith(f"the file has {32 + 62 * frame_bytes - 100:,} bytes "
                                    "(61.997 frames: the file is 100 bytes short of 62)")
