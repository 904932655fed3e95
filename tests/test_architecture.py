"""The layout is the architecture (docs/architecture.md): every import between the project's
layers goes down the layer diagram, no two layers or packages import each other, and no package
reaches into another's private (underscore) modules or names. Imports inside functions count."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"collider_contract": "client", "collider_client": "client",
            "collider_server": "server", "collider_cli": "server"}

#: Layer of a module: the longest prefix listed here wins.
LAYERS = {
    "collider_contract": "contract",
    "collider_server": "engine",  # the package root re-exports the engine's public names
    "collider_server.engine": "engine",
    "collider_server.making": "making",
    "collider_server.service": "service",
    "collider_client": "sdk",
    "collider_client.sim": "simulator",
    "collider_client.adapters": "adapters",
    "collider_cli.launch": "tooling",
    "collider_cli.net": "tooling",
    "collider_cli": "cli",
    "collider_cli.bench": "bench",
    "collider_cli.views": "views",
}

#: What each layer may import (besides itself): the layer diagram of docs/architecture.md.
ALLOWED = {
    "contract": set(),
    "engine": {"contract"},
    "making": {"engine", "contract"},
    "service": {"engine", "contract"},
    "sdk": {"contract", "engine"},  # engine: only the embedded backend, on first use
    "simulator": {"sdk", "contract"},
    "adapters": {"sdk"},
    "tooling": {"service", "contract"},
    "bench": {"making", "engine", "sdk", "contract", "tooling"},
    "views": {"making", "engine", "sdk", "simulator", "contract", "tooling"},
    "cli": {"bench", "views", "making", "engine", "service", "sdk", "simulator", "contract",
            "tooling"},
}


def modules() -> dict[str, Path]:
    """Every module of the project's packages by dotted name."""
    found = {}
    for package, folder in PACKAGES.items():
        for path in sorted((ROOT / folder / package).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = path
    return found


def imports_of(name: str, path: Path) -> list[tuple[str, str | None, int]]:
    """``(module, imported name or None, line)`` for every import in the file, relative ones
    resolved; a ``from m import x`` also yields ``m.x`` (x may be a module)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(alias.name, None, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            for alias in node.names:
                out.append((module, alias.name, node.lineno))
    return out


def layer_of(module: str) -> str | None:
    best = None
    for prefix in LAYERS:
        if (module == prefix or module.startswith(prefix + ".")) and (best is None or len(prefix) > len(best)):
            best = prefix
    return None if best is None else LAYERS[best]


def project_edges():
    """``(importer, imported module, name, line)`` for imports of the project's own modules."""
    known = modules()
    for name, path in known.items():
        for module, imported, line in imports_of(name, path):
            if module.split(".")[0] in PACKAGES:
                yield name, module, imported, line


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` (node -> successors) as a list of nodes, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for succ in sorted(graph.get(node, ())):
            if state.get(succ) == 1:
                return stack[stack.index(succ):] + [succ]
            if succ not in state:
                cycle = visit(succ)
                if cycle:
                    return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def test_every_module_has_a_layer():
    assert [m for m in modules() if layer_of(m) is None] == []


def test_imports_go_down_the_layer_diagram():
    wrong = []
    for importer, module, _, line in project_edges():
        source, target = layer_of(importer), layer_of(module)
        if source != target and target not in ALLOWED[source]:
            wrong.append(f"{importer}:{line} ({source}) imports {module} ({target})")
    assert wrong == []


@pytest.mark.parametrize("level", ["layer", "package"])
def test_no_cycle(level):
    key = layer_of if level == "layer" else (lambda module: module.split(".")[0])
    graph: dict[str, set[str]] = {}
    for importer, module, _, _ in project_edges():
        if key(importer) != key(module):
            graph.setdefault(key(importer), set()).add(key(module))
    assert find_cycle(graph) is None
    assert find_cycle(ALLOWED) is None  # the diagram itself is a DAG


def test_no_package_reaches_into_another_packages_private_parts():
    wrong = []
    for importer, module, imported, line in project_edges():
        if importer.split(".")[0] == module.split(".")[0]:
            continue
        private = [part for part in module.split(".") + [imported or ""]
                   if part.startswith("_") and not part.startswith("__")]
        if private:
            wrong.append(f"{importer}:{line} imports {module}{'.' + imported if imported else ''}")
    assert wrong == []


def test_the_checks_see_a_violation():
    """The graph checks find a planted cycle, and the private-part rule reads underscores."""
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
    assert layer_of("collider_cli.views.page") == "views" and layer_of("collider_cli.main") == "cli"
    assert layer_of("collider_client._embedded") == "sdk"
    assert layer_of("somebody_else") is None
