"""Every hint a ``collider`` command prints works when pasted.

The commands are run in the situations where they print hints, in a user's working folder of
their own with the user's cache directory pointed at a scratch one: a bake, a training run (its
``next:`` line and, interrupted, how to resume), ``info`` of a model never evaluated, a bench and a
budget bake that leave presets unmeasured, a budget bake given another mesh's figures, and eval
told the wrong unit. What they print is what is read, so they run in this process from the words
a shell would split their line into (``here``; a fresh ``collider`` spends seconds of CPU
importing torch before its work), except the interrupted training run, whose SIGTERM is part of
the situation. Each hint (a ``next: collider ...`` line or a ``collider ...`` between backticks) is
then pasted into a shell as a user pastes it, the installed ``collider`` in that folder with that
environment: it must finish with status 0, or, when it is a long job (a training run, a full
bench, an eval), run without an error until its work is under way (``UNDER_WAY``: a progress bar
that counted work done, or the line that starts it; at most ``LONG_AFTER_S``) and end on SIGTERM
with status 143 (what an interrupted long command returns).

The situations are built once per run (``built_once``: the commands that depend on each other,
such as the bench of the trained network, in one folder; the independent ones apart), and each
hint is pasted by a test of its own in a copy of the folder its command left, so that pytest-xdist
spreads the hints over its workers and no hint runs in what another hint left behind.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest
from tests.conftest import run_collider

HINT = re.compile(r"next: (collider .+)$|`(collider [^`]+)`", re.MULTILINE)
#: A pasted hint still running after this long is a long job: it is stopped with SIGTERM.
LONG_AFTER_S = 20.0
#: A progress bar on stderr that has counted work done (tqdm's "| 1.00/5.00", not "| 0.00/5.00").
COUNTED = re.compile(r"\| *(?!0\.00/)\d[\d.]*[kMG]?/\d")
#: What a long job prints on stderr once its work is under way, its command line, files and
#: models accepted: a progress bar that counted work done (eval's first step, train's first
#: second), a bench's plan ("bench: building and measuring ...", printed with --quiet too), a
#: resumed training run's first line. A pasted hint is stopped with SIGTERM once it prints one,
#: without waiting for LONG_AFTER_S.
UNDER_WAY = re.compile(COUNTED.pattern + r"|^bench: building and measuring |^resuming ", re.MULTILINE)
MODELS = "my models"  # a folder name that needs quoting in a shell

pytestmark = pytest.mark.skipif(shutil.which("collider") is None, reason="the collider command is not installed")


def user_env(home: Path) -> dict:
    """The environment a user working in ``home`` runs commands in."""
    env = {k: v for k, v in os.environ.items() if k not in ("COLLIDER_MODELS", "XDG_CACHE_HOME")}
    env["XDG_CACHE_HOME"] = str(home / "cache")  # the default cache, in the user's own cache dir
    return env


def here(command: str, cwd: Path, env: dict) -> subprocess.CompletedProcess:
    """``command`` (a ``collider ...`` line) run in this process as a shell in ``cwd`` with ``env``
    would run it: the words ``shlex`` splits it into, that folder the working directory and
    ``env`` the environment while it runs (both restored after)."""
    words = shlex.split(command)
    assert words[0] == "collider", command
    saved_env, saved_cwd = dict(os.environ), os.getcwd()
    os.environ.clear()
    os.environ.update(env)
    os.chdir(cwd)
    try:
        return run_collider(*words[1:])
    finally:
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)


def hints(*outputs: str) -> list[str]:
    found = []
    for text in outputs:
        for match in HINT.finditer(text):
            found.append((match.group(1) or match.group(2)).strip())
    return found


def paste(hint: str, cwd: Path, env: dict, under_way: re.Pattern = UNDER_WAY) -> str:
    """Run ``hint`` as pasted; returns how it ended ("0", or "143 after SIGTERM": still running
    once it printed ``under_way`` or after LONG_AFTER_S)."""
    # bash parses the line as typed; exec makes the command itself the process SIGTERM reaches.
    process = subprocess.Popen(["bash", "-c", f"exec {hint}"], cwd=cwd, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE)
    out, err = Drained(process.stdout), Drained(process.stderr)
    deadline = time.monotonic() + LONG_AFTER_S
    while process.poll() is None and time.monotonic() < deadline and not under_way.search(err.text()):
        time.sleep(0.1)
    if process.poll() is None:
        # A long job that started without refusing anything: stop it as a user or a scheduler would.
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=120)
        # 143: stopped as a long command stops; -15: the signal came as it was exiting after its
        # work (its SIGTERM handler already handed back), e.g. an eval that took the whole wait.
        assert process.returncode in (143, -signal.SIGTERM), \
            f"{hint!r} after SIGTERM: {process.returncode}\n{err.all()[-2000:]}"
        assert "error:" not in err.all(), f"{hint!r}: {err.all()[-2000:]}"
        return "143 after SIGTERM"
    assert process.returncode == 0, f"{hint!r} exited {process.returncode}:\n{out.all()[-2000:]}\n{err.all()[-2000:]}"
    return "0"


class Drained:
    """A pipe read to its end by a thread of its own (a full pipe would stop the command):
    :meth:`text` is what came so far, :meth:`all` all of it (once the command has ended)."""

    def __init__(self, pipe):
        self._chunks: list[bytes] = []
        self._thread = threading.Thread(target=self._read, args=(pipe,), daemon=True)
        self._thread.start()

    def _read(self, pipe) -> None:
        with pipe:
            for chunk in iter(lambda: os.read(pipe.fileno(), 65536), b""):
                self._chunks.append(chunk)

    def text(self) -> str:
        return b"".join(self._chunks).decode(errors="replace")

    def all(self) -> str:
        self._thread.join(timeout=60)
        return self.text()


# -- the situations: each builder runs its commands in a user's folder and returns what they printed


def add_meshes(home: Path) -> None:
    import trimesh

    trimesh.creation.icosphere(subdivisions=3, radius=0.05).export(home / "ball.obj")
    trimesh.creation.box(extents=(0.08, 0.06, 0.04)).export(home / "box.obj")


def baked(home: Path, env: dict) -> dict[str, str]:
    """A voxel bake, ``info`` of it never evaluated, a budget bake given a missing bench, and eval
    told the wrong unit."""
    bake = here(f"collider bake ball.obj --name ball-grid --resolution 16 --models '{MODELS}'", home, env)
    assert bake.returncode == 0, bake.stderr
    assert f"next: collider eval ball-grid --mesh ball.obj --models '{MODELS}'" in bake.stdout

    info = here(f"collider info ball-grid --models '{MODELS}'", home, env)
    assert info.returncode == 0 and "not evaluated" in info.stdout, info.stdout + info.stderr

    # Its refusal prints no hint to paste.
    budget = here(f"collider bake ball.obj --name ball-pick --models '{MODELS}' --max-error 50mm --kind voxel "
                  "--quiet --bench box-bench.json", home, env)
    assert budget.returncode == 2  # no such file: refused in one line, no hint

    units = here(f"collider eval ball-grid --mesh ball.obj --models '{MODELS}' --units mm --no-save", home, env)
    assert units.returncode == 2 and "is not the unit ball-grid was made in" in units.stderr
    return {"bake": bake.stdout + bake.stderr, "info": info.stdout, "eval --units": units.stderr}


def trained(home: Path, env: dict) -> dict[str, str]:
    """A training run, then a bench of its network that leaves a preset unmeasured."""
    # A few steps: the hint, the checkpoint and the bench's unmeasured preset do not depend on how many.
    train = here(f"collider train ball.obj --name ball-net --models '{MODELS}' --steps 5 --samples 4000 "
                  "--batch-size 512 --scale 2 --quiet", home, env)
    assert train.returncode == 0, train.stderr
    assert f"next: collider eval ball-net --mesh ball.obj --models '{MODELS}' --scale 2.0" in train.stdout
    # The checkpoint lives beside the model folder, not in the working folder's runs/.
    assert (home / "runs" / "ball-net.ckpt.safetensors").is_file()

    bench = here(f"collider bench ball.obj --kinds neural --scale 2 --models '{MODELS}' --no-served --sizes 1k "
                  "--accuracy-points 2000 --repeats 3 --presets grid,fast --quiet --output bench-out", home, env)
    assert bench.returncode == 0, bench.stderr
    return {"train": train.stdout + train.stderr, "bench": bench.stdout}


def benched_another_mesh(home: Path, env: dict) -> dict[str, str]:
    """A budget bake given the bench of another mesh."""
    other = here("collider bench box.obj --kinds kdtree --no-served --sizes 1k --accuracy-points 1000 "
                  "--repeats 3 --quiet --output box-bench", home, env)
    assert other.returncode == 0, other.stderr
    wrong = here(f"collider bake ball.obj --name ball-pick --models '{MODELS}' --max-error 50mm "
                  "--bench box-bench/bench.json", home, env)
    assert wrong.returncode == 2 and "measured another mesh" in wrong.stderr
    return {"bake --bench of another mesh": wrong.stderr}


def interrupted(home: Path, env: dict) -> dict[str, str]:
    """A long training run stopped by SIGTERM once it has a checkpoint."""
    # --max-minutes puts a validation, and so the first checkpoint, every 1/30 of the budget (2 s
    # here) instead of every 500 steps (minutes on a loaded 2-core host); what is checked, that the
    # interrupted run names the command that resumes it and that command resumes, is the same. The
    # budget outlasts LONG_AFTER_S, so that the pasted command is still a long job when resumed.
    run = subprocess.Popen(f"exec collider train ball.obj --name ball-long --models '{MODELS}' --steps 200000 "
                           "--max-minutes 1 --samples 4000 --batch-size 512 --quiet", shell=True, cwd=home, env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (home / "runs" / "ball-long.ckpt.safetensors").is_file() and time.monotonic() < deadline:
        time.sleep(0.5)
    run.send_signal(signal.SIGTERM)
    out, err = run.communicate(timeout=60)
    assert run.returncode == 143, err
    return {"train, SIGTERM": out + err}


#: situation -> the builder of the folder it happens in.
SITUATIONS = {"bake": baked, "info": baked, "eval --units": baked, "train": trained, "bench": trained,
              "bake --bench of another mesh": benched_another_mesh, "train, SIGTERM": interrupted}

#: Every hint each situation prints, by the start of its command (a regular expression): a new
#: hint, not listed here, fails the test of every hint of its situation until it is. Listed so that
#: neighbours need different folders: two workers taking the first tests build two at once.
HINTS = [
    pytest.param("bake", r"collider eval ball-grid --mesh ball\.obj ", id="bake-eval"),
    pytest.param("train", r"collider eval ball-net ", id="train-eval"),
    pytest.param("bake --bench of another mesh", r"collider bench ball\.obj$", id="bake-other-mesh-bench"),
    pytest.param("train, SIGTERM", r"collider train ball\.obj --name ball-long ", id="sigterm-resume"),
    pytest.param("info", r"collider eval ball-grid --mesh /", id="info-eval"),
    # a bench that trains the missing presets, and a training run of one of them
    pytest.param("bench", r"collider bench ball\.obj .*--train-minutes 3", id="bench-train-minutes"),
    pytest.param("eval --units", r"collider info ball-grid ", id="units-info"),
    pytest.param("bench", r"collider train ball\.obj --name ball-fast --preset fast --scale 2\.0 ", id="bench-train-fast"),
]


@pytest.fixture(scope="session")
def situation(built_once):
    """``situation(name)`` -> (the folder its commands left, what they printed): built once per run."""

    def get(name: str) -> tuple[Path, str]:
        build = SITUATIONS[name]

        def make(home: Path) -> None:
            add_meshes(home)
            (home / "printed.json").write_text(json.dumps(build(home, user_env(home))))

        home = built_once(f"hints-{build.__name__}", make)
        return home, json.loads((home / "printed.json").read_text())[name]

    return get


@pytest.mark.slow
@pytest.mark.parametrize(("name", "pattern"), HINTS)
def test_every_hint_every_command_prints_works_when_pasted(situation, tmp_path, name, pattern):
    built, printed = situation(name)
    found = hints(printed)
    assert found, printed
    listed = [p for n, p in (h.values for h in HINTS) if n == name]
    assert all(any(re.match(p, hint) for p in listed) for hint in found), (found, listed)
    (hint,) = [hint for hint in found if re.match(pattern, hint)]

    # Pasted in a copy of the folder the command left, as the user's shell and cache directory.
    home = tmp_path / "user"
    shutil.copytree(built, home, symlinks=True)
    # The bench of the other mesh's hint runs until its first collider is built (its bar counted
    # a step): the bench and bake caches went to the user's cache directory, not the working folder.
    cached = name == "bake --bench of another mesh"
    paste(hint, home, user_env(home), COUNTED if cached else UNDER_WAY)
    if cached:
        assert (home / "cache" / "neural-collider" / "colliders").is_dir() and not (home / "out" / "bench-cache").exists()
