"""Every command in the README, docs/ and models/README.md runs on a fresh clone: no documented
command uses a folder outside the repository (`../shared` exists only beside this project's CI),
every `collider` command parses, every file it reads is in the repository (or written by a
command before it on the same page), the fast ones run for real, and the README's curl and
Python snippets get real answers from a real server."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from tests.conftest import run_collider

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", ROOT / "models" / "README.md", ROOT / "docker" / "README.md",
                *(ROOT / "docs").glob("*.md")])
#: Subcommands that answer in about a second and write nothing: run for real.
FAST = {"info", "query"}
#: Options whose value is a file the command reads.
INPUT_OPTIONS = {"mesh", "points", "pose", "config", "bench", "animation"}


def blocks(page: Path, languages=("bash", "sh", "console", "")) -> list[str]:
    """The fenced code blocks of ``page`` in ``languages`` ('' = no language given)."""
    return [body for language, body in re.findall(r"```([a-z]*)\n(.*?)```", page.read_text(), re.DOTALL)
            if language in languages]


def commands(page: Path) -> list[str]:
    """Shell commands of the page's shell blocks, continuation lines joined, comments kept."""
    out = []
    for block in blocks(page):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip()
            if line and not line.startswith("#"):
                out.append(line)
    return out


def page_commands(page: Path) -> list[tuple[list[str] | None, str]]:
    """Every command on the page, in order (lines split at ``&&``, ``;`` and ``|``): its argv
    (None where the split cut it, as in ``python -c "a; b"``) and its text."""
    out: list[tuple[list[str] | None, str]] = []
    for line in commands(page):
        for part in re.split(r"&&|;|\|", line):
            try:
                argv = shlex.split(part, comments=True)
            except ValueError:
                argv = None
            if argv != []:
                out.append((argv, part))
    return out


def collider_commands(page: Path) -> list[list[str]]:
    """The argv (after ``collider``) of every ``collider ...`` command on the page."""
    return [argv[1:] for argv, _ in page_commands(page) if argv and argv[0] == "collider"]


#: A file name in another command's text (a script's argument, a path in ``python -c``'s code):
#: what that command may write.
NAMED_FILE = re.compile(r"[\w./-]+\.\w+")


def all_pages_commands():
    return [(page.relative_to(ROOT).as_posix(), argv) for page in PAGES for argv in collider_commands(page)]


def test_the_pages_document_commands():
    """The checks below see the pages' commands (a broken extractor would pass them all)."""
    found = all_pages_commands()
    assert len(found) >= 20
    assert ("README.md", ["info"]) in found


def test_no_documented_command_uses_a_folder_outside_the_repository():
    wrong = [f"{page.relative_to(ROOT)}: {line}" for page in PAGES for line in commands(page)
             if "../shared" in line or "/work/" in line]
    assert wrong == []


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_collider_command_parses_and_names_files_that_exist(page):
    from collider_cli import build_parser

    parser = build_parser()
    made: set[str] = set()  # files and model names written by earlier commands on the page
    problems = []
    for command, text in page_commands(page):
        if not command or command[0] != "collider":  # a script: the files it names may be what it writes
            made |= set(NAMED_FILE.findall(text))
            continue
        argv = command[1:]
        if "--help" in argv or "-h" in argv:
            continue
        try:
            args = parser.parse_args(argv)
        except SystemExit:
            problems.append(f"does not parse: collider {shlex.join(argv)}")
            continue
        for path in _inputs(args):
            # An absolute path is not the repository's, whatever this machine holds there.
            if (Path(path).is_absolute() or not (ROOT / path).exists()) and path not in made and str(Path(path).with_suffix("")) not in made:
                problems.append(f"collider {shlex.join(argv)}: {path} is not in the repository")
        model = getattr(args, "model", None)
        if model and args.command in ("query", "info", "eval", "view") and model not in made \
                and not (ROOT / "models" / f"{model}.safetensors").is_file() and not Path(model).suffix:
            problems.append(f"collider {shlex.join(argv)}: no model {model!r} in models/ nor made before")
        made |= _outputs(args)
    assert problems == []


def _inputs(args) -> list[str]:
    # (eval's --points is a count, query's a file: files are the options argparse makes Paths)
    paths = [str(value) for name in INPUT_OPTIONS if (value := getattr(args, name, None)) is not None
             and (isinstance(value, Path) or name in ("mesh", "animation"))]
    if args.command in ("bake", "train", "bench"):
        paths.append(args.mesh)
    paths += [item.partition("=")[2] for item in getattr(args, "check_mesh", None) or []]
    if args.command == "simulate" and (args.scene.endswith(".toml") or "/" in args.scene):
        paths.append(args.scene)
    return paths


def _outputs(args) -> set[str]:
    made = {args.name} if getattr(args, "name", None) else set()
    if args.command == "animate":
        made |= {str(args.output / f"{args.name}.obj"), str(args.output / f"{args.name}.pc2")}
        if args.name == "walker":  # also the character, and the skinned model with --bake skinned
            made |= {str(args.output / "walker.glb"), "walker-skinned"}
    if args.command == "simulate":
        from collider_client.sim.scene import load_scene, resolve_scene

        stem = load_scene(resolve_scene(args.scene)).path.stem
        made |= {str(args.output / stem), str(args.output / f"{stem}.pc2"), str(args.output / f"{stem}.obj")}
    return made


FAST_COMMANDS = [(page, argv) for page, argv in all_pages_commands()
                 if argv and argv[0] in FAST and "--models" not in argv]


@pytest.mark.parametrize("page, argv", FAST_COMMANDS, ids=[f"{p}: {' '.join(a)}" for p, a in FAST_COMMANDS])
def test_the_fast_commands_run(page, argv, monkeypatch):
    """Run as a user would, from the repository's root, on the shipped models: in this process (a
    traceback would be an exception here; the installed entry point's own process is
    tests/cli/test_cli_models.py's)."""
    monkeypatch.delenv("COLLIDER_MODELS", raising=False)
    monkeypatch.chdir(ROOT)
    out = run_collider(*argv)
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr and out.stdout.strip()


def test_the_readme_service_snippets_answer(tmp_path):
    """The README's curl command and Python snippet, against a real server (its port instead of
    8000: the documented one may be taken here)."""
    import json

    from collider_cli.launch import ServerThread

    readme = ROOT / "README.md"
    curl = [c for c in commands(readme) if c.startswith("curl")]
    python = blocks(readme, ("python",))
    assert curl and python
    # Every shipped model loaded and warmed up, as `collider serve` does: in a fresh checkout the
    # first warm-up compiles each kind's numba kernels (the articulated walker's take about a
    # minute on 2 busy cores; cached after), so give it the time a first start takes.
    with ServerThread(models=ROOT / "models", device="cpu", ready_timeout_s=300.0) as server:
        for command in curl:
            command = command.replace("localhost:8000", f"127.0.0.1:{server.port}")
            out = subprocess.run(command, shell=True, capture_output=True, text=True, timeout=60)
            assert out.returncode == 0, out.stderr
            answer = json.loads(out.stdout)
            assert {"distance", "model"} <= set(answer), answer
        for code in python:
            script = tmp_path / "snippet.py"
            script.write_text(code.replace("http://127.0.0.1:8000", server.url))
            out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
            assert out.returncode == 0, out.stderr


def test_ci_runs_the_readmes_test_command():
    """CI (.ci/run) runs the README's test command, so the README's promise is what CI checks."""
    readme_test = [c.split("#")[0].strip() for c in commands(ROOT / "README.md") if "pytest" in c]
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()
          if "pytest" in line and not line.lstrip().startswith("#")]
    assert readme_test and readme_test == ci
