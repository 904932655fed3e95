"""The glTF reader and the engine's skinning against an independent evaluation written here from
the glTF 2.0 specification (its own accessor decoding, node matrices from TRS, the scene graph,
keyframe sampling, joint matrix = global(joint) @ inverseBind, skinned position = sum w *
jointMatrix * v), on the public RiggedSimple and RiggedFigure samples and on the generated walker
with LINEAR, STEP and CUBICSPLINE clips: equal to 1e-6 m at times between and on keyframes; and
the exact ``skinned`` kind that ``collider bake RiggedFigure.gltf --kind skinned --z-up`` makes,
posed in its clip, against the same evaluation."""

import base64
import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from collider_server.engine.skinning import Channel, Clip, Skin, pose_at, skin_vertices
from collider_server.making.gltf import read_gltf
from collider_server.making.gltf_writer import write_gltf
from collider_server.making.walker import make_walker

SAMPLE = Path(__file__).parents[1] / "data" / "gltf" / "RiggedSimple.gltf"
FIGURE = Path(__file__).parents[1] / "data" / "gltf" / "RiggedFigure.gltf"  # a humanoid, 19 joints
TOLERANCE_M = 1e-6

# -- the specification, written out -------------------------------------------------------------

DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def load(path: Path):
    """(JSON document, buffer 0's bytes) of a .gltf with a data: URI or a .glb."""
    raw = path.read_bytes()
    if raw[:4] == b"glTF":
        json_length = struct.unpack("<I", raw[12:16])[0]
        doc = json.loads(raw[20:20 + json_length])
        bin_start = 20 + json_length
        return doc, raw[bin_start + 8:bin_start + 8 + struct.unpack("<I", raw[bin_start:bin_start + 4])[0]]
    doc = json.loads(raw)
    return doc, base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])


def accessor(doc, data, index) -> np.ndarray:
    """(count, n) float64: elements at byteOffset + i * stride; normalised ints scaled."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(DTYPES[acc["componentType"]])
    n = SIZES[acc["type"]]
    stride = view.get("byteStride") or n * dtype.itemsize
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    rows = [np.frombuffer(data, dtype, n, start + i * stride) for i in range(acc["count"])]
    out = np.array(rows, dtype=np.float64)
    if acc.get("normalized"):
        out = np.maximum(out / np.iinfo(dtype).max, -1.0)
    return out


def quaternion_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def trs(t, r, s) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quaternion_matrix(np.asarray(r) / np.linalg.norm(r)) @ np.diag(s)
    m[:3, 3] = t
    return m


def sample(times, values, interpolation, path, t):
    """A sampler's value at ``t`` (held beyond the ends), by the specification's formulas."""
    k_count = len(times)
    if interpolation == "CUBICSPLINE":
        values = values.reshape(k_count, 3, -1)  # in-tangent, value, out-tangent
    point = (lambda k: values[k, 1]) if interpolation == "CUBICSPLINE" else (lambda k: values[k])
    if t <= times[0]:
        return point(0)
    if t >= times[-1]:
        return point(k_count - 1)
    k = int(np.searchsorted(times, t, side="right")) - 1
    delta = times[k + 1] - times[k]
    u = (t - times[k]) / delta
    if interpolation == "STEP":
        return values[k]
    if interpolation == "CUBICSPLINE":
        p0, m0 = values[k, 1], delta * values[k, 2]
        p1, m1 = values[k + 1, 1], delta * values[k + 1, 0]
        p = ((2 * u**3 - 3 * u**2 + 1) * p0 + (u**3 - 2 * u**2 + u) * m0
             + (-2 * u**3 + 3 * u**2) * p1 + (u**3 - u**2) * m1)
        return p / np.linalg.norm(p) if path == "rotation" else p
    a, b = values[k], values[k + 1]
    if path != "rotation":
        return (1 - u) * a + u * b
    dot = float(a @ b)
    if dot < 0:
        b, dot = -b, -dot
    if dot > 0.9995:
        q = (1 - u) * a + u * b
        return q / np.linalg.norm(q)
    angle = math.acos(dot)
    return (math.sin((1 - u) * angle) * a + math.sin(u * angle) * b) / math.sin(angle)


def skinned_primitives(doc, data, animation: int, t: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per primitive of the skinned mesh: (rest positions, skinned positions) at ``t``."""
    nodes = doc["nodes"]
    local = {}
    for i, node in enumerate(nodes):
        if "matrix" in node:
            local[i] = np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T
        else:
            local[i] = [node.get("translation", [0, 0, 0]), node.get("rotation", [0, 0, 0, 1]),
                        node.get("scale", [1, 1, 1])]
    anim = doc["animations"][animation]
    for channel in anim["channels"]:
        s = anim["samplers"][channel["sampler"]]
        target = channel["target"]
        value = sample(accessor(doc, data, s["input"])[:, 0], accessor(doc, data, s["output"]),
                       s.get("interpolation", "LINEAR"), target["path"], t)
        local[target["node"]][["translation", "rotation", "scale"].index(target["path"])] = value
    matrices = {i: m if isinstance(m, np.ndarray) else trs(*m) for i, m in local.items()}
    world = {}

    def visit(i, above):
        world[i] = above @ matrices[i]
        for child in nodes[i].get("children", []):
            visit(child, world[i])

    for root in doc["scenes"][doc.get("scene", 0)]["nodes"]:
        visit(root, np.eye(4))
    out = []
    for node in nodes:
        if "skin" not in node:
            continue
        skin = doc["skins"][node["skin"]]
        inverse = accessor(doc, data, skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
        joint_matrix = np.array([world[j] @ inverse[k] for k, j in enumerate(skin["joints"])])
        for prim in doc["meshes"][node["mesh"]]["primitives"]:
            attributes = prim["attributes"]
            v = accessor(doc, data, attributes["POSITION"])
            joints = accessor(doc, data, attributes["JOINTS_0"]).astype(int)
            weights = accessor(doc, data, attributes["WEIGHTS_0"])
            homogeneous = np.concatenate([v, np.ones((len(v), 1))], axis=1)
            moved = sum(weights[:, k, None] * np.einsum("vij,vj->vi", joint_matrix[joints[:, k]], homogeneous)
                        for k in range(4))
            out.append((v, moved[:, :3]))
    return out


# -- the comparisons ----------------------------------------------------------------------------

def compare(path: Path, times_s) -> float:
    """The largest distance (m) between the reader + engine skinning and the specification's
    evaluation, over every clip at ``times_s`` (fractions of the clip) and every file vertex."""
    doc, data = load(path)
    skin = read_gltf(path).skin
    where = {tuple(v): i for i, v in enumerate(skin.vertices)}
    worst = 0.0
    for a, clip in enumerate(skin.clips):
        for fraction in times_s:
            t = fraction * clip.duration_s
            ours = skin_vertices(skin, pose_at(skin, clip.name, t, mode="clamp")[0])
            for rest, theirs in skinned_primitives(doc, data, a, t):
                index = np.array([where[tuple(v)] for v in rest])  # the welded vertex of each
                worst = max(worst, float(np.abs(ours[index] - theirs).max()))
    return worst


FRACTIONS = (0.0, 0.013, 0.25, 0.3711, 0.5, 0.77, 0.999, 1.0)


@pytest.mark.parametrize("sample", [SAMPLE, FIGURE], ids=lambda p: p.stem)
def test_the_sample_buffer_matches_every_accessor_bound(sample):
    """A shipped sample's embedded buffer is the original's: every accessor's min and max."""
    doc, data = load(sample)
    assert len(data) == doc["buffers"][0]["byteLength"]
    for i, acc in enumerate(doc["accessors"]):
        values = accessor(doc, data, i)
        np.testing.assert_allclose(values.min(axis=0), acc["min"], rtol=1e-6, atol=1e-12, err_msg=str(i))
        np.testing.assert_allclose(values.max(axis=0), acc["max"], rtol=1e-6, atol=1e-12, err_msg=str(i))


@pytest.mark.parametrize(("sample", "later_s", "move"), [(SAMPLE, 1.5, 0.5), (FIGURE, 1.0, 0.2)],
                         ids=["RiggedSimple", "RiggedFigure"])
def test_the_public_sample_skins_as_the_specification_says(sample, later_s, move):
    skin = read_gltf(sample).skin
    moved = skin_vertices(skin, pose_at(skin, None, later_s)[0])
    assert np.abs(moved - skin_vertices(skin, pose_at(skin, None, 0.0)[0])).max() > move  # it moves
    assert compare(sample, FRACTIONS) < TOLERANCE_M


def test_the_figure_bakes_as_the_exact_skinned_kind():
    """What ``collider bake RiggedFigure.gltf --kind skinned --z-up`` makes (the function it
    calls): the file's 19 joints with their parents (the skeleton lists parents first, not in the
    file's order), its one clip and duration, and at clip times the model's posed skin is the
    specification's, placed; its distance there is 0."""
    from collider_server.making.characters import skinned_from_file
    from collider_server.making.placement import MeshPlacement

    doc, data = load(FIGURE)
    collider, read, transform = skinned_from_file(FIGURE, "figure", MeshPlacement(z_up=True), loop=False)
    skin = collider.skin
    joints = doc["skins"][0]["joints"]
    parent = {c: n for n, node in enumerate(doc["nodes"]) for c in node.get("children", [])}
    file_parents = {doc["nodes"][j]["name"]: doc["nodes"][parent[j]]["name"] if parent[j] in joints else None
                    for j in joints}
    names = skin.skeleton.names
    assert skin.skeleton.joint_count == len(joints) == 19
    assert {n: names[p] if p >= 0 else None for n, p in zip(names, skin.skeleton.parents, strict=True)} == file_parents
    durations = [max(doc["accessors"][s["input"]]["max"][0] for s in a["samplers"]) for a in doc["animations"]]
    assert [(c.name, c.duration_s) for c in skin.clips] == [("animation 0", pytest.approx(durations[0]))]
    where = {tuple(v): i for i, v in enumerate(read.skin.vertices)}  # the file's frame, welded
    for t in (0.31, 0.9):
        ours = skin_vertices(skin, pose_at(skin, "animation 0", t, mode="clamp")[0])
        (rest, theirs), = skinned_primitives(doc, data, 0, t)
        placed = theirs @ transform[:3, :3].T + transform[:3, 3]
        index = np.array([where[tuple(v)] for v in rest])
        np.testing.assert_allclose(ours[index], placed, rtol=0, atol=TOLERANCE_M)
        answer = collider.query(placed, ("distance",), clip="animation 0", time=t)
        assert np.abs(answer.distance).max() < TOLERANCE_M


@pytest.fixture(scope="module")
def walker():
    return make_walker()


def with_interpolation(skin: Skin, interpolation: str) -> Skin:
    """``skin``'s clips resampled as STEP or CUBICSPLINE (tangents: the values' central
    differences per second), so those samplers go through a file too."""
    clips = []
    for clip in skin.clips:
        channels = []
        for ch in clip.channels:
            values = ch.values
            if interpolation == "CUBICSPLINE":
                tangent = np.gradient(values, ch.times, axis=0)
                values = np.stack([tangent, values, tangent], axis=1)
            channels.append(Channel(ch.joint, ch.path, interpolation, ch.times, values))
        clips.append(Clip(clip.name, tuple(channels), clip.duration_s))
    return Skin(skin.vertices, skin.faces, skin.joints, skin.weights, skin.skeleton, tuple(clips))


@pytest.mark.parametrize("interpolation", ["LINEAR", "STEP", "CUBICSPLINE"])
def test_the_walker_skins_as_the_specification_says(tmp_path, walker, interpolation):
    skin = walker.skin() if interpolation == "LINEAR" else with_interpolation(walker.skin(), interpolation)
    centres = skin.vertices[skin.faces].mean(axis=1)[:, 0]
    path = write_gltf(skin, tmp_path / "walker.glb",  # two primitives: a seam down the middle
                      parts=[np.flatnonzero(centres < 0), np.flatnonzero(centres >= 0)])
    assert compare(path, FRACTIONS) < TOLERANCE_M


def test_the_walker_file_gives_back_the_vertices_it_was_built_from(tmp_path, walker):
    """The generator's own forward kinematics (rotation matrices, no quaternions) at every
    keyframe equal the reader's skin posed by the engine."""
    path = write_gltf(walker.skin(), tmp_path / "walker.glb")
    skin = read_gltf(path).skin
    np.testing.assert_array_equal(skin.vertices, walker.vertices)
    for motion in walker.motions:
        for key in range(0, len(motion.times), 3):
            t = float(np.float32(motion.times[key]))
            ours = skin_vertices(skin, pose_at(skin, motion.name, t, mode="clamp")[0])
            np.testing.assert_allclose(ours, walker.reference_vertices(motion, key), rtol=0, atol=TOLERANCE_M)
