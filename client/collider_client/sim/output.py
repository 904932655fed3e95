"""What a run writes: OBJ (the cloth's first frame, quads) + PC2 (every frame), a PNG preview.

PC2 is the point cache Blender reads with its Mesh Cache modifier: a 32-byte header
(``b"POINTCACHE2\\0"``, int32 version 1, int32 points, float32 start frame, float32 sample rate,
int32 samples) then float32 x, y, z per point per frame, little-endian. Coordinates are metres,
world frame (z up in the shipped scenes; Blender is z-up too).
"""

from __future__ import annotations

import struct
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
        self._file = open(self.path, "wb")
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


def read_pc2(path: Path) -> np.ndarray:
    """(frames, n, 3) float32 from a PC2 file, memory-mapped. A file that is not a PC2 cache, or
    holds fewer bytes than its header promises (a truncated copy), or more, is a ValueError
    naming the file and what is wrong; finiteness is the reader's to check."""
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
    _magic, version, points, _start, _rate, samples = PC2_HEADER.unpack(head)
    if version != 1 or points < 1 or samples < 0:
        raise ValueError(f"{path}: PC2 header is malformed (version {version}, {points} points, "
                         f"{samples} samples)")
    expected = PC2_HEADER.size + samples * points * 12
    if size != expected:
        held = (size - PC2_HEADER.size) / (points * 12)
        what = "truncated" if size < expected else "longer than its header says"
        raise ValueError(f"{path}: {what}: the header promises {samples} frames of {points} "
                         f"points ({expected:,} bytes), the file has {size:,} bytes "
                         f"({held:.4g} frames)")
    if samples == 0:
        return np.zeros((0, points, 3), dtype=np.float32)
    return np.memmap(path, dtype="<f4", mode="r", offset=PC2_HEADER.size,
                     shape=(samples, points, 3))


class PC2Frames:
    """The frames of a written PC2 file as a sequence of ``(t, (n, 3) float32 positions)``, read
    from the file on access (memory-mapped): a run streams its frames to disk instead of keeping
    them (a 4096 x 4096 cloth is 200 MB a frame).

    path : the PC2 file (complete, closed); times_s : the simulated time of each frame
    """

    def __init__(self, path: Path, times_s: list[float], points: int):
        self.path, self.times_s, self.points = Path(path), list(times_s), points

    def __len__(self) -> int:
        return len(self.times_s)

    def __getitem__(self, i: int) -> tuple[float, np.ndarray]:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} of {len(self)}")
        i %= len(self)
        data = np.memmap(self.path, dtype="<f4", mode="r", offset=32 + i * self.points * 12,
                         shape=(self.points, 3))
        return self.times_s[i], np.array(data)

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def write_preview(path: Path, frames: dict[int, np.ndarray], width: int, height: int,
                  times_s: dict[int, float], title: str,
                  collider_points: list[np.ndarray] | None = None) -> None:
    """PNG with one 3-D panel per chosen frame: the cloth surface (and collider surface points,
    world frame, when given). ``frames`` maps frame index -> (W*H, 3) positions;
    ``collider_points`` is one list of (m, 3) arrays for every panel, or a dict frame index ->
    list (moving colliders, drawn at each frame's pose)."""
    import matplotlib.pyplot as plt

    fig = preview_figure(frames, width, height, times_s, title, collider_points)
    fig.savefig(path, dpi=PREVIEW_DPI)
    plt.close(fig)


#: Resolution of the PNG preview: each panel is 4.2 x 4.4 inches, 462 x 484 pixels.
PREVIEW_DPI = 110


def preview_figure(frames: dict[int, np.ndarray], width: int, height: int,
                   times_s: dict[int, float], title: str,
                   collider_points: list[np.ndarray] | None = None):
    """The matplotlib figure that :func:`write_preview` saves (same arguments, no path)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    count = len(frames)
    fig = plt.figure(figsize=(4.2 * count, 4.4))
    stride = max(1, max(width, height) // 60)  # plot_surface is slow above ~60 x 60 cells
    per_frame = (collider_points if isinstance(collider_points, dict)
                 else {i: collider_points or [] for i in frames})
    all_points = np.concatenate(list(frames.values()) + [p for i in frames for p in per_frame[i]])
    lo, hi = all_points.min(axis=0), all_points.max(axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6)
    for k, (index, vertices) in enumerate(sorted(frames.items())):
        ax = fig.add_subplot(1, count, k + 1, projection="3d")
        grid = vertices.reshape(height, width, 3)[::stride, ::stride]
        ax.plot_surface(grid[..., 0], grid[..., 1], grid[..., 2], color="#4a90d9",
                        edgecolor="#1f4e79", linewidth=0.2, alpha=0.9, shade=True)
        for pts in per_frame[index]:
            ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=0.3, c="#c0392b", alpha=0.4)
        for axis, set_lim in zip(range(3), (ax.set_xlim, ax.set_ylim, ax.set_zlim)):
            set_lim(centre[axis] - half, centre[axis] + half)
        ax.set_title(f"frame {index}, t = {times_s[index]:.3f} s", fontsize=9)
        ax.set_xlabel("x (m)", fontsize=7)
        ax.set_ylabel("y (m)", fontsize=7)
        ax.set_zlabel("z (m)", fontsize=7)
        ax.tick_params(labelsize=6)
        # The default box fills the panel and pushes the z label past its right edge (cut off
        # in the PNG): a smaller box leaves it room.
        ax.set_box_aspect(None, zoom=0.82)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig
