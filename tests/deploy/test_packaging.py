"""Packaging: the extras split (serve / train / sim), the images' pinned constraints, the shipped
models found by a normal (non-editable) ``pip install``, and the licence files in the wheel."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import tomllib
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
EXTRAS = PYPROJECT["project"]["optional-dependencies"]
CONSTRAINTS = REPO / "docker" / "constraints.txt"


def requirements(extra: str) -> dict[str, Requirement]:
    """The extra's direct requirements, self-references (``neural-collider[serve]``) expanded."""
    found: dict[str, Requirement] = {}
    for line in EXTRAS[extra]:
        req = Requirement(line)
        if req.name == "neural-collider":
            for sub in req.extras:
                found.update(requirements(sub))
        else:
            found[req.name.lower()] = req
    return found


def pins(path: Path) -> dict[str, str]:
    found = {}
    for line in path.read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            req = Requirement(line)
            (spec,) = req.specifier  # exactly one '==' pin per line
            assert spec.operator == "==", f"{path.name}: {line!r} is not pinned with =="
            found[req.name.lower()] = spec.version
    return found


def test_serving_extra_leaves_out_training_and_plotting():
    serve = requirements("serve")
    assert "torch" in serve and "fastapi" in serve
    for heavy in ("matplotlib", "scikit-image", "trimesh"):
        assert heavy not in serve, f"{heavy} is not needed to serve"


def test_server_extra_is_the_union_of_the_others():
    union = {**requirements("serve"), **requirements("train"), **requirements("sim")}
    assert set(requirements("server")) == set(union)


def test_constraints_pin_every_serving_requirement_within_its_range():
    pinned = pins(CONSTRAINTS)
    for name, req in requirements("serve").items():
        if name == "torch":
            continue  # pinned by the Dockerfile's TORCH_VERSION (its index differs per target)
        if req.marker is not None and not req.marker.evaluate({"sys_platform": "linux"}):
            continue
        assert name in pinned, f"docker/constraints.txt lacks {name}"
        assert req.specifier.contains(pinned[name]), f"{name}=={pinned[name]} is outside {req}"


@pytest.mark.slow
def test_a_wheel_install_serves_the_shipped_models(tmp_path):
    """Build the wheel, install it (no dependencies: they are this venv's) under a prefix, and
    list the default repository from a folder that has no models/: the shipped models."""
    from importlib.metadata import version

    from packaging.version import Version

    if Version(version("setuptools")) < Version("77"):
        pytest.skip("setuptools >= 77 (the build backend) is not installed here: pip install -e '.[dev]'")
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "--quiet", "-w", str(wheels), str(REPO)], check=True, cwd=tmp_path)
    (wheel,) = wheels.glob("neural_collider-*.whl")
    # The licence and the third-party notice travel in the wheel, named by its metadata.
    with zipfile.ZipFile(wheel) as archive:
        (metadata,) = [n for n in archive.namelist() if n.endswith(".dist-info/METADATA")]
        named = [line.split(":", 1)[1].strip() for line in archive.read(metadata).decode().splitlines()
                 if line.startswith("License-File:")]
        assert named == ["LICENSE", "THIRD_PARTY_NOTICES.md"]
        for name in named:
            (inside,) = [n for n in archive.namelist() if n.endswith(f".dist-info/licenses/{name}")]
            assert archive.read(inside) == (REPO / name).read_bytes()
    prefix = tmp_path / "prefix"
    # --ignore-installed: without it pip uninstalls this venv's own (editable) neural-collider
    # before installing under the prefix, and every later test loses collider_server.
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--ignore-installed",
                    "--quiet", "--prefix", str(prefix), str(wheel)], check=True)
    (site,) = prefix.glob("lib/python*/site-packages")
    empty = tmp_path / "elsewhere"
    empty.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("COLLIDER_MODELS", "PYTHONPATH")}
    env["PYTHONPATH"] = str(site)
    script = ("import collider_server, sys; from collider_server.engine.repository import ModelRepository;"
              "r = ModelRepository(); print(collider_server.__file__); print(r.root);"
              "print(','.join(r.names()))")
    out = subprocess.run([sys.executable, "-c", script], cwd=empty, env=env, check=True,
                         capture_output=True, text=True).stdout.splitlines()
    assert out[0].startswith(str(site)), "the test imported the wrong copy of collider_server"
    assert Path(out[1]) == (prefix / "share" / "neural-collider" / "models").resolve()
    shipped = sorted(p.stem for p in (REPO / "models").glob("*.safetensors"))
    assert out[2].split(",") == shipped


def test_a_command_whose_extra_is_missing_names_the_extra(monkeypatch, capsys, tmp_path):
    import collider_cli as cli

    mesh = tmp_path / "box.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    monkeypatch.setitem(sys.modules, "trimesh", None)  # as if only the 'serve' extra were installed
    code = cli.main(["bake", str(mesh), "--kind", "kdtree", "--name", "box",
                     "--models", str(tmp_path / "models")])
    err = capsys.readouterr().err
    assert code == 2
    assert "trimesh is not installed" in err and "neural-collider[train]" in err
    assert "Traceback" not in err
