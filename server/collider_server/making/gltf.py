"""glTF 2.0 characters: the skinned mesh of a ``.gltf`` or ``.glb`` file, its skeleton and its
animation clips, read as one :class:`~collider_server.engine.skinning.Skin` (pygltflib).

What is read, by the glTF 2.0 specification:

- **buffers**: embedded ``data:`` URIs, external files beside the ``.gltf``, a ``.glb``'s binary
  chunk; accessors of every component type (normalised integers scaled to [0, 1] or [-1, 1]),
  byte strides, padded matrix columns and sparse accessors;
- **the skinned mesh**: every primitive (triangles, strips, fans) of every mesh node bound to
  the file's one skin, merged; the mesh node's own transform is ignored, as the specification
  says for skinned meshes; ``JOINTS_n`` / ``WEIGHTS_n`` (every set, so more than 4 influences);
  weights that do not sum to 1 are normalised and counted in the notes;
- **the skeleton**: the skin's joints, plus the non-joint nodes between two joints (and animated
  non-joint ancestors) as joints no vertex follows; the transform of every node above them is
  folded into ``Skeleton.root``; TRS or matrix nodes; inverse bind matrices (identity when
  absent);
- **clips**: every animation's translation, rotation and scale channels (LINEAR, STEP,
  CUBICSPLINE); morph-target ``weights`` channels and channels of nodes outside the skeleton are
  ignored and said in the notes;
- **the surface is closed**: vertices split at UV or normal seams are welded by position; their
  joints and weights must agree (the notes say where they do not, keeping the first).

Every problem is a :class:`GltfError` (a ValueError) naming the file and what is wrong: no
skinned mesh, several skins, unsupported required extensions (Draco, meshopt), broken buffers or
accessors, times that do not increase.
"""

from __future__ import annotations

import base64
import binascii
import json
import struct
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..engine.meshes import Mesh
from ..engine.skinning import Channel, Clip, Skeleton, Skin, trs_matrices, world_transforms
from .mesh_files import MAX_FACES, check_has_volume, file_sha256
from .transforms import matrix_trs


class GltfError(ValueError):
    """A glTF file that cannot be read as a skinned character; the message names the file."""


@dataclass(frozen=True)
class SkinFile:
    """A character read from a file.

    skin : the :class:`Skin` in the file's frame and units (glTF: metres, Y up)
    notes : what the reader changed or ignored, one sentence each (normalised weights, welded
        seams, ignored morph targets ...)
    name : the file's stem; sha256 : the file's digest
    """

    skin: Skin
    notes: tuple[str, ...]
    name: str
    sha256: str


#: numpy dtypes of glTF's component types (little-endian).
COMPONENT_TYPES = {5120: np.dtype("<i1"), 5121: np.dtype("<u1"), 5122: np.dtype("<i2"),
                   5123: np.dtype("<u2"), 5125: np.dtype("<u4"), 5126: np.dtype("<f4")}
#: Numbers per element of each accessor type; matrices as (columns, rows).
TYPE_SHAPES = {"SCALAR": (1, 1), "VEC2": (1, 2), "VEC3": (1, 3), "VEC4": (1, 4),
               "MAT2": (2, 2), "MAT3": (3, 3), "MAT4": (4, 4)}
#: Required extensions that change nothing this reader uses (materials, textures, lights) or
#: that it reads anyway (quantized attributes are normalised or plain integer accessors).
HARMLESS_EXTENSIONS = ("KHR_mesh_quantization", "KHR_materials_", "KHR_texture_",
                       "KHR_lights_punctual", "EXT_texture_webp")
#: Primitive modes: 4 triangles, 5 triangle strip, 6 triangle fan (0-3: points and lines).
TRIANGLE_MODES = (4, 5, 6)


def read_gltf(path: str | Path, max_faces: int = MAX_FACES) -> SkinFile:
    """The skinned character of a glTF 2.0 file (``.gltf`` with embedded or external buffers,
    or ``.glb``) in the file's frame (Y up) and units (metres), its triangles wound outward.
    Raises :class:`GltfError` naming the file and the problem."""
    path = Path(path)
    document, blob = _load(path)
    reader = _Reader(path, document, blob)
    return reader.read(max_faces)


def has_skin(path: str | Path) -> bool:
    """Whether the glTF file ``path`` holds a skin (a character for :func:`read_gltf`) rather
    than only static meshes; GltfError when it cannot be read."""
    document, _ = _load(Path(path))
    return bool(document.skins)


def _load(path: Path):
    import pygltflib

    if path.is_dir():
        raise GltfError(f"{path}: is a directory, not a glTF file")
    if not path.is_file():
        raise GltfError(f"{path}: no such glTF file")
    data = path.read_bytes()
    try:
        if data[:4] == b"glTF":
            if len(data) < 20:
                raise GltfError(f"{path}: a truncated .glb file ({len(data)} bytes)")
            document = pygltflib.GLTF2.load_from_bytes(data)
            if document is None:
                raise GltfError(f"{path}: a .glb file without its JSON chunk")
            blob = document.binary_blob()
        else:
            text = data.decode("utf-8-sig")
            json.loads(text)  # a clear message for broken JSON before the dataclass parser
            document = pygltflib.GLTF2.from_json(text, infer_missing=True)
            blob = None
    except GltfError:
        raise
    except UnicodeDecodeError:
        raise GltfError(f"{path}: neither a .glb (binary glTF) nor UTF-8 JSON text") from None
    except json.JSONDecodeError as exc:
        raise GltfError(f"{path}: not valid glTF JSON ({exc})") from None
    except (struct.error, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise GltfError(f"{path}: cannot parse the glTF file ({type(exc).__name__}: {exc})") from None
    version = str(getattr(document.asset, "version", "") or "")
    if not version.startswith("2."):
        raise GltfError(f"{path}: glTF version {version or '(none)'}; only glTF 2.0 is read")
    return document, blob


def _name(item, kind: str, index: int) -> str:
    return getattr(item, "name", None) or f"{kind} {index}"


class _Reader:
    """One file's reading: buffers resolved once, then accessors, mesh, skeleton and clips."""

    def __init__(self, path: Path, document, blob):
        self.path = path
        self.doc = document
        self.blob = blob
        self.buffers: dict[int, bytes] = {}
        self.notes: list[str] = []

    def fail(self, message: str) -> GltfError:
        return GltfError(f"{self.path}: {message}")

    # -- buffers and accessors ------------------------------------------------------------------

    def buffer(self, index: int) -> bytes:
        if index in self.buffers:
            return self.buffers[index]
        buffers = self.doc.buffers or []
        if not 0 <= index < len(buffers):
            raise self.fail(f"buffer {index} does not exist ({len(buffers)} buffers)")
        buffer = buffers[index]
        uri = buffer.uri
        if uri is None:
            if index != 0 or self.blob is None:
                raise self.fail(f"buffer {index} has no uri and is not a .glb's binary chunk")
            data = bytes(self.blob)
        elif uri.startswith("data:"):
            head, _, payload = uri.partition(",")
            if not head.endswith(";base64"):
                raise self.fail(f"buffer {index}: a data: URI that is not base64")
            try:
                data = base64.b64decode(payload, validate=True)
            except (binascii.Error, ValueError):
                raise self.fail(f"buffer {index}: its data: URI is not valid base64") from None
        else:
            file = self.path.parent / urllib.parse.unquote(uri)
            if not file.is_file():
                raise self.fail(f"buffer {index}: its file {uri!r} is missing (looked for {file})")
            data = file.read_bytes()
        if buffer.byteLength is not None and len(data) < buffer.byteLength:
            raise self.fail(f"buffer {index} has {len(data):,} bytes, its byteLength says "
                            f"{buffer.byteLength:,}: truncated")
        self.buffers[index] = data
        return data

    def view_bytes(self, index: int) -> tuple[bytes, int, int, int | None]:
        """``(buffer bytes, start, length, byteStride)`` of buffer view ``index``."""
        views = self.doc.bufferViews or []
        if not 0 <= index < len(views):
            raise self.fail(f"buffer view {index} does not exist ({len(views)} views)")
        view = views[index]
        data = self.buffer(view.buffer)
        start, length = view.byteOffset or 0, view.byteLength or 0
        if start < 0 or start + length > len(data):
            raise self.fail(f"buffer view {index} (bytes {start}..{start + length}) runs past "
                            f"its buffer {view.buffer} ({len(data):,} bytes)")
        return data, start, length, view.byteStride

    def accessor(self, index, what: str) -> np.ndarray:
        """Accessor ``index`` as (count, n) float64 (normalised integers scaled), or (count, c, r)
        for matrices (column-major as stored); ``what`` names it in errors."""
        accessors = self.doc.accessors or []
        if index is None or not 0 <= index < len(accessors):
            raise self.fail(f"{what}: accessor {index} does not exist ({len(accessors)} accessors)")
        acc = accessors[index]
        dtype = COMPONENT_TYPES.get(acc.componentType)
        if dtype is None or acc.type not in TYPE_SHAPES:
            raise self.fail(f"{what}: accessor {index} has an unknown component type "
                            f"{acc.componentType} or type {acc.type!r}")
        columns, rows = TYPE_SHAPES[acc.type]
        count = int(acc.count or 0)
        if acc.bufferView is None:
            raw = np.zeros((count, columns, rows), dtype=dtype)  # all zeros, unless sparse
        else:
            raw = self._strided(index, acc, dtype, columns, rows, count, what)
        if acc.sparse is not None and acc.sparse.count:
            raw = self._sparse(index, acc, raw, dtype, what)
        values = raw.astype(np.float64)
        if acc.normalized and dtype.kind in "iu":
            top = float(np.iinfo(dtype).max)
            values = np.maximum(values / top, -1.0)
        if not np.all(np.isfinite(values)):
            raise self.fail(f"{what}: accessor {index} holds non-finite numbers")
        return values.reshape(count, columns * rows) if columns == 1 else values

    def _strided(self, index, acc, dtype, columns, rows, count, what) -> np.ndarray:
        data, start, length, stride = self.view_bytes(acc.bufferView)
        size = dtype.itemsize
        column_bytes = -(-rows * size // 4) * 4 if columns > 1 else rows * size  # columns pad to 4
        element = columns * column_bytes
        stride = stride or element
        offset = start + (acc.byteOffset or 0)
        end = offset + (count - 1) * stride + element if count else offset
        if end > start + length:
            raise self.fail(f"{what}: accessor {index} ({count} x {acc.type}) runs past its "
                            f"buffer view {acc.bufferView} ({length:,} bytes)")
        if offset % size:
            raise self.fail(f"{what}: accessor {index} starts at byte {offset}, not aligned to "
                            f"its {size}-byte components")
        array = np.ndarray((count, columns, rows), dtype=dtype, buffer=data, offset=offset,
                           strides=(stride, column_bytes, size))
        return array.copy()

    def _sparse(self, index, acc, raw, dtype, what) -> np.ndarray:
        sparse = acc.sparse
        count = int(sparse.count)
        idx_type = COMPONENT_TYPES.get(sparse.indices.componentType)
        if idx_type is None or idx_type.kind != "u":
            raise self.fail(f"{what}: accessor {index}'s sparse indices have component type "
                            f"{sparse.indices.componentType}")
        positions = self._packed(sparse.indices.bufferView, sparse.indices.byteOffset, idx_type,
                                 (count,), what).astype(np.int64)
        values = self._packed(sparse.values.bufferView, sparse.values.byteOffset, dtype,
                              (count,) + raw.shape[1:], what)
        if count and (positions.min() < 0 or positions.max() >= len(raw)):
            raise self.fail(f"{what}: accessor {index}'s sparse indices exceed its count {len(raw)}")
        out = raw.copy()
        out[positions] = values
        return out

    def _packed(self, view, byte_offset, dtype, shape, what) -> np.ndarray:
        data, start, length, _ = self.view_bytes(view)
        offset = start + (byte_offset or 0)
        nbytes = int(np.prod(shape)) * dtype.itemsize
        if offset + nbytes > start + length:
            raise self.fail(f"{what}: sparse data runs past buffer view {view}")
        return np.frombuffer(data, dtype=dtype, count=int(np.prod(shape)), offset=offset).reshape(shape)

    # -- the character --------------------------------------------------------------------------

    def read(self, max_faces: int) -> SkinFile:
        self.check_extensions()
        skin_index, mesh_nodes = self.skinned_nodes()
        gskin = self.doc.skins[skin_index]
        nodes, parents, root = self.skeleton_nodes(gskin)
        skeleton = self.skeleton(gskin, skin_index, nodes, parents, root)
        slot = {node: j for j, node in enumerate(nodes)}
        joint_slot = np.array([slot[n] for n in gskin.joints], dtype=np.int64)
        vertices, faces, joints, weights = self.mesh(mesh_nodes, joint_slot, max_faces)
        vertices, faces, joints, weights = self.weld(vertices, faces, joints, weights)
        mesh = Mesh(vertices, faces, self.path.stem)
        try:
            volume = check_has_volume(mesh, str(self.path))
        except ValueError as exc:
            raise GltfError(str(exc)) from None
        if volume < 0:  # wound inward: orient outward once (as mesh_files.load_mesh)
            faces = faces[:, ::-1].copy()
        clips = self.clips(slot)
        try:
            skin = Skin(vertices, faces, joints, weights, skeleton, tuple(clips))
        except ValueError as exc:
            raise self.fail(str(exc)) from None
        return SkinFile(skin, tuple(self.notes), self.path.stem, file_sha256(self.path))

    def check_extensions(self) -> None:
        for name in self.doc.extensionsRequired or []:
            if not name.startswith(HARMLESS_EXTENSIONS):
                raise self.fail(f"requires the extension {name}, which this reader does not "
                                "support (re-export without it, e.g. without mesh compression)")

    def skinned_nodes(self) -> tuple[int, list[int]]:
        """The file's one skin and the nodes whose skinned meshes use it."""
        nodes = self.doc.nodes or []
        by_skin: dict[int, list[int]] = {}
        for i, node in enumerate(nodes):
            if node.mesh is not None and node.skin is not None:
                by_skin.setdefault(node.skin, []).append(i)
        if not by_skin:
            meshes = len(self.doc.meshes or [])
            raise self.fail(f"no skinned mesh: {meshes} mesh(es), none on a node with a skin "
                            "(export the character with its armature / skin)")
        if len(by_skin) > 1:
            described = "; ".join(
                f"skin {s} ({_name(self.doc.skins[s], 'skin', s)}) on "
                + ", ".join(repr(_name(nodes[n], 'node', n)) for n in ns)
                for s, ns in sorted(by_skin.items()))
            raise self.fail(f"{len(by_skin)} skins ({described}): one skinned character per "
                            "file is supported")
        skin_index, mesh_nodes = next(iter(by_skin.items()))
        if not 0 <= skin_index < len(self.doc.skins or []):
            raise self.fail(f"node {mesh_nodes[0]} uses skin {skin_index}, which does not exist")
        others = [i for i, n in enumerate(nodes) if n.mesh is not None and n.skin is None]
        if others:
            self.notes.append(f"ignored {len(others)} mesh node(s) without a skin: "
                              + ", ".join(repr(_name(nodes[i], "node", i)) for i in others[:5]))
        return skin_index, mesh_nodes

    # -- skeleton -------------------------------------------------------------------------------

    def node_parents(self) -> dict[int, int]:
        parent: dict[int, int] = {}
        for i, node in enumerate(self.doc.nodes or []):
            for child in node.children or []:
                if child in parent:
                    raise self.fail(f"node {child} has two parents ({parent[child]} and {i})")
                parent[child] = i
        return parent

    def ancestors(self, node: int, parent: dict[int, int]) -> list[int]:
        chain, seen = [], {node}
        while node in parent:
            node = parent[node]
            if node in seen:
                raise self.fail(f"the node hierarchy has a cycle through node {node}")
            seen.add(node)
            chain.append(node)
        return chain

    def skeleton_nodes(self, gskin):
        """The skeleton's nodes in order (parents first), their parents' slots (J,) and the
        transform (4, 4) of everything above them."""
        joints = list(gskin.joints or [])
        count = len(self.doc.nodes or [])
        if not joints:
            raise self.fail("the skin has no joints")
        if len(set(joints)) != len(joints) or any(not 0 <= j < count for j in joints):
            raise self.fail(f"the skin's joints {joints} repeat a node or name one that does not exist")
        parent = self.node_parents()
        members = set(joints)
        for j in joints:  # non-joint nodes between two joints move their children: keep them
            chain = self.ancestors(j, parent)
            for depth, a in enumerate(chain):
                if a in set(joints):
                    members.update(chain[:depth])
                    break
        tops = sorted(n for n in members if parent.get(n) not in members)
        chains = [self.ancestors(n, parent) for n in tops]
        common = [a for a in chains[0] if all(a in c for c in chains[1:])]
        lowest = common[0] if common else None
        for c in chains:  # roots under different parents: the nodes up to their common ancestor
            members.update(c[:c.index(lowest)] if lowest is not None else c)
        animated = {ch.target.node for a in self.doc.animations or [] for ch in a.channels or []
                    if ch.target is not None and ch.target.path in ("translation", "rotation", "scale")}
        above = self.ancestors(lowest, parent) if lowest is not None else []
        above = [lowest, *above] if lowest is not None else []
        moving = [i for i, a in enumerate(above) if a in animated]
        if moving:  # an animated ancestor moves the whole skeleton: it becomes a joint
            top = moving[-1]
            members.update(above[: top + 1])
            lowest = above[top + 1] if top + 1 < len(above) else None
        root = np.eye(4)
        if lowest is not None:
            for a in reversed([lowest, *self.ancestors(lowest, parent)]):
                root = root @ self.local_matrix(a)
        order: list[int] = []
        stack = sorted((n for n in members if parent.get(n) not in members), reverse=True)
        while stack:  # depth first: every parent before its children
            n = stack.pop()
            order.append(n)
            stack.extend(sorted((c for c in self.doc.nodes[n].children or [] if c in members),
                                reverse=True))
        slot = {n: i for i, n in enumerate(order)}
        parents = np.array([slot.get(parent.get(n), -1) if parent.get(n) in members else -1
                            for n in order], dtype=np.int64)
        return order, parents, root

    def local_trs(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        node = self.doc.nodes[index]
        if node.matrix is not None and not np.allclose(node.matrix, np.eye(4).reshape(-1)):
            return self.decompose(np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T, index)
        t = np.asarray(node.translation if node.translation is not None else [0, 0, 0], float)
        r = np.asarray(node.rotation if node.rotation is not None else [0, 0, 0, 1], float)
        s = np.asarray(node.scale if node.scale is not None else [1, 1, 1], float)
        if t.shape != (3,) or r.shape != (4,) or s.shape != (3,) or not np.linalg.norm(r) > 0:
            raise self.fail(f"node {index} ({_name(node, 'node', index)}) has a malformed "
                            "translation, rotation or scale")
        return t, r / np.linalg.norm(r), s

    def local_matrix(self, index: int) -> np.ndarray:
        t, r, s = self.local_trs(index)
        return trs_matrices(t[None], r[None], s[None])[0]

    def decompose(self, m: np.ndarray, index: int):
        """A node's matrix (4, 4) as translation, rotation (x, y, z, w) and scale."""
        try:
            return matrix_trs(m)
        except ValueError as exc:
            raise self.fail(f"node {index} ({_name(self.doc.nodes[index], 'node', index)}) has "
                            f"{exc}") from None

    def skeleton(self, gskin, skin_index, nodes, parents, root) -> Skeleton:
        trs = [self.local_trs(n) for n in nodes]
        translation = np.array([t for t, _, _ in trs])
        rotation = np.array([r for _, r, _ in trs])
        scale = np.array([s for _, _, s in trs])
        names, seen = [], set()
        for n in nodes:
            name = _name(self.doc.nodes[n], "node", n)
            names.append(name if name not in seen else f"{name} (node {n})")
            seen.add(names[-1])
        joints = list(gskin.joints)
        if gskin.inverseBindMatrices is None:
            inverse = np.tile(np.eye(4), (len(joints), 1, 1))
        else:
            matrices = self.accessor(gskin.inverseBindMatrices, f"skin {skin_index}'s inverseBindMatrices")
            if matrices.shape != (len(joints), 4, 4):
                raise self.fail(f"skin {skin_index}: {len(matrices)} inverse bind matrices "
                                f"(type MAT4 wanted) for {len(joints)} joints")
            inverse = np.transpose(matrices, (0, 2, 1))  # stored column-major
        # Nodes added between joints bind where they rest; no vertex follows them.
        provisional = Skeleton(names, parents, translation, rotation, scale,
                               np.tile(np.eye(4), (len(nodes), 1, 1)), root)
        rest = world_transforms(provisional, trs_matrices(translation, rotation, scale))
        inverse_bind = np.linalg.inv(rest)
        slot = {n: i for i, n in enumerate(nodes)}
        for k, n in enumerate(joints):
            inverse_bind[slot[n]] = inverse[k]
        added = len(nodes) - len(joints)
        if added:
            self.notes.append(f"{added} node(s) between or above the joints that move them became "
                              "joints no vertex follows")
        return Skeleton(names, parents, translation, rotation, scale, inverse_bind, root)

    # -- the mesh -------------------------------------------------------------------------------

    def mesh(self, mesh_nodes, joint_slot, max_faces):
        """Every triangle primitive of the skinned mesh nodes, concatenated: vertices (V, 3),
        faces (F, 3), joints (V, K) skeleton slots, weights (V, K), before welding."""
        parts, offset = [], 0
        ignored_modes, morphs = 0, 0
        for n in mesh_nodes:
            mesh_index = self.doc.nodes[n].mesh
            if not 0 <= mesh_index < len(self.doc.meshes or []):
                raise self.fail(f"node {n} uses mesh {mesh_index}, which does not exist")
            gmesh = self.doc.meshes[mesh_index]
            for p, prim in enumerate(gmesh.primitives or []):
                where = f"mesh {_name(gmesh, 'mesh', mesh_index)!r} primitive {p}"
                mode = 4 if prim.mode is None else prim.mode
                if mode not in TRIANGLE_MODES:
                    ignored_modes += 1
                    continue
                if prim.extensions and "KHR_draco_mesh_compression" in prim.extensions:
                    raise self.fail(f"{where} is Draco-compressed, which this reader does not support")
                morphs += bool(prim.targets)
                attributes = prim.attributes
                if attributes.POSITION is None:
                    raise self.fail(f"{where} has no POSITION")
                vertices = self.accessor(attributes.POSITION, f"{where} POSITION")
                if vertices.shape[1] != 3:
                    raise self.fail(f"{where}: POSITION must be VEC3")
                joints, weights = self.influences(attributes, len(vertices), where)
                if joints.size and (joints.min() < 0 or joints.max() >= len(joint_slot)):
                    raise self.fail(f"{where}: JOINTS index joint {int(joints.max())}, but the "
                                    f"skin has {len(joint_slot)}")
                if prim.indices is None:
                    indices = np.arange(len(vertices), dtype=np.int64)
                else:
                    indices = self.accessor(prim.indices, f"{where} indices").reshape(-1).astype(np.int64)
                if len(indices) and (indices.min() < 0 or indices.max() >= len(vertices)):
                    raise self.fail(f"{where}: an index beyond its {len(vertices)} vertices")
                faces = primitive_triangles(indices, mode)
                parts.append((vertices, faces + offset, joint_slot[joints], weights))
                offset += len(vertices)
        if ignored_modes:
            self.notes.append(f"ignored {ignored_modes} primitive(s) of points or lines")
        if morphs:
            self.notes.append(f"ignored the morph targets of {morphs} primitive(s) (the rest shape is read)")
        if not parts or not sum(len(f) for _, f, _, _ in parts):
            raise self.fail("the skinned mesh has no triangles")
        width = max(j.shape[1] for _, _, j, _ in parts)

        def pad(a):  # every vertex gets the most influences any primitive has
            return np.pad(a, ((0, 0), (0, width - a.shape[1])))

        vertices = np.concatenate([v for v, _, _, _ in parts])
        faces = np.concatenate([f for _, f, _, _ in parts])
        joints = np.concatenate([pad(j) for _, _, j, _ in parts])
        weights = np.concatenate([pad(w) for _, _, _, w in parts])
        if len(faces) > max_faces:
            raise self.fail(f"{len(faces):,} faces, more than this machine handles ({max_faces:,})")
        return vertices, faces, joints, self.normalised(weights)

    def influences(self, attributes, count: int, where: str):
        """(count, 4 n) joints (skin joint indices) and weights of every JOINTS_i / WEIGHTS_i."""
        joints, weights = [], []
        for i in range(64):
            j_acc = getattr(attributes, f"JOINTS_{i}", None)
            w_acc = getattr(attributes, f"WEIGHTS_{i}", None)
            if j_acc is None and w_acc is None:
                break
            if j_acc is None or w_acc is None:
                raise self.fail(f"{where}: JOINTS_{i} and WEIGHTS_{i} must come together")
            acc = self.doc.accessors[j_acc]
            if acc.normalized or COMPONENT_TYPES.get(acc.componentType, np.dtype("f4")).kind != "u":
                raise self.fail(f"{where}: JOINTS_{i} must be unsigned integers")
            j = self.accessor(j_acc, f"{where} JOINTS_{i}")
            w = self.accessor(w_acc, f"{where} WEIGHTS_{i}")
            if j.shape != (count, 4) or w.shape != (count, 4):
                raise self.fail(f"{where}: JOINTS_{i} / WEIGHTS_{i} must be VEC4 per vertex")
            joints.append(j.astype(np.int64))
            weights.append(w)
        if not joints:
            raise self.fail(f"{where} has no JOINTS_0 / WEIGHTS_0: it is not skinned")
        return np.concatenate(joints, axis=1), np.concatenate(weights, axis=1)

    def normalised(self, weights: np.ndarray) -> np.ndarray:
        if np.any(weights < 0):
            raise self.fail(f"{int((weights < 0).any(axis=1).sum())} vertices have negative weights")
        sums = weights.sum(axis=1)
        if np.any(sums <= 0):
            raise self.fail(f"{int((sums <= 0).sum())} vertices have no weight (all zero): a "
                            "skinned vertex must follow some joint")
        off = np.abs(sums - 1.0)
        if np.any(off > 1e-6):
            self.notes.append(f"normalised the weights of {int((off > 1e-6).sum()):,} vertices "
                              f"that did not sum to 1 (off by up to {off.max():.3g})")
        return weights / sums[:, None]

    def weld(self, vertices, faces, joints, weights):
        """Vertices at one position (split at UV or normal seams) merged into one; their
        influences compared (the first one's kept); faces that collapse dropped."""
        from scipy import sparse

        _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
        # Kept in file order (a file without seams keeps its vertex order).
        order = np.argsort(first)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        first, inverse = first[order], rank[inverse.reshape(-1)]
        unique = vertices[first]
        if len(unique) < len(vertices):
            self.notes.append(f"welded {len(vertices) - len(unique):,} vertices split at seams "
                              f"({len(vertices):,} -> {len(unique):,})")
            # Each vertex's influences as a sparse row over the joints (repeated joints add up).
            rows = np.repeat(np.arange(len(vertices)), joints.shape[1])
            size = int(joints.max()) + 1
            dense = sparse.csr_matrix((weights.reshape(-1), (rows, joints.reshape(-1))),
                                      shape=(len(vertices), size))
            difference = abs(dense - dense[first[inverse]]).max(axis=1).toarray().reshape(-1)
            differ = difference > 1e-6
            if differ.any():
                self.notes.append(f"{int(np.unique(inverse[differ]).size):,} welded positions "
                                  f"have different joints or weights on their copies (by up "
                                  f"to {difference.max():.3g}); the first copy's are kept")
        faces = inverse[faces]
        keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
        if not keep.all():
            self.notes.append(f"dropped {int((~keep).sum()):,} degenerate triangle(s)")
        faces = faces[keep]
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        _, uses = np.unique(edges, axis=0, return_counts=True)
        if np.any(uses == 1):
            self.notes.append(f"the welded surface has {int((uses == 1).sum()):,} boundary "
                              "edges: it is not closed (inside and outside are judged by the "
                              "winding number)")
        return unique, faces, joints[first], weights[first]

    # -- clips ----------------------------------------------------------------------------------

    def clips(self, slot: dict[int, int]) -> list[Clip]:
        clips, names = [], set()
        ignored_weights, ignored_nodes = 0, set()
        for a, animation in enumerate(self.doc.animations or []):
            name = _name(animation, "animation", a)
            if name in names:
                name = f"{name} ({a})"
            names.add(name)
            samplers = animation.samplers or []
            channels = []
            for c, channel in enumerate(animation.channels or []):
                target = channel.target
                where = f"animation {name!r} channel {c}"
                if target is None or target.node is None:
                    continue
                if target.path == "weights":
                    ignored_weights += 1
                    continue
                if target.path not in ("translation", "rotation", "scale"):
                    raise self.fail(f"{where}: unknown path {target.path!r}")
                if target.node not in slot:
                    ignored_nodes.add(target.node)
                    continue
                if not 0 <= channel.sampler < len(samplers):
                    raise self.fail(f"{where}: sampler {channel.sampler} does not exist")
                sampler = samplers[channel.sampler]
                interpolation = sampler.interpolation or "LINEAR"
                times = self.accessor(sampler.input, f"{where} input").reshape(-1)
                values = self.accessor(sampler.output, f"{where} output")
                width = {"translation": 3, "rotation": 4, "scale": 3}[target.path]
                if interpolation == "CUBICSPLINE":
                    if values.shape != (3 * len(times), width):
                        raise self.fail(f"{where}: a CUBICSPLINE output needs 3 x {len(times)} "
                                        f"values of {width}, got {list(values.shape)}")
                    values = values.reshape(len(times), 3, width)
                elif values.shape != (len(times), width):
                    raise self.fail(f"{where}: {list(values.shape)} output values for "
                                    f"{len(times)} times of {target.path}")
                if len(times) and np.any(np.diff(times) <= 0):
                    raise self.fail(f"{where}: its keyframe times do not increase")
                try:
                    channels.append(Channel(slot[target.node], target.path, interpolation, times, values))
                except ValueError as exc:
                    raise self.fail(f"{where}: {exc}") from None
            if not channels:
                self.notes.append(f"skipped animation {name!r}: it moves no joint of the skin")
                continue
            duration = max(float(ch.times[-1]) for ch in channels)
            clips.append(Clip(name, tuple(channels), duration))
        if ignored_weights:
            self.notes.append(f"ignored {ignored_weights} morph-target weights channel(s)")
        if ignored_nodes:
            self.notes.append(f"ignored the channels of {len(ignored_nodes)} node(s) outside "
                              "the skeleton")
        return clips


def primitive_triangles(indices: np.ndarray, mode: int) -> np.ndarray:
    """(F, 3) int64 triangles from a primitive's indices: a list (4), a strip (5: every other
    triangle flipped to keep the winding) or a fan (6)."""
    if mode == 4:
        usable = len(indices) - len(indices) % 3
        return indices[:usable].reshape(-1, 3)
    k = np.arange(max(len(indices) - 2, 0))
    if mode == 5:
        even = k % 2 == 0
        a = indices[k]
        b = np.where(even, indices[k + 1], indices[k + 2])
        c = np.where(even, indices[k + 2], indices[k + 1])
        return np.stack([a, b, c], axis=1)
    return np.stack([np.full(len(k), indices[0]), indices[k + 1], indices[k + 2]], axis=1)
