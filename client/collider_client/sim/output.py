"""What a run writes: OBJ (the cloth's first frame, quads) + PC2 (every frame), both as
:mod:`collider_contract.point_cache` writes them (metres, world frame; z up in the shipped scenes,
as in Blender), and a PNG preview.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from collider_contract.point_cache import read_pc2


class PC2Frames:
    """The frames of a written PC2 file as a sequence of ``(t, (n, 3) float32 positions)``, read
    from the file on access (memory-mapped): a run streams its frames to disk instead of keeping
    them (a 4096 x 4096 cloth is 200 MB a frame).

    path : the PC2 file (complete, closed); times_s : the simulated time of each frame
    """

    def __init__(self, path: Path, times_s: list[float], points: int):
        self.path, self.times_s, self.points = Path(path), list(times_s), points
        self._frames = read_pc2(self.path)  # memory-mapped; checked against its header
        if self._frames.shape[:2] != (len(self.times_s), points):
            raise ValueError(f"{self.path}: holds {self._frames.shape[0]} frames of {self._frames.shape[1]} "
                             f"points, the run wrote {len(self.times_s)} of {points}")

    def __len__(self) -> int:
        return len(self.times_s)

    def __getitem__(self, i: int) -> tuple[float, np.ndarray]:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} of {len(self)}")
        i %= len(self)
        return self.times_s[i], np.array(self._frames[i])

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def write_preview(path: Path, frames: dict[int, np.ndarray], width: int, height: int,
                  times_s: dict[int, float], title: str,
                  collider_points: list[np.ndarray] | dict[int, list[np.ndarray]] | None = None,
                  up=(0.0, 0.0, 1.0)) -> None:
    """PNG with one 3-D panel per chosen frame: the cloth surface (and collider surface points,
    world frame, when given), drawn with ``up`` (the scene's up, world frame) vertical.
    ``frames`` maps frame index -> (W*H, 3) positions; ``collider_points`` is one list of
    (m, 3) arrays for every panel, or a dict frame index -> list (moving colliders, drawn at
    each frame's pose)."""
    import matplotlib.pyplot as plt

    fig = preview_figure(frames, width, height, times_s, title, collider_points, up)
    fig.savefig(path, dpi=PREVIEW_DPI)
    plt.close(fig)


#: Resolution of the PNG preview: each panel is 4.2 x 4.4 inches, 462 x 484 pixels.
PREVIEW_DPI = 110


def view_axes(up) -> tuple[np.ndarray, list[str]]:
    """The preview's axes for a scene whose up is ``up`` (3,), world frame: (3, 3) float64 rows,
    a right-handed orthonormal basis whose last row is ``up`` (a panel's x, y and vertical
    axes, world frame), and their labels. An up along a world axis keeps the world's axis
    names, cycled so that it is vertical (+y up draws z, x, y; -y up draws x, z, -y); any other
    up gets axes named by their directions."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    names, eye = "xyz", np.eye(3)
    k = int(np.argmax(np.abs(up)))
    if np.allclose(np.abs(up), eye[k], atol=1e-12):
        if up[k] > 0:  # cyclic: (k+1, k+2, k) is right-handed
            rows = np.array([eye[(k + 1) % 3], eye[(k + 2) % 3], eye[k]])
            labels = [names[(k + 1) % 3], names[(k + 2) % 3], names[k]]
        else:  # (k+2, k+1, -k): e_{k+2} x e_{k+1} = -e_k
            rows = np.array([eye[(k + 2) % 3], eye[(k + 1) % 3], -eye[k]])
            labels = [names[(k + 2) % 3], names[(k + 1) % 3], f"-{names[k]}"]
        return rows, [f"{label} (m)" for label in labels]
    first = np.cross(eye[(k + 1) % 3], up)
    first /= np.linalg.norm(first)
    rows = np.array([first, np.cross(up, first), up])

    def along(v):
        return "along (" + ", ".join(f"{c:.2g}" for c in v + 0.0) + ") (m)"

    return rows, [along(r) for r in rows]


def preview_figure(frames: dict[int, np.ndarray], width: int, height: int,
                   times_s: dict[int, float], title: str,
                   collider_points: list[np.ndarray] | dict[int, list[np.ndarray]] | None = None,
                   up=(0.0, 0.0, 1.0)):
    """The matplotlib figure that :func:`write_preview` saves (same arguments, no path)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, labels = view_axes(up)
    count = len(frames)
    fig = plt.figure(figsize=(4.2 * count, 4.4))
    stride = max(1, max(width, height) // 60)  # plot_surface is slow above ~60 x 60 cells
    per_frame = (collider_points if isinstance(collider_points, dict)
                 else {i: collider_points or [] for i in frames})
    # Everything in the panels' axes (world coordinates along rows): up is the vertical.
    frames = {i: np.asarray(v, dtype=np.float64) @ rows.T for i, v in frames.items()}
    per_frame = {i: [np.asarray(p, dtype=np.float64).reshape(-1, 3) @ rows.T for p in per_frame[i]]
                 for i in frames}
    all_points = np.concatenate(list(frames.values()) + [p for i in frames for p in per_frame[i]])
    lo, hi = all_points.min(axis=0), all_points.max(axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6)
    for k, (index, vertices) in enumerate(sorted(frames.items())):
        ax = fig.add_subplot(1, count, k + 1, projection="3d")
        grid = vertices.reshape(height, width, 3)[::stride, ::stride]
        ax.plot_surface(grid[..., 0], grid[..., 1], grid[..., 2], color="#4a90d9",
                        edgecolor="#1f4e79", linewidth=0.2, alpha=0.9, shade=True)
        for pts in per_frame[index]:
            ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=1.0, c="#c0392b", alpha=0.6)
        for axis, set_lim in zip(range(3), (ax.set_xlim, ax.set_ylim, ax.set_zlim)):
            set_lim(centre[axis] - half, centre[axis] + half)
        ax.set_title(f"frame {index}, t = {times_s[index]:.3f} s", fontsize=9)
        ax.set_xlabel(labels[0], fontsize=7)
        ax.set_ylabel(labels[1], fontsize=7)
        ax.set_zlabel(labels[2], fontsize=7)
        ax.tick_params(labelsize=6)
        # The default box fills the panel and pushes the z label past its right edge (cut off
        # in the PNG): a smaller box leaves it room.
        ax.set_box_aspect(None, zoom=0.82)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig
