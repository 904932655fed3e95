"""A model repository: every NAME.safetensors in a folder is found by NAME; names are checked."""

from __future__ import annotations

import shutil

import pytest

from collider_server.engine.repository import ModelRepository, check_name, default_models_dir


@pytest.fixture
def repo(small_sphere_model):
    folder = small_sphere_model.parent
    shutil.copy(small_sphere_model, folder / "ball_2.0-v1.safetensors")
    (folder / "notes.txt").write_text("not a model")
    (folder / ".sphere.safetensors.abc.tmp").write_bytes(b"half a file")
    (folder / ".hidden.safetensors").write_bytes(b"x")
    (folder / "has space.safetensors").write_bytes(b"x")
    (folder / "twice.safetensors.safetensors").write_bytes(b"x")  # stem ends in the suffix
    (folder / "sub.safetensors").mkdir()
    return ModelRepository(folder)


def test_discovery_by_name(repo):
    assert repo.names() == ["ball_2.0-v1", "sphere"]
    for name in repo.names():
        assert repo.path(name).is_file()
        assert repo.info(name).kind == "voxel"
        collider = repo.load(name, "cpu")
        assert collider.device == "cpu"
        assert collider.query([[0.0, 0.0, 0.0]], "distance").distance[0] < -0.09


def test_a_path_works_where_a_name_does(repo, tmp_path, monkeypatch):
    path = repo.path("sphere")
    assert repo.resolve(str(path)) == path
    assert repo.load(str(path), "cpu").info.name == "sphere"
    # A bare name is a repository name even if a file of that name is in the working directory.
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sphere").write_text("a stray file")
    assert repo.resolve("sphere") == path


def test_unknown_name_lists_the_models(repo):
    with pytest.raises(FileNotFoundError, match=r"no model named 'cube' in .* \(models: ball_2.0-v1, sphere\)"):
        repo.load("cube")


def test_missing_folder_has_no_models(tmp_path):
    empty = ModelRepository(tmp_path / "absent")
    assert empty.names() == []
    with pytest.raises(FileNotFoundError, match=r"\(models: none\)"):
        empty.info("anything")


@pytest.mark.parametrize("name", ["", "../etc/passwd", "a/b", ".hidden", "-flag", "a b", "x" * 65,
                                  "model.safetensors", "naïve", None, 7])
def test_invalid_names_are_rejected(repo, name):
    with pytest.raises(ValueError, match="invalid model name"):
        check_name(name)
    if isinstance(name, str) and "/" not in name and not name.endswith(".safetensors"):
        with pytest.raises(ValueError, match="invalid model name"):
            repo.load(name)


@pytest.mark.parametrize("name", ["bunny", "Dragon_2", "a", "v1.2-final", "x" * 64])
def test_valid_names(name):
    assert check_name(name) == name


def test_default_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("COLLIDER_MODELS", str(tmp_path))
    assert default_models_dir() == tmp_path
    assert ModelRepository().root == tmp_path
    monkeypatch.delenv("COLLIDER_MODELS")
    monkeypatch.chdir(tmp_path)
    assert default_models_dir().name == "models"
