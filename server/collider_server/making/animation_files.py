"""Animated mesh files: an OBJ (the topology, vertices in file order) with a PC2 vertex cache
(the format ``collider simulate`` writes and Blender's Mesh Cache modifier and Houdini read), or
a numbered sequence of OBJ files with the same faces, or a USD stage with time-sampled points
(:mod:`collider_server.making.usd`).

A vertex cache indexes the OBJ's ``v`` lines in file order, so the OBJ is read here as written
(no merged or dropped vertices, which a general mesh reader may do). Every problem is an
:class:`AnimationError` naming the file and what is wrong: a cache of another vertex count, a
non-finite position, a single frame, a bad frame rate, a truncated cache, frames whose faces
differ.
"""

from __future__ import annotations

import glob
import hashlib
import math
import re
from pathlib import Path

import numpy as np

from collider_contract import Timeline
from collider_contract.animation import MAX_FRAME_RATE_HZ, is_frame_rate
from collider_contract.point_cache import read_pc2, read_pc2_header

from ..engine.animated_meshes import AnimatedMesh, max_surface_speed
from ..engine.meshes import Mesh
from .mesh_files import MAX_FACES, check_has_volume, file_sha256
from .usd import USD_SUFFIXES


class AnimationError(ValueError):
    """An animation that cannot be used; the message names the file and the problem."""


def check_frame_rate(frame_rate_hz) -> float:
    """``frame_rate_hz`` as a float: frames per second in ``(0, MAX_FRAME_RATE_HZ]`` (the
    timeline's rule, :func:`collider_contract.animation.is_frame_rate`), else AnimationError."""
    if not is_frame_rate(frame_rate_hz):
        raise AnimationError(f"--fps must be a number of frames per second in (0, "
                             f"{MAX_FRAME_RATE_HZ:g}], got {frame_rate_hz!r}")
    return float(frame_rate_hz)


def read_obj(path: str | Path, max_faces: int = MAX_FACES) -> Mesh:
    """The vertices (every ``v`` line, in file order) and triangles (polygons split into fans;
    1-based and negative indices) of an OBJ file, float64. Texture and normal indices are
    ignored."""
    vertices, faces = _parse_obj(Path(path), want_faces=True)
    if len(faces) > max_faces:
        raise AnimationError(f"{path}: {len(faces):,} faces, more than this machine handles "
                             f"({max_faces:,}); decimate it first")
    return Mesh(vertices, faces, Path(path).stem, file_sha256(Path(path)))


def _parse_obj(path: Path, want_faces: bool) -> tuple[np.ndarray, np.ndarray | None]:
    if path.is_dir():
        raise AnimationError(f"{path}: is a directory, not an OBJ file")
    if not path.is_file():
        raise AnimationError(f"{path}: no such OBJ file")
    data = path.read_bytes()
    if b"\0" in data[: 1 << 20]:
        raise AnimationError(f"{path}: binary data, not an OBJ file (a text format)")
    text = data.decode("utf-8", errors="replace")
    coords, polygons = [], []
    for number, line in enumerate(text.splitlines(), 1):
        if line.startswith("v "):
            parts = line.split()
            try:
                coords.append((float(parts[1]), float(parts[2]), float(parts[3])))
            except (IndexError, ValueError):
                raise AnimationError(f"{path}: line {number}: a vertex needs three numbers, got "
                                     f"{line.strip()[:60]!r}") from None
        elif want_faces and line.startswith("f "):
            polygons.append((number, line.split()[1:]))
    vertices = np.array(coords, dtype=np.float64).reshape(-1, 3)
    if not len(vertices):
        raise AnimationError(f"{path}: no vertices (no 'v' lines)")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise AnimationError(f"{path}: vertex {row} is not finite ({vertices[row].tolist()})")
    if not want_faces:
        return vertices, None
    triangles = []
    count = len(vertices)
    for number, corners in polygons:
        try:
            index = [int(c.split("/")[0]) for c in corners]
        except ValueError:
            raise AnimationError(f"{path}: line {number}: face indices must be integers") from None
        index = [i - 1 if i > 0 else count + i for i in index]
        if len(index) < 3 or any(not 0 <= i < count for i in index):
            raise AnimationError(f"{path}: line {number}: a face needs 3 or more indices of "
                                 f"existing vertices (1..{count}), got {corners}")
        triangles.extend((index[0], index[j], index[j + 1]) for j in range(1, len(index) - 1))
    if not triangles:
        raise AnimationError(f"{path}: no faces (no 'f' lines)")
    return vertices, np.array(triangles, dtype=np.int64)


def read_cache(cache: str | Path, mesh: Mesh) -> tuple[np.ndarray, str, tuple[float, float] | None]:
    """The frames of ``cache`` for ``mesh`` (read by :func:`read_obj`): (F, v, 3) float64, the
    cache's sha256 (a sequence: over its files' digests in order) and a PC2 file's header
    (start frame, sample rate), None for a sequence.

    cache : a ``.pc2`` file, or a glob pattern of OBJ files (``'frames/*.obj'``; the files are
        ordered by the last number in their names) whose faces are ``mesh``'s"""
    text = str(cache)
    if any(c in text for c in "*?["):
        return _read_sequence(text, mesh)
    path = Path(text)
    if path.suffix.lower() != ".pc2":
        raise AnimationError(f"{path}: an animation is a .pc2 vertex cache or a pattern of OBJ "
                             "files such as 'frames/*.obj'")
    try:
        header = read_pc2_header(path)
        frames = read_pc2(path)
    except ValueError as exc:
        raise AnimationError(str(exc)) from None
    if frames.shape[1] != mesh.vertices.shape[0]:
        raise AnimationError(f"{path}: {frames.shape[1]:,} points per frame, but {mesh.name}.obj "
                             f"has {len(mesh.vertices):,} vertices: it is not a cache of this mesh")
    frames = np.asarray(frames, dtype=np.float64)
    _check_frames(frames, path)
    return frames, file_sha256(path), (header.start_frame, header.sample_rate)


def _read_sequence(pattern: str, mesh: Mesh) -> tuple[np.ndarray, str]:
    paths = sorted((Path(p) for p in glob.glob(pattern)), key=_frame_order)
    if not paths:
        raise AnimationError(f"{pattern}: no files match")
    frames = np.empty((len(paths), len(mesh.vertices), 3))
    digest = hashlib.sha256()
    for i, path in enumerate(paths):
        vertices, faces = _parse_obj(path, want_faces=True)
        if len(vertices) != len(mesh.vertices):
            raise AnimationError(f"{path}: {len(vertices):,} vertices, but {mesh.name}.obj has "
                                 f"{len(mesh.vertices):,}: every frame needs the same vertices")
        if not np.array_equal(faces, mesh.faces):
            raise AnimationError(f"{path}: its faces differ from {mesh.name}.obj's (an animation "
                                 "keeps its topology: the same faces in every frame)")
        frames[i] = vertices
        digest.update(file_sha256(path).encode())
    _check_frames(frames, pattern)
    return frames, digest.hexdigest(), None


def _frame_order(path: Path):
    numbers = re.findall(r"\d+", path.stem)
    return (int(numbers[-1]) if numbers else -1, path.name)


def _check_frames(frames: np.ndarray, where) -> None:
    if len(frames) < 2:
        raise AnimationError(f"{where}: {len(frames)} frame(s); an animation needs at least 2")
    bad = ~np.isfinite(frames).all(axis=2)
    if bad.any():
        frame, vertex = (int(i) for i in np.argwhere(bad)[0])
        raise AnimationError(f"{where}: frame {frame}, vertex {vertex} is not finite "
                             f"({frames[frame, vertex].tolist()})")


def load_animation(mesh_path: str | Path, cache: str | Path, frame_rate_hz: float,
                   loop: bool = False) -> AnimatedMesh:
    """An OBJ and its vertex cache as an :class:`AnimatedMesh` in the file's units and frame,
    its triangles oriented outward (flipped when the first frame winds them inward). The frame
    rate (frames per second) and ``loop`` (wrap beyond the ends; else clamp) are the caller's:
    a PC2 file's own sample rate counts scene frames, not seconds."""
    rate = check_frame_rate(frame_rate_hz)
    mesh_path = Path(mesh_path)
    if mesh_path.suffix.lower() in USD_SUFFIXES:
        return _load_usd_animation(mesh_path, Path(str(cache)), rate, loop)
    if mesh_path.suffix.lower() != ".obj":
        raise AnimationError(f"{mesh_path}: an animated mesh is an OBJ file (its vertex order is "
                             "the cache's)")
    mesh = read_obj(mesh_path)
    frames, cache_sha, cache_timing = read_cache(cache, mesh)
    faces = mesh.faces
    try:
        volume = check_has_volume(Mesh(frames[0], faces), f"{cache} (frame 0)")
    except ValueError as exc:
        raise AnimationError(str(exc)) from None
    if volume < 0:  # wound inward: orient outward once (see mesh_files.load_mesh)
        faces = faces[:, ::-1].copy()
    timeline = Timeline(len(frames), rate, bool(loop), max_surface_speed(frames, rate))
    return AnimatedMesh(frames, faces, timeline, mesh.name, mesh.sha256, Path(str(cache)).name,
                        cache_sha, cache_timing)


#: What this project writes in a PC2 header and expects: the first sample at scene frame 0, one
#: sample per scene frame.
PC2_DEFAULT_TIMING = (0.0, 1.0)


def cache_timing_warning(animation: AnimatedMesh) -> str | None:
    """A line saying that a PC2 cache's header asks for another start frame or sample rate than
    :data:`PC2_DEFAULT_TIMING` and that they are not applied (sample k plays at k / fps
    seconds), or None where there is nothing to say."""
    if animation.cache_timing is None or tuple(animation.cache_timing) == PC2_DEFAULT_TIMING:
        return None
    start, rate = animation.cache_timing
    return (f"{animation.cache}: its header says start frame {start:g}, sample rate {rate:g}; neither is "
            f"applied: sample k plays at k / fps seconds from 0 (give --fps the rate of the samples, "
            f"docs/animation.md)")


def _load_usd_animation(stage: Path, cache: Path, rate: float, loop: bool) -> AnimatedMesh:
    """A USD stage's time-sampled points (:func:`~collider_server.making.usd.read_usd_animation`):
    the stage holds its frames (``cache`` must be the stage itself) and its own rate (``rate``
    must be it)."""
    from .usd import read_usd_animation

    if cache.resolve() != stage.resolve():
        raise AnimationError(f"{cache}: a USD stage holds its own frames: give the stage itself "
                             f"as the animation (--animation {stage})")
    animation = read_usd_animation(stage, loop)
    stage_rate = animation.timeline.frame_rate_hz
    if not math.isclose(stage_rate, rate, rel_tol=1e-9):
        raise AnimationError(f"{stage}: its frames play at {stage_rate:g} per second "
                             f"(timeCodesPerSecond and the samples' spacing), not {rate:g}: give "
                             f"--fps {stage_rate:g}")
    return animation


def write_animation(animation: AnimatedMesh, folder: str | Path, name: str) -> tuple[Path, Path]:
    """``folder/NAME.obj`` (the first frame, every vertex in order) and ``folder/NAME.pc2``
    (every frame, float32): what :func:`load_animation` reads back, Blender's Mesh Cache too.
    The frame rate is not in the files (a PC2 counts scene frames): give it when baking."""
    from collider_contract.point_cache import PC2Writer, write_obj

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    obj, pc2 = folder / f"{name}.obj", folder / f"{name}.pc2"
    write_obj(obj, animation.frames[0], animation.faces, name,
              comment=f"neural-collider animation {name}: the first frame of {name}.pc2 "
                      f"({animation.timeline.frames} frames at {animation.timeline.frame_rate_hz:g} "
                      "fps), metres")
    with PC2Writer(pc2, animation.vertex_count) as writer:
        for frame in animation.frames:
            writer.write(frame)
    return obj, pc2
