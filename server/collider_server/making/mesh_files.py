"""Mesh files: reading OBJ, PLY, STL, OFF and GLB with clear errors (trimesh).

Every command that makes or measures a collider reads its mesh here; a file that cannot be used
(missing, unreadable, binary where text is expected, empty, flat, volumeless or too large) is a
:class:`MeshError` naming the file and the reason.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from ..engine.meshes import Mesh

# Beyond this many faces a mesh is refused rather than risk exhausting memory (an exact query
# structure costs roughly 1 KB per face, and training samples scale with the surface).
MAX_FACES = 20_000_000


class MeshError(ValueError):
    """A mesh file that cannot be used: missing, unreadable, empty, volumeless or too large."""


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_mesh(path: str | Path, max_faces: int = MAX_FACES) -> Mesh:
    """Read a triangle mesh (OBJ, PLY, STL, OFF, GLB/GLTF; several parts are concatenated),
    its triangles oriented outward (flipped when the file winds them inward).

    Raises :class:`MeshError` with the file name and the reason when the file is missing,
    unreadable, has no triangles, encloses no volume, or has more than ``max_faces`` faces.
    """
    import trimesh

    path = Path(path)
    if path.is_dir():
        raise MeshError(f"{path}: is a directory, not a mesh file")
    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file")
    check_text_format(path)
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except ImportError:
        # trimesh guesses the encoding of text that is not UTF-8 with an optional package; a
        # binary blob named .obj ends up here, so say what is wrong with the file instead.
        raise MeshError(f"{path}: cannot read mesh (not UTF-8 text, so not a valid "
                        f"{path.suffix or 'mesh'} file)") from None
    except Exception as exc:  # noqa: BLE001 -- trimesh raises many types for broken files
        raise MeshError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{path}: file holds no triangle mesh")
    faces = np.asarray(loaded.faces, dtype=np.int64)
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    if len(faces) == 0 or len(vertices) == 0:
        raise MeshError(f"{path}: {empty_reason(path, len(vertices))}")
    if len(faces) > max_faces:
        raise MeshError(
            f"{path}: mesh has {len(faces):,} faces, more than this machine handles "
            f"({max_faces:,}); decimate it first"
        )
    if not np.isfinite(vertices).all():
        raise MeshError(f"{path}: mesh has NaN or Inf vertex coordinates")
    mesh = Mesh(vertices, faces, path.stem, file_sha256(path))
    if check_has_volume(mesh, str(path)) < 0:
        # Triangles wound inward (clockwise seen from outside) make the winding number -1
        # inside, which the sign test reads as outside everywhere, and turn face and vertex
        # normals inward: orient them outward once, here.
        mesh = Mesh(vertices, faces[:, ::-1].copy(), mesh.name, mesh.sha256)
    return mesh


#: Formats that are text only: a file of these that is not UTF-8 text is not that format.
TEXT_SUFFIXES = (".obj", ".off")


def check_text_format(path: Path, probe_bytes: int = 1 << 20) -> None:
    """Raise :class:`MeshError` when a text-only format's file (OBJ, OFF) holds NUL bytes, i.e.
    is binary: trimesh would otherwise guess an encoding (with charset-normalizer installed, any
    blob decodes) and report an empty mesh instead of an unreadable file. Text in another
    encoding than UTF-8 (a Latin-1 comment) has no NUL byte and is left to trimesh."""
    if path.suffix.lower() not in TEXT_SUFFIXES:
        return
    with open(path, "rb") as fh:
        head = fh.read(probe_bytes)
    if b"\x00" in head:
        raise MeshError(f"{path}: cannot read mesh (binary data, so not a valid {path.suffix} "
                        "file; it is a text format)")


def empty_reason(path: Path, vertices: int) -> str:
    """Why a file that read as no triangles has none: a text file that is not of its format at
    all (no OBJ ``v`` / ``f`` line, no OFF header) says so and quotes its start; else the mesh is
    empty (vertices without faces, or nothing)."""
    suffix = path.suffix.lower()
    if suffix in TEXT_SUFFIXES:
        with open(path, "rb") as fh:
            head = fh.read(1 << 20).decode("utf-8", errors="replace")
        lines = [line.strip() for line in head.splitlines() if line.strip() and not line.lstrip().startswith("#")]
        if suffix == ".obj":
            shaped = any(line.split(maxsplit=1)[0] in ("v", "f") for line in lines)
        else:
            shaped = bool(lines) and lines[0].upper().endswith("OFF")
        if lines and not shaped:
            start = lines[0][:40]
            what = "no vertex (v) or face (f) line" if suffix == ".obj" else "no OFF header"
            return f"not an {suffix[1:].upper()} file: {what} (it starts with {start!r})"
    if vertices:
        return f"mesh is empty: {vertices} vertices but no triangles"
    return "mesh is empty (no triangles)"


def check_has_volume(mesh: Mesh, where: str) -> float:
    """Raise :class:`MeshError` when the mesh is flat or encloses (almost) nothing; else return
    its signed volume (mesh units cubed; negative when its triangles are wound inward)."""
    extent = np.ptp(mesh.vertices, axis=0)
    if np.sort(extent)[0] <= 1e-9 * max(extent.max(), 1e-30):
        raise MeshError(f"{where}: mesh is flat (extent {extent.tolist()}); it encloses no volume")
    # About the box centre: for a closed mesh the volume is the same from any origin, for an open
    # one (holes) it is not, and a far-away origin could even flip its sign.
    tri = mesh.vertices[mesh.faces] - mesh.bounds.mean(axis=0)
    signed_volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    if abs(signed_volume) < 1e-6 * float(np.prod(extent)):
        raise MeshError(
            f"{where}: mesh encloses no volume (signed volume {signed_volume:.3g}); "
            "a signed distance needs a closed or nearly closed surface"
        )
    return float(signed_volume)


