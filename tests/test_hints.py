"""Every hint a ``collider`` command prints works when pasted.

The commands are run the way a user runs them (the installed ``collider`` through a shell, in a
working folder of their own, the user's cache directory pointed at a scratch one), in the
situations where they print hints: a bake, a training run (its ``next:`` line and, interrupted,
how to resume), ``info`` of a model never evaluated, a bench and a budget bake that leave presets
unmeasured, a budget bake given another mesh's figures, and eval told the wrong unit. Each hint
(a ``next: collider ...`` line or a ``collider ...`` between backticks) is then pasted into the
same shell: it must finish with status 0, or, when it is a long job (a training run, a full
bench), run for a while without an error and end on SIGTERM with status 143 (what an interrupted
long command returns).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

HINT = re.compile(r"next: (collider .+)$|`(collider [^`]+)`", re.MULTILINE)
#: A pasted hint still running after this long is a long job: it is stopped with SIGTERM.
LONG_AFTER_S = 20.0

pytestmark = pytest.mark.skipif(shutil.which("collider") is None, reason="the collider command is not installed")


@pytest.fixture(scope="module")
def user(tmp_path_factory):
    """A user's working folder with a mesh, and the environment they run commands in."""
    import trimesh

    home = tmp_path_factory.mktemp("user")
    trimesh.creation.icosphere(subdivisions=3, radius=0.05).export(home / "ball.obj")
    trimesh.creation.box(extents=(0.08, 0.06, 0.04)).export(home / "box.obj")
    env = {k: v for k, v in os.environ.items() if k not in ("COLLIDER_MODELS", "XDG_CACHE_HOME")}
    env["XDG_CACHE_HOME"] = str(home / "cache")  # the default cache, in the user's own cache dir
    return home, env


def shell(command: str, cwd: Path, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(command, shell=True, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def hints(*outputs: str) -> list[str]:
    found = []
    for text in outputs:
        for match in HINT.finditer(text):
            found.append((match.group(1) or match.group(2)).strip())
    return found


def paste(hint: str, cwd: Path, env: dict) -> str:
    """Run ``hint`` as pasted; returns how it ended ("0" or "143 after SIGTERM")."""
    # bash parses the line as typed; exec makes the command itself the process SIGTERM reaches.
    process = subprocess.Popen(["bash", "-c", f"exec {hint}"], cwd=cwd, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        out, err = process.communicate(timeout=LONG_AFTER_S)
    except subprocess.TimeoutExpired:
        # A long job that started without refusing anything: stop it as a user or a scheduler would.
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=120)
        # 143: stopped as a long command stops; -15: the signal came as it was exiting after its
        # work (its SIGTERM handler already handed back), e.g. an eval that took the whole wait.
        assert process.returncode in (143, -signal.SIGTERM), f"{hint!r} after SIGTERM: {process.returncode}\n{err[-2000:]}"
        assert "error:" not in err, f"{hint!r}: {err[-2000:]}"
        return "143 after SIGTERM"
    assert process.returncode == 0, f"{hint!r} exited {process.returncode}:\n{out[-2000:]}\n{err[-2000:]}"
    return "0"


@pytest.mark.slow
def test_every_hint_every_command_prints_works_when_pasted(user):
    home, env = user
    models = "my models"  # a folder name that needs quoting in a shell
    printed = []

    bake = shell(f"collider bake ball.obj --name ball-grid --resolution 16 --models '{models}'", home, env)
    assert bake.returncode == 0, bake.stderr
    printed.append(("bake", bake.stdout + bake.stderr))
    assert f"next: collider eval ball-grid --mesh ball.obj --models '{models}'" in bake.stdout

    train = shell(f"collider train ball.obj --name ball-net --models '{models}' --steps 60 --samples 4000 "
                  "--batch-size 512 --scale 2 --quiet", home, env)
    assert train.returncode == 0, train.stderr
    printed.append(("train", train.stdout + train.stderr))
    assert f"next: collider eval ball-net --mesh ball.obj --models '{models}' --scale 2.0" in train.stdout
    # The checkpoint lives beside the model folder, not in the working folder's runs/.
    assert (home / "runs" / "ball-net.ckpt.safetensors").is_file()

    info = shell(f"collider info ball-grid --models '{models}'", home, env)
    assert info.returncode == 0 and "not evaluated" in info.stdout, info.stdout + info.stderr
    printed.append(("info", info.stdout))

    bench = shell(f"collider bench ball.obj --kinds neural --scale 2 --models '{models}' --no-served --sizes 1k "
                  "--accuracy-points 2000 --repeats 3 --presets grid,fast --quiet --output bench-out", home, env)
    assert bench.returncode == 0, bench.stderr
    printed.append(("bench", bench.stdout))

    budget = shell(f"collider bake ball.obj --name ball-pick --models '{models}' --max-error 50mm --kind voxel "
                   "--quiet --bench box-bench.json", home, env)
    assert budget.returncode == 2  # no such file: refused in one line, no hint
    other = shell("collider bench box.obj --kinds kdtree --no-served --sizes 1k --accuracy-points 1000 "
                  "--repeats 3 --quiet --output box-bench", home, env)
    assert other.returncode == 0, other.stderr
    wrong = shell(f"collider bake ball.obj --name ball-pick --models '{models}' --max-error 50mm "
                  "--bench box-bench/bench.json", home, env)
    assert wrong.returncode == 2 and "measured another mesh" in wrong.stderr
    printed.append(("bake --bench of another mesh", wrong.stderr))

    units = shell(f"collider eval ball-grid --mesh ball.obj --models '{models}' --units mm --no-save", home, env)
    assert units.returncode == 2 and "is not the unit ball-grid was made in" in units.stderr
    printed.append(("eval --units", units.stderr))

    interrupted = subprocess.Popen(f"exec collider train ball.obj --name ball-long --models '{models}' --steps 200000 "
                                   "--samples 4000 --batch-size 512 --quiet", shell=True, cwd=home, env=env,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (home / "runs" / "ball-long.ckpt.safetensors").is_file() and time.monotonic() < deadline:
        time.sleep(0.5)
    interrupted.send_signal(signal.SIGTERM)
    out, err = interrupted.communicate(timeout=60)
    assert interrupted.returncode == 143, err
    printed.append(("train, SIGTERM", out + err))

    found = {name: hints(text) for name, text in printed}
    assert all(found.values()), {name: text for name, text in printed if not found[name]}
    outcomes = {}
    for commands in found.values():
        for command in commands:
            if command not in outcomes:
                outcomes[command] = paste(command, home, env)
    # Among them: eval after bake and after train, a bench that trains the missing presets, a
    # training run of one of them, the bench of the right mesh, info, and the resumed training.
    assert any(c.startswith("collider eval ball-net") for c in outcomes)
    assert any("--train-minutes 3" in c for c in outcomes)
    assert any(c.startswith("collider train ball.obj --name ball-fast --preset fast --scale 2.0") for c in outcomes)
    assert any(c.startswith("collider info ball-grid") for c in outcomes)
    assert any(c.startswith("collider train ball.obj --name ball-long") for c in outcomes)
    # The bench and bake caches went to the user's cache directory, not the working folder.
    assert (home / "cache" / "neural-collider" / "colliders").is_dir() and not (home / "out" / "bench-cache").exists()
