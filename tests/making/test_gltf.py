"""The glTF 2.0 reader (making/gltf.py) on a public sample (RiggedSimple, tests/data/gltf) and
on variants of it written here: external buffers, normalised and sparse accessors, welding,
weight normalisation, placement, and one-line errors for broken files."""

import base64
import copy
import json
from pathlib import Path

import numpy as np
import pytest

from collider_server.engine.skinning import pose_at, skin_vertices
from collider_server.making.gltf import GltfError, read_gltf
from collider_server.making.placement import MeshPlacement

SAMPLE = Path(__file__).parents[1] / "data" / "gltf" / "RiggedSimple.gltf"


def sample_document() -> dict:
    return json.loads(SAMPLE.read_text())


def buffer_bytes(doc) -> bytearray:
    return bytearray(base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1]))


def set_buffer(doc, data: bytes) -> None:
    doc["buffers"][0] = {"byteLength": len(data),
                         "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(data)).decode()}


def add_accessor(doc, array: np.ndarray, component: int, kind: str, normalized=False) -> int:
    """Append ``array``'s bytes to buffer 0 as a new view and accessor; its index."""
    data = buffer_bytes(doc)
    data.extend(b"\0" * (-len(data) % 4))
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(data), "byteLength": array.nbytes})
    data.extend(np.ascontiguousarray(array).tobytes())
    set_buffer(doc, data)
    doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": component,
                             "count": len(array), "type": kind, "normalized": normalized})
    return len(doc["accessors"]) - 1


def write(tmp_path, doc, name="variant.gltf") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def test_the_sample_reads_with_its_skeleton_root_and_clip():
    read = read_gltf(SAMPLE)
    skin = read.skin
    assert read.notes == ()
    assert skin.vertices.shape == (96, 3) and skin.faces.shape == (188, 3)
    assert skin.skeleton.parents.tolist() == [-1, 0]
    # node 0 (a Z-up matrix) and node 4 (identity) above the joints fold into the root.
    np.testing.assert_allclose(skin.skeleton.root, [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0],
                                                    [0, 0, 0, 1]], atol=1e-12)
    assert [c.name for c in skin.clips] == ["animation 0"]
    assert skin.clips[0].duration_s == pytest.approx(2.083333015441895)
    assert len(skin.clips[0].channels) == 6


def test_external_buffers_read_the_same(tmp_path):
    doc = sample_document()
    (tmp_path / "cylinder data.bin").write_bytes(bytes(buffer_bytes(doc)))
    doc["buffers"][0] = {"byteLength": doc["buffers"][0]["byteLength"], "uri": "cylinder%20data.bin"}
    skin = read_gltf(write(tmp_path, doc)).skin
    np.testing.assert_array_equal(skin.vertices, read_gltf(SAMPLE).skin.vertices)
    (tmp_path / "cylinder data.bin").unlink()
    with pytest.raises(GltfError, match="its file 'cylinder%20data.bin' is missing"):
        read_gltf(tmp_path / "variant.gltf")


def test_normalised_integer_weights_are_scaled(tmp_path):
    doc = sample_document()
    weights = np.frombuffer(bytes(buffer_bytes(doc)[224:1760]), np.float32).reshape(-1, 4)
    attributes = doc["meshes"][0]["primitives"][0]["attributes"]
    as_short = np.round(weights * 65535).astype(np.uint16)
    attributes["WEIGHTS_0"] = add_accessor(doc, as_short, 5123, "VEC4", normalized=True)
    skin = read_gltf(write(tmp_path, doc)).skin
    np.testing.assert_allclose(skin.weights, weights, atol=1.5 / 65535)


def test_normalised_integer_rotations_are_scaled(tmp_path):
    """Quantized keyframes (KHR_mesh_quantization): rotations as normalised shorts."""
    doc = sample_document()
    floats = read_gltf(SAMPLE).skin.clips[0].channels[4].values  # node 3's rotation
    shorts = np.round(floats * 32767).astype(np.int16)
    doc["animations"][0]["samplers"][4]["output"] = add_accessor(doc, shorts, 5122, "VEC4", normalized=True)
    values = read_gltf(write(tmp_path, doc)).skin.clips[0].channels[4].values
    np.testing.assert_allclose(values, floats, atol=1 / 32767)


def test_sparse_weights_that_do_not_sum_to_one_are_normalised_and_said(tmp_path):
    doc = sample_document()
    rows = np.array([3, 10], dtype=np.uint16)
    values = np.array([[0.5, 0.25, 0, 0], [0.6, 0.6, 0, 0]], dtype=np.float32)
    indices = add_accessor(doc, rows, 5123, "SCALAR")
    replaced = add_accessor(doc, values, 5126, "VEC4")
    weights = doc["meshes"][0]["primitives"][0]["attributes"]["WEIGHTS_0"]
    doc["accessors"][weights]["sparse"] = {
        "count": 2,
        "indices": {"bufferView": doc["accessors"][indices]["bufferView"], "componentType": 5123},
        "values": {"bufferView": doc["accessors"][replaced]["bufferView"]}}
    read = read_gltf(write(tmp_path, doc))
    assert "normalised the weights of 2 vertices that did not sum to 1 (off by up to 0.25)" in read.notes
    np.testing.assert_allclose(read.skin.weights[3, :2], [2 / 3, 1 / 3])
    np.testing.assert_allclose(read.skin.weights[10, :2], [0.5, 0.5])


def test_vertices_split_at_seams_are_welded_and_differing_weights_said(tmp_path):
    doc = sample_document()
    prim = doc["meshes"][0]["primitives"][0]
    # A second primitive with its own copy of every vertex: a seam everywhere it meets the first.
    second = copy.deepcopy(prim)
    doc["meshes"][0]["primitives"].append(second)
    data = buffer_bytes(doc)
    faces = np.frombuffer(bytes(data[5000:6128]), np.uint16).reshape(-1, 3)
    prim["indices"] = add_accessor(doc, faces[:90].reshape(-1).copy(), 5123, "SCALAR")
    second["indices"] = add_accessor(doc, faces[90:].reshape(-1).copy(), 5123, "SCALAR")
    read = read_gltf(write(tmp_path, doc))
    assert any(n.startswith("welded 96 vertices split at seams (192 -> 96)") for n in read.notes)
    assert read.skin.vertices.shape == (96, 3) and read.skin.joints.shape == (96, 4)
    assert read.skin.faces.shape == (188, 3) and not any("boundary" in n for n in read.notes)
    # The copies' weights differ: the reader says so.
    other = np.tile(np.array([[0.5, 0.5, 0, 0]], np.float32), (96, 1))
    second["attributes"] = dict(second["attributes"], WEIGHTS_0=add_accessor(doc, other, 5126, "VEC4"))
    notes = read_gltf(write(tmp_path, doc)).notes
    assert any("welded positions have different joints or weights" in n for n in notes), notes


def test_placement_moves_the_whole_skin_at_every_pose(tmp_path):
    doc = sample_document()
    doc["animations"][0]["channels"].pop(3)  # node 3's translation: its rest one is used
    skin = read_gltf(write(tmp_path, doc)).skin
    placed, transform = MeshPlacement(z_up=True, fit_size=1.7).apply_to_skin(skin)
    assert np.ptp(placed.vertices, axis=0).max() == pytest.approx(1.7)
    for t in (0.0, 0.7, 1.9):
        before = skin_vertices(skin, pose_at(skin, None, t)[0])
        after, _ = pose_at(placed, None, t)
        np.testing.assert_allclose(skin_vertices(placed, after),
                                   before @ transform[:3, :3].T + transform[:3, 3], atol=1e-12)
        # The joints stay rigid: the scale went into the translations.
        np.testing.assert_allclose(np.linalg.det(after[:, :3, :3]), 1.0, atol=1e-6)


def broken(doc, change):
    doc = copy.deepcopy(doc)
    change(doc)
    return doc


@pytest.mark.parametrize("change, message", [
    (lambda d: d["nodes"][1].pop("skin"), "no skinned mesh: 1 mesh"),
    (lambda d: d.update(extensionsRequired=["KHR_draco_mesh_compression"]),
     "requires the extension KHR_draco_mesh_compression"),
    (lambda d: d["buffers"][0].update(uri=d["buffers"][0]["uri"][:4000]), "truncated|not valid base64"),
    (lambda d: d["bufferViews"][2].update(byteLength=900), "runs past its buffer view 2"),
    (lambda d: d["accessors"][0].update(count=5000), "runs past its buffer view 0"),
    (lambda d: d.update(skins=d["skins"] * 2) or d["nodes"].append({"mesh": 0, "skin": 1})
     or d["scenes"][0]["nodes"].append(5), "2 skins .*one skinned character per file"),
    (lambda d: d["nodes"][2].update(rotation=None) or d["nodes"][2].update(
        matrix=[1, 0.5, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]), "shear or projection"),
    (lambda d: d["animations"][0]["samplers"][0].update(output=9),
     "channel 0: \\[3, 1\\] output values for 3 times of translation"),
    (lambda d: d["animations"][0]["samplers"][1].update(input=0),
     "channel 1: .*keyframe times do not increase|output values"),
    (lambda d: d["asset"].update(version="1.0"), "only glTF 2.0"),
])
def test_broken_files_are_one_line_errors_naming_the_file(tmp_path, change, message):
    doc = broken(sample_document(), change)
    doc["nodes"][2] = {k: v for k, v in doc["nodes"][2].items() if v is not None}
    path = write(tmp_path, doc)
    with pytest.raises(GltfError, match=message) as caught:
        read_gltf(path)
    assert str(caught.value).startswith(f"{path}: ") and "\n" not in str(caught.value)


def test_not_a_gltf_file(tmp_path):
    for name, data, message in (("a.gltf", b'{"asset": ', "not valid glTF JSON"),
                                ("b.glb", b"glTF\x02\0\0\0\x10", "truncated .glb"),
                                ("c.gltf", b"\xff\xfe\x00binary", "neither a .glb")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(GltfError, match=message):
            read_gltf(tmp_path / name)
    with pytest.raises(GltfError, match="no such glTF file"):
        read_gltf(tmp_path / "missing.gltf")


def test_strips_and_fans_become_triangles_wound_alike():
    from collider_server.making.gltf import primitive_triangles

    strip = primitive_triangles(np.arange(6), 5)
    assert strip.tolist() == [[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]]
    fan = primitive_triangles(np.array([7, 1, 2, 3, 4]), 6)
    assert fan.tolist() == [[7, 1, 2], [7, 2, 3], [7, 3, 4]]
    assert primitive_triangles(np.arange(7), 4).tolist() == [[0, 1, 2], [3, 4, 5]]
