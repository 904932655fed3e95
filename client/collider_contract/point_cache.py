"""The point-cache files animations travel in: an OBJ (the mesh, its vertex order) and a PC2 vertex
cache (every frame), as Blender's Mesh Cache modifier and Houdini read and write them. The
simulator writes its cloth runs in them; `collider bake --animation` reads animated colliders from
them. numpy only.

PC2: a 32-byte header (``b"POINTCACHE2\\0"``, int32 version 1, int32 points, float32 start frame,
float32 sample rate, int32 samples) then float32 x, y, z per point per frame, little-endian. The
file carries no units, frame or frame rate: its writer and reader agree on them (the simulator:
metres, world frame; an animated collider: the units and rate given to `collider bake`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

PC2_MAGIC = b"POINTCACHE2\0"


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, name: str = "cloth",
              comment: str = "neural-collider cloth, metres, world frame") -> None:
    """OBJ with ``vertices`` (n, 3) and 0-based ``faces`` (F, k) written 1-based, in the vertex
    order given (a PC2 cache of the same vertices indexes them in that order)."""
    with open(path, "w") as f:
        f.write(f"# {comment}\no {name}\n")
        np.savetxt(f, vertices, fmt="v %.7g %.7g %.7g")
        np.savetxt(f, faces + 1, fmt="f" + " %d" * faces.shape[1])


class PC2Writer:
    """Appends frames of (n, 3) positions to a PC2 file; the sample count is fixed on close."""

    def __init__(self, path: Path, points: int):
        self.path = Path(path)
        self.points = points
        self.samples = 0
        self._file = open(self.path, "wb")  # noqa: SIM115 -- open across write() calls, closed by close()
        # Start frame 0, sample rate 1.0: one sample per (Blender) frame.
        self._file.write(struct.pack("<12siiffi", PC2_MAGIC, 1, points, 0.0, 1.0, 0))

    def write(self, vertices: np.ndarray) -> None:
        if vertices.shape != (self.points, 3):
            raise ValueError(f"frame must be ({self.points}, 3), got {vertices.shape}")
        self._file.write(np.ascontiguousarray(vertices, dtype="<f4").tobytes())
        self.samples += 1

    def close(self) -> None:
        if self._file.closed:
            return
        self._file.seek(28)
        self._file.write(struct.pack("<i", self.samples))
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


PC2_HEADER = struct.Struct("<12siiffi")


@dataclass(frozen=True)
class PC2Header:
    """What a PC2 file's header says: ``points`` per frame, ``samples`` (frames), and the scene
    frame of the first sample (``start_frame``) and the scene frames between samples
    (``sample_rate``), which this project writes as 0 and 1 (docs/animation.md: what they
    mean here)."""

    points: int
    samples: int
    start_frame: float
    sample_rate: float


def read_pc2_header(path: Path) -> PC2Header:
    """The header of a PC2 file, checked against the file: a file that is not a PC2 cache, or
    holds fewer bytes than its header promises (a truncated copy), or more, is a ValueError
    naming the file and what is wrong (the frames it holds, with their fraction)."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a directory, not a PC2 file")
    if not path.is_file():
        raise ValueError(f"{path}: no such PC2 file")
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(PC2_HEADER.size)
    if len(head) < PC2_HEADER.size or not head.startswith(PC2_MAGIC):
        raise ValueError(f"{path}: not a PC2 file (no POINTCACHE2 header)")
    _magic, version, points, start, rate, samples = PC2_HEADER.unpack(head)
    if version != 1 or points < 1 or samples < 0:
        raise ValueError(f"{path}: PC2 header is malformed (version {version}, {points} points, "
                         f"{samples} samples)")
    expected = PC2_HEADER.size + samples * points * 12
    if size != expected:
        what = "truncated" if size < expected else "longer than its header says"
        raise ValueError(f"{path}: {what}: the header promises {samples} frames of {points} "
                         f"points ({expected:,} bytes), the file has {size:,} bytes "
                         f"({_frames_held(size - PC2_HEADER.size, points)})")
    return PC2Header(points, samples, float(start), float(rate))


def _frames_held(data_bytes: int, points: int) -> str:
    """The frames that ``data_bytes`` of positions hold, with enough digits to tell a part of a
    frame from a whole: "3 frames", "61.997 frames: the file is 100 bytes short of 62",
    "3.5 frames: 12 bytes beyond 3"."""
    frame_bytes = points * 12
    whole, part = divmod(data_bytes, frame_bytes)
    if part == 0:
        return f"{whole} frames"
    held = data_bytes / frame_bytes
    digits = 1
    while round(held, digits) in (whole, whole + 1) and digits < 15:
        digits += 1
    return f"{held:.{digits}f} frames: the file is {frame_bytes - part:,} bytes short of {whole + 1}"


def read_pc2(path: Path) -> np.ndarray:
    """(frames, n, 3) float32 from a PC2 file, memory-mapped (read-only), after
    :func:`read_pc2_header`'s checks; finiteness is the reader's to check."""
    header = read_pc2_header(path)
    if header.samples == 0:
        return np.zeros((0, header.points, 3), dtype=np.float32)
    return np.memmap(path, dtype="<f4", mode="r", offset=PC2_HEADER.size,
                     shape=(header.samples, header.points, 3))
