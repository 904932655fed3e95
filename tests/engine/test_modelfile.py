"""Model files: bit-identical round trips for every kind, and a clear ModelFileError naming the
file for every way a file can be wrong. Loading never unpickles."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from collider_server.engine.modelfile import (
    FORMAT,
    ModelFileError,
    content_hash,
    load_collider,
    read_info,
    save_collider,
)

KINDS = ["neural", "voxel", "mesh", "kdtree"]
FIELDS = ["distance", "normal", "contact", "collides"]


def query_points(seed=0):
    rng = np.random.default_rng(seed)
    return np.concatenate([rng.uniform(-0.15, 0.15, (200, 3)), rng.uniform(-5, 5, (20, 3))])


@pytest.mark.parametrize("kind", KINDS)
def test_round_trip_is_bit_identical(shape_collider, tmp_path, kind):
    collider = shape_collider("torus", kind)
    collider.info.accuracy = {"band_1mm_mean_mm": 0.01}
    try:
        path = save_collider(collider, tmp_path / "torus")
    finally:
        collider.info.accuracy = {}
    assert path.name == "torus.safetensors"
    loaded = load_collider(path, "cpu")
    assert type(loaded) is type(collider) and loaded.info.kind == kind
    assert loaded.info.accuracy == {"band_1mm_mean_mm": 0.01}
    assert read_info(path) == loaded.info
    assert loaded.nbytes() == collider.nbytes()
    points = query_points()
    before, after = collider.query(points, FIELDS), loaded.query(points, FIELDS)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(after, name), getattr(before, name), err_msg=name)
    for name, array in collider.tensors().items():
        np.testing.assert_array_equal(loaded.tensors()[name], array, err_msg=name)


def test_save_is_atomic_and_leaves_no_temporary_files(small_sphere_model):
    folder = small_sphere_model.parent
    assert [p.name for p in folder.iterdir()] == ["sphere.safetensors"]
    # Readable by other users (a server in a container), not the private 0600 of a temp file.
    assert small_sphere_model.stat().st_mode & 0o777 == 0o644


def expect_error(path, message):
    with pytest.raises(ModelFileError, match=message) as caught:
        load_collider(path, "cpu")
    assert str(caught.value).startswith(str(path)), "the message names the file"
    assert caught.value.path == str(path)
    assert isinstance(caught.value, ValueError)
    return caught.value


def test_missing_and_non_file_paths(tmp_path):
    expect_error(tmp_path / "nothing.safetensors", "no such model file")
    expect_error(tmp_path, "is a directory, not a model file")


@pytest.mark.parametrize("keep", [0.5, 0.98, 10])
def test_truncated_file(small_sphere_model, tmp_path, keep):
    data = small_sphere_model.read_bytes()
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(data[: int(len(data) * keep)] if keep < 1 else data[:keep])
    expect_error(cut, "not a readable safetensors file|truncated")


@pytest.mark.parametrize("where", ["data", "info"])
def test_tampered_byte_fails_the_content_hash(small_sphere_model, where):
    data = bytearray(small_sphere_model.read_bytes())
    if where == "data":
        data[-100] ^= 0x01  # one bit of one grid value
    else:
        at = data.index(b"sphere", 8)  # inside the collider JSON (the name), same length
        data[at : at + 6] = b"sphare"
    small_sphere_model.write_bytes(bytes(data))
    expect_error(small_sphere_model, "content hash mismatch")


def write_model(path, tensors, info: dict, format_string=FORMAT, hash_override=None):
    """A model file written by hand (valid safetensors, chosen metadata)."""
    from safetensors.numpy import save_file

    info_json = json.dumps(info, sort_keys=True)
    metadata = {"format": format_string, "collider": info_json,
                "content_sha256": hash_override or content_hash(info_json, tensors)}
    save_file(tensors, str(path), metadata=metadata)
    return path


def base_info(kind="voxel", **changes):
    info = {"name": "x", "kind": kind, "domain_min": [-1.0, -1.0, -1.0], "domain_max": [1.0, 1.0, 1.0]}
    info.update(changes)
    return info


def test_wrong_format_string(tmp_path):
    path = write_model(tmp_path / "x.safetensors", {"grid": np.zeros((4, 4, 4), np.float32)},
                       base_info(), format_string="someone-else/3")
    expect_error(path, r"not a collider model \(format 'someone-else/3'")
    with pytest.raises(ModelFileError, match="not a collider model"):
        read_info(path)


def test_plain_safetensors_without_metadata(tmp_path):
    from safetensors.numpy import save_file

    path = tmp_path / "weights.safetensors"
    save_file({"w": np.zeros(3, np.float32)}, str(path))
    expect_error(path, r"not a collider model \(format None")


@pytest.mark.parametrize("kind, tensors, message", [
    ("voxel", {"vertices": np.zeros((4, 3))}, "exactly one tensor 'grid'"),
    ("voxel", {"grid": np.zeros((4, 4), np.float32)}, "must be 3-D"),
    ("mesh", {"vertices": np.zeros((4, 3)), "faces": np.array([[0, 1, 9]], np.int32)}, "do not exist"),
    ("mesh", {"grid": np.zeros((4, 4, 4), np.float32)}, "'vertices' and 'faces'"),
    ("kdtree", {"vertices": np.zeros((4, 3)), "normals": np.zeros((5, 3))}, r"must both be \(v, 3\)"),
    ("kdtree", {"vertices": np.zeros((0, 3)), "normals": np.zeros((0, 3))}, "no vertices"),
    ("mesh", {"vertices": np.zeros((4, 3)), "faces": np.zeros((0, 3), np.int32)}, "no faces"),
    ("neural", {"fourier": np.zeros((3, 8), np.float32)}, "lack a valid architecture"),
    ("teapot", {"grid": np.zeros((4, 4, 4), np.float32)}, "unknown collider kind 'teapot'"),
])
def test_tensors_that_do_not_fit_the_kind(tmp_path, kind, tensors, message):
    path = write_model(tmp_path / "x.safetensors", tensors, base_info(kind))
    expect_error(path, message)


def test_neural_weights_of_another_shape(tmp_path, tiny_neural_collider):
    collider = tiny_neural_collider([-1, -1, -1], [1, 1, 1])
    tensors = collider.tensors()
    tensors["fourier"] = np.zeros((3, 5), np.float32)
    path = write_model(tmp_path / "x.safetensors", tensors, collider.info.to_dict())
    expect_error(path, "weights do not match the architecture")


@pytest.mark.parametrize("info, message", [
    ("{not json", "collider metadata is malformed"),
    (json.dumps({"name": "x"}), "collider metadata is malformed"),
    (json.dumps({**base_info(), "colour": "red"}), r"unknown collider info keys: \['colour'\]"),
])
def test_malformed_metadata(tmp_path, info, message):
    from safetensors.numpy import save_file

    path = tmp_path / "x.safetensors"
    save_file({"grid": np.zeros((4, 4, 4), np.float32)}, str(path),
              metadata={"format": FORMAT, "collider": info, "content_sha256": "0"})
    expect_error(path, message)


@pytest.mark.parametrize("changes, message", [
    ({"domain_min": [-1.0, -1.0]}, r"domain_min must be 3 finite numbers, got \[-1\.0, -1\.0\]"),
    ({"domain_min": ["a", -1.0, -1.0]}, "domain_min must be 3 finite numbers"),
    ({"domain_min": [[-1.0], [-1.0], [-1.0]]}, "domain_min must be 3 finite numbers"),
    ({"domain_max": [1.0, 1.0, 1.0, 1.0]}, r"domain_max must be 3 finite numbers, got \[1\.0"),
    ({"domain_max": [1.0, None, 1.0]}, "domain_max must be 3 finite numbers"),
    ({"domain_max": [1.0, 1e400, 1.0]}, "domain_max must be 3 finite numbers"),  # JSON Infinity
    ({"domain_min": [2.0, -1.0, -1.0]},
     (r"domain_min must be below domain_max on every axis, got \[2\.0, -1\.0, -1\.0\] and "
     r"\[1\.0, 1\.0, 1\.0\]")),
    ({"domain_min": [-1.0, 1.0, -1.0]}, "domain_min must be below domain_max"),  # equal on y
    ({"meters_per_unit": 0.0}, r"meters_per_unit must be a number > 0, got 0\.0"),
    ({"meters_per_unit": -0.001}, "meters_per_unit must be a number > 0"),
    ({"meters_per_unit": "1"}, r"meters_per_unit must be a number > 0, got '1'"),
])
def test_bad_domain_or_units_in_metadata(tmp_path, changes, message):
    path = write_model(tmp_path / "x.safetensors", {"grid": np.zeros((4, 4, 4), np.float32)},
                       base_info(**changes))
    expect_error(path, message)


class _Payload:
    """Unpickling this would create ``marker``: proof that code from the file ran."""

    marker = None

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def test_loading_never_unpickles(tmp_path, monkeypatch):
    marker = tmp_path / "pwned"
    _Payload.marker = marker
    path = tmp_path / "evil.safetensors"
    path.write_bytes(pickle.dumps(_Payload()))
    # Belt and braces: any unpickling during the load fails the test outright.
    def refuse(*args, **kwargs):
        raise AssertionError("the loader unpickled")

    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(pickle, "load", refuse)
    expect_error(path, "not a readable safetensors file")
    assert not marker.exists()


def test_a_torch_checkpoint_is_refused(tmp_path):
    import torch

    path = tmp_path / "checkpoint.safetensors"
    torch.save({"w": torch.zeros(3)}, path)
    expect_error(path, "not a readable safetensors file")


def test_neural_scalar_radius_keeps_its_shape_and_old_files_still_load(tmp_path, tiny_neural_collider):
    collider = tiny_neural_collider([-1, -1, -1], [1, 1, 1], seed=4)
    from safetensors.numpy import load_file

    path = save_collider(collider, tmp_path / "new.safetensors")
    assert load_file(str(path))["radius"].shape == ()
    # A file written when the radius was stored as shape (1,).
    tensors = collider.tensors()
    tensors["radius"] = tensors["radius"].reshape(1)
    old = write_model(tmp_path / "old.safetensors", tensors, collider.info.to_dict())
    points = query_points(1)
    np.testing.assert_array_equal(load_collider(old, "cpu").query(points).distance,
                                  collider.query(points).distance)


def test_a_bad_device_is_not_blamed_on_the_file(small_sphere_model):
    with pytest.raises(ValueError, match="unknown device 'tpu'") as caught:
        load_collider(small_sphere_model, "tpu")
    assert not isinstance(caught.value, ModelFileError)
