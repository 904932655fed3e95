"""Writing a :class:`~collider_server.engine.skinning.Skin` as a glTF 2.0 binary file (``.glb``,
pygltflib): what :func:`collider_server.making.gltf.read_gltf` and other tools (Blender, three.js)
read back.

Every number is stored as float32 (positions, weights, inverse bind matrices, keyframes), joints
as unsigned bytes (or shorts beyond 255 joints). The skeleton's joints become nodes with their
rest TRS; a ``root`` other than the identity becomes a parent node holding it; the mesh is one
node bound to the skin, cut into primitives by ``parts`` if asked (each primitive has its own
copy of the vertices its faces use, as a file split at material or UV seams does).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..engine.skinning import Skin

ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
FLOAT, UNSIGNED_BYTE, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5121, 5123, 5125


class _Blob:
    """The binary chunk and its buffer views / accessors, built together."""

    def __init__(self, gltf):
        self.gltf = gltf
        self.data = bytearray()

    def add(self, array: np.ndarray, component: int, kind: str, target: int | None = None,
            bounds: bool = False) -> int:
        import pygltflib

        array = np.ascontiguousarray(array)
        while len(self.data) % 4:  # every view starts 4-byte aligned
            self.data.append(0)
        self.gltf.bufferViews.append(pygltflib.BufferView(
            buffer=0, byteOffset=len(self.data), byteLength=array.nbytes, target=target))
        self.data.extend(array.tobytes())
        accessor = pygltflib.Accessor(bufferView=len(self.gltf.bufferViews) - 1,
                                      componentType=component, count=len(array), type=kind)
        if bounds:  # required for POSITION and animation inputs
            flat = array.reshape(len(array), -1)
            accessor.min = flat.min(axis=0).astype(float).tolist()
            accessor.max = flat.max(axis=0).astype(float).tolist()
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1


def write_gltf(skin: Skin, path: str | Path, parts: list[np.ndarray] | None = None,
               name: str = "character") -> Path:
    """Write ``skin`` (its vertices in metres, Y up as glTF expects) to ``path`` (``.glb``).

    parts : optional list of (F_i,) int64 face indices, together every face once: one primitive
        each (their shared vertices duplicated, so the reader must weld them); default one part
    """
    import pygltflib

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    skeleton = skin.skeleton
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(generator="neural-collider", version="2.0"))
    blob = _Blob(gltf)
    j = skeleton.joint_count
    children = [[] for _ in range(j)]
    for c, p in enumerate(skeleton.parents):
        if p >= 0:
            children[int(p)].append(c)
    for k in range(j):
        gltf.nodes.append(pygltflib.Node(
            name=skeleton.names[k], children=children[k] or None,
            translation=skeleton.rest_translation[k].tolist(),
            rotation=skeleton.rest_rotation[k].tolist(), scale=skeleton.rest_scale[k].tolist()))
    roots = [k for k in range(j) if skeleton.parents[k] < 0]
    if not np.allclose(skeleton.root, np.eye(4)):
        gltf.nodes.append(pygltflib.Node(name="root", children=roots,
                                         matrix=skeleton.root.T.reshape(-1).tolist()))
        roots = [len(gltf.nodes) - 1]

    joint_type = UNSIGNED_BYTE if j <= 256 else UNSIGNED_SHORT
    joint_dtype = np.uint8 if j <= 256 else np.uint16
    primitives = []
    for faces in parts if parts is not None else [np.arange(len(skin.faces))]:
        used, local = np.unique(skin.faces[faces], return_inverse=True)
        indices = local.reshape(-1).astype(np.uint32)
        attributes = pygltflib.Attributes(
            POSITION=blob.add(skin.vertices[used].astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER, True))
        for s in range(0, skin.joints.shape[1], 4):  # JOINTS_n / WEIGHTS_n, 4 influences each
            joints = np.zeros((len(used), 4), dtype=joint_dtype)
            weights = np.zeros((len(used), 4), dtype=np.float32)
            width = min(4, skin.joints.shape[1] - s)
            joints[:, :width] = skin.joints[used, s:s + width]
            weights[:, :width] = skin.weights[used, s:s + width]
            setattr(attributes, f"JOINTS_{s // 4}", blob.add(joints, joint_type, "VEC4", ARRAY_BUFFER))
            setattr(attributes, f"WEIGHTS_{s // 4}", blob.add(weights, FLOAT, "VEC4", ARRAY_BUFFER))
        primitives.append(pygltflib.Primitive(
            attributes=attributes, indices=blob.add(indices, UNSIGNED_INT, "SCALAR", ELEMENT_ARRAY_BUFFER)))
    gltf.meshes.append(pygltflib.Mesh(name=name, primitives=primitives))
    gltf.nodes.append(pygltflib.Node(name=name, mesh=0, skin=0))
    inverse_bind = np.transpose(skeleton.inverse_bind, (0, 2, 1)).astype(np.float32)  # column-major
    gltf.skins.append(pygltflib.Skin(name="skeleton", joints=list(range(j)),
                                     inverseBindMatrices=blob.add(inverse_bind, FLOAT, "MAT4")))

    for clip in skin.clips:
        samplers, channels = [], []
        for channel in clip.channels:
            times = blob.add(channel.times.astype(np.float32), FLOAT, "SCALAR", bounds=True)
            values = channel.values.astype(np.float32).reshape(-1, channel.values.shape[-1])
            kind = "VEC4" if channel.path == "rotation" else "VEC3"
            samplers.append(pygltflib.AnimationSampler(
                input=times, output=blob.add(values, FLOAT, kind), interpolation=channel.interpolation))
            channels.append(pygltflib.AnimationChannel(
                sampler=len(samplers) - 1,
                target=pygltflib.AnimationChannelTarget(node=channel.joint, path=channel.path)))
        gltf.animations.append(pygltflib.Animation(name=clip.name, samplers=samplers, channels=channels))

    gltf.scenes.append(pygltflib.Scene(nodes=roots + [len(gltf.nodes) - 1]))
    gltf.scene = 0
    gltf.buffers.append(pygltflib.Buffer(byteLength=len(blob.data)))
    gltf.set_binary_blob(bytes(blob.data))
    gltf.save_binary(str(path))
    return path
