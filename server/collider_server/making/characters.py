"""Character files: which reader reads a skinned character (glTF 2.0 or USD, by the file's
suffix), and the ``skinned`` collider made from one, placed (``collider bake CHARACTER --kind
skinned``)."""

from __future__ import annotations

from pathlib import Path

from .gltf import GltfError, SkinFile, read_gltf
from .placement import MeshPlacement
from .usd import USD_SUFFIXES

#: Suffixes of the glTF files :func:`read_character` reads (USD: :data:`USD_SUFFIXES`).
GLTF_SUFFIXES = (".gltf", ".glb")


def is_character_file(path: str | Path) -> bool:
    return Path(path).suffix.lower() in GLTF_SUFFIXES + USD_SUFFIXES


def is_skinned_character(path: str | Path) -> bool:
    """Whether ``path`` is a skinned character: a USD stage, or a glTF file with a skin (a glTF
    of static meshes is a mesh file); a ValueError naming the file when a glTF cannot be read."""
    suffix = Path(path).suffix.lower()
    if suffix in USD_SUFFIXES:
        return True
    if suffix in GLTF_SUFFIXES:
        from .gltf import has_skin

        return has_skin(path)
    return False


def read_character(path: str | Path) -> SkinFile:
    """The skinned character of ``path`` in the file's frame and units; a ValueError (one line,
    naming the file) when it has none or cannot be read."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in GLTF_SUFFIXES:
        return read_gltf(path)
    if suffix in USD_SUFFIXES:
        from .usd import read_usd_skin

        return read_usd_skin(path)
    raise GltfError(f"{path}: a skinned character is a glTF 2.0 file (.gltf, .glb) or a USD "
                    "stage (.usd, .usda, .usdc, .usdz)")


def skinned_from_file(path: str | Path, name: str, placement: MeshPlacement, *, loop: bool,
                      padding: float = 0.1):
    """``(collider, SkinFile, transform)``: the ``skinned`` collider named ``name`` of the
    character in ``path`` under ``placement`` (its transform, (4, 4), recorded in the source)."""
    from ..engine.meshes import Mesh
    from .mesh_check import check_mesh
    from .skinned import skinned_collider

    read = read_character(path)
    skin, transform = placement.apply_to_skin(read.skin)
    source = {"mesh": read.name, "sha256": read.sha256, "path": str(Path(path).resolve()),
              "vertices": len(skin.vertices), "faces": len(skin.faces),
              "joints": skin.skeleton.joint_count, "transform": transform.tolist(),
              "notes": list(read.notes),
              "check": check_mesh(Mesh(skin.vertices, skin.faces, read.name)).to_dict()}
    collider = skinned_collider(skin, name, loop=loop, padding=padding, units=placement.units,
                                meters_per_unit=placement.meters_per_unit, source=source)
    return collider, read, transform
