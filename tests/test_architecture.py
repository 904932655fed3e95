"""The layout is the architecture (docs/architecture.md), and this file checks what that page says.

The page's table is read here: its "may import" column (the layers a layer may import before the
semicolon, the third-party distributions after it, "(embedded only)" limiting one to the SDK's
embedded backend) is the rule, and every module of the four packages must be named in its
layer's row. Every import counts: at module level or inside functions, relative ones, and
``importlib.import_module(...)`` / ``__import__(...)`` whose name the source spells out (a
literal, or a loop over a module-level list of literals); a dynamic import whose name cannot be
read is itself a violation. No two layers or packages import each other, and no package reaches
into another's private (underscore) modules or names.

The checks run on sources (:func:`violations`), so the tests at the end plant breaks into copies
of the real sources and see each reported.
"""

from __future__ import annotations

import ast
import functools
import importlib
import importlib.metadata
import re
import sys
from pathlib import Path
from typing import NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "architecture.md"
PACKAGES = {"collider_contract": "client", "collider_client": "client",
            "collider_server": "server", "collider_cli": "server"}

#: Layer of a module: the longest prefix listed here wins. The page's rows name the same modules
#: (:func:`test_every_module_is_named_in_its_layers_row` holds the two together).
LAYERS = {
    "collider_contract": "contract",
    "collider_server": "engine",  # the package root re-exports the engine's public names
    "collider_server.engine": "engine",
    "collider_server.making": "making",
    "collider_server.service": "service",
    "collider_server.service.batching": "batcher",
    "collider_client": "sdk",
    "collider_client.sim": "simulator",
    "collider_client.adapters": "adapters",
    "collider_cli.launch": "tooling",
    "collider_cli.net": "tooling",
    "collider_cli": "cli",
    "collider_cli.bench": "bench",
    "collider_cli.views": "views",
}

#: The modules a "(NAME only)" of the page's "may import" column stands for.
ONLY = {"embedded": {"collider_client._embedded"}}

DYNAMIC_IMPORTS = {"import_module", "__import__"}


class Source(NamedTuple):
    path: Path
    text: str


class Import(NamedTuple):
    module: str | None  # None: a dynamic import whose name the source does not spell out
    name: str | None  # the x of ``from module import x``
    line: int


class Rule(NamedTuple):
    """A layer's "may import" cell: layers and distributions, each either allowed to the whole
    layer (None) or only to the listed modules."""

    layers: dict[str, set[str] | None]
    libraries: dict[str, set[str] | None]


# -- reading the sources -------------------------------------------------------------------


def sources() -> dict[str, Source]:
    """Every module of the project's packages by dotted name."""
    found = {}
    for package, folder in PACKAGES.items():
        for path in sorted((ROOT / folder / package).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = Source(path, path.read_text())
    return found


def _strings(node: ast.AST) -> list[str] | None:
    """The strings of a literal str, or of a list / tuple / set of them; None otherwise."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value]
    if isinstance(node, (ast.List, ast.Tuple, ast.Set)):
        items = [_strings(item) for item in node.elts]
        if all(item is not None and len(item) == 1 for item in items):
            return [item[0] for item in items]
    return None


def _literal_names(tree: ast.Module) -> dict[str, list[str]]:
    """Names the source binds to literal strings: module-level ``NAMES = ["a", "b"]`` and the
    targets of loops over them (``for name in NAMES``) or over literal lists."""
    constants: dict[str, list[str]] = {}
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, ast.AnnAssign) and node.value else [])
        for target in targets:
            values = _strings(node.value)
            if isinstance(target, ast.Name) and values is not None:
                constants[target.id] = values
    loops = dict(constants)
    for node in ast.walk(tree):
        if isinstance(node, (ast.For, ast.comprehension)) and isinstance(node.target, ast.Name):
            values = (constants.get(node.iter.id) if isinstance(node.iter, ast.Name)
                      else _strings(node.iter))
            if values is not None:
                loops.setdefault(node.target.id, []).extend(values)
    return loops


def _absolute(module: str, package: str, level: int) -> str:
    """``module`` imported ``level`` dots below ``package``, as an absolute name."""
    base = package.split(".")
    base = base[:len(base) - level + 1]
    return ".".join(base + ([module] if module else []))


@functools.cache
def imports_of(name: str, source: Source) -> list[Import]:
    """Every import in the module's source, relative ones resolved; a ``from m import x`` yields
    ``(m, x)`` (x may be a module), a dynamic import ``(module or None, None)``."""
    package = name if source.path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(source.text, str(source.path))
    literal = _literal_names(tree)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [Import(alias.name, None, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = _absolute(node.module, package, node.level) if node.level else node.module
            out += [Import(module, alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.Call):
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if called not in DYNAMIC_IMPORTS:
                continue
            first = node.args[0] if node.args else None
            names = (_strings(first) if not isinstance(first, ast.Name) else literal.get(first.id))
            if not names:
                out.append(Import(None, None, node.lineno))
                continue
            for module in names:
                dots = len(module) - len(module.lstrip("."))
                out.append(Import(_absolute(module[dots:], package, dots) if dots else module,
                                  None, node.lineno))
    return out


def layer_of(module: str) -> str | None:
    best = None
    for prefix in LAYERS:
        if (module == prefix or module.startswith(prefix + ".")) and (best is None or len(prefix) > len(best)):
            best = prefix
    return None if best is None else LAYERS[best]


# -- reading the page ----------------------------------------------------------------------


def table(text: str) -> dict[str, list[str]]:
    """The rows of the page's layer table: layer (lower case) -> its cells."""
    rows = {}
    for line in text.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) == 4 and cells[0] not in ("layer", "---"):
            rows[cells[0].lower()] = cells
    return rows


def _distribution(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def rules(text: str) -> dict[str, Rule]:
    """Each layer's "may import" cell, read: ``layers; distributions``, each item optionally
    followed by a parenthesis; "(NAME only)" limits the item to :data:`ONLY`'s modules of NAME,
    any other parenthesis is a comment; "every layer" is every other layer."""
    rows = table(text)
    out = {}
    for layer, cells in rows.items():
        rule = Rule({}, {})
        for item in re.split(r"[,;]", cells[3]):
            match = re.fullmatch(r"\s*([^()]+?)\s*(?:\((.*)\))?\s*", item)
            assert match, f"{PAGE.name}: cannot read {item!r} in the row of {layer}"
            what, note = match.group(1), match.group(2) or ""
            only = re.fullmatch(r"(\w+) only", note)
            modules = ONLY[only.group(1)] if only else None
            if what == "every layer":
                rule.layers.update({other: None for other in rows if other != layer})
            elif what.lower() in rows:
                rule.layers[what.lower()] = modules
            else:
                rule.libraries[_distribution(what)] = modules
        out[layer] = rule
    return out


@functools.cache
def _installed() -> dict[str, list[str]]:
    return importlib.metadata.packages_distributions()


def _distributions_of(top: str) -> list[str]:
    """The installed distributions that provide the import name ``top`` (itself when none is)."""
    return [_distribution(d) for d in _installed().get(top, [top])]


# -- the checks ------------------------------------------------------------------------------


def violations(found: dict[str, Source], text: str) -> list[str]:
    """Every import of ``found`` that breaks a rule of the page ``text``, one line each."""
    rule_of = rules(text)
    wrong = []
    for importer, source in found.items():
        layer = layer_of(importer)
        for module, imported, line in imports_of(importer, source):
            where = f"{importer}:{line} ({layer})"
            if module is None:
                wrong.append(f"{where}: a dynamic import whose module name is not in the source")
                continue
            top = module.split(".")[0]
            if top in PACKAGES:
                target = layer_of(module)
                allowed = rule_of[layer].layers
                if target != layer and (target not in allowed or (
                        allowed[target] is not None and importer not in allowed[target])):
                    wrong.append(f"{where} imports {module} ({target})")
                private = [part for part in module.split(".") + [imported or ""]
                           if part.startswith("_") and not part.startswith("__")]
                if top != importer.split(".")[0] and private:
                    wrong.append(f"{where} imports the private {module}"
                                 f"{'.' + imported if imported else ''}")
            elif top not in sys.stdlib_module_names:
                libraries = rule_of[layer].libraries
                names = [d for d in _distributions_of(top) if d in libraries]
                if not names or all(libraries[d] is not None and importer not in libraries[d]
                                    for d in names):
                    wrong.append(f"{where} imports {module} (third-party {', '.join(_distributions_of(top))})")
    return wrong


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


def unnamed_modules(found: dict[str, Source], text: str) -> list[str]:
    """Modules no backticked path of their layer's row names: ``wire.py``, ``kinds/neural.py``
    or the full path for a module; its folder (``kinds/``) for a package's ``__init__.py``."""
    rows = table(text)
    missing = []
    for name, source in found.items():
        path = source.path.relative_to(ROOT).as_posix()
        if source.path.name == "__init__.py":
            path = path.removesuffix("__init__.py")
        tokens = re.findall(r"`([^`]+)`", " ".join(rows.get(layer_of(name), [])))
        if not any(path == token or path.endswith("/" + token) for token in tokens):
            missing.append(f"{name} ({path}) in the row of {layer_of(name)}")
    return missing


# -- the tests on the real sources -------------------------------------------------------------


@pytest.fixture(scope="module")
def found() -> dict[str, Source]:
    return sources()


@pytest.fixture(scope="module")
def page() -> str:
    return PAGE.read_text()


def test_every_module_has_a_layer_and_every_layer_a_row(found, page):
    assert [m for m in found if layer_of(m) is None] == []
    assert set(table(page)) == set(LAYERS.values())


def test_every_import_follows_the_pages_may_import_column(found, page):
    assert violations(found, page) == []


def test_every_module_is_named_in_its_layers_row(found, page):
    assert unnamed_modules(found, page) == []


@pytest.mark.parametrize("level", ["layer", "package"])
def test_no_cycle(found, page, level):
    key = layer_of if level == "layer" else (lambda module: module.split(".")[0])
    graph: dict[str, set[str]] = {}
    for importer, source in found.items():
        for module, _, _ in imports_of(importer, source):
            if module and module.split(".")[0] in PACKAGES and key(importer) != key(module):
                graph.setdefault(key(importer), set()).add(key(module))
    assert find_cycle(graph) is None
    # The page's column is a DAG itself.
    assert find_cycle({layer: set(rule.layers) for layer, rule in rules(page).items()}) is None


def test_the_cli_registers_its_commands_through_imports_the_checker_reads(found):
    """``collider_cli.main`` imports each command module with ``importlib.import_module`` over a
    list of names: the checker sees those imports."""
    seen = {module for module, _, _ in imports_of("collider_cli.main", found["collider_cli.main"])}
    assert {"collider_cli.commands.models", "collider_cli.commands.serve"} <= seen


def engine_names_outside_all(found: dict[str, Source]) -> list[str]:
    """The embedded backend's engine imports that are not ``from collider_server.engine import
    NAME`` with NAME in ``engine.__all__``: it uses the engine's exported API only, as the
    service's twin (docs/architecture.md)."""
    exported = set(importlib.import_module("collider_server.engine").__all__)
    module = "collider_client._embedded"
    return [f"{module}:{line} imports {imported_from}{'.' + name if name else ''}"
            for imported_from, name, line in imports_of(module, found[module])
            if imported_from and layer_of(imported_from) == "engine"
            and (imported_from != "collider_server.engine" or name not in exported)]


def test_the_embedded_backend_imports_only_what_the_engine_exports(found):
    assert engine_names_outside_all(found) == []
    broken = planted(found, "collider_client._embedded",
                     "def _planted():\n    from collider_server.engine.devices import device_of  # planted")
    line = len(broken["collider_client._embedded"].text.splitlines())
    assert engine_names_outside_all(broken) == [
        f"collider_client._embedded:{line} imports collider_server.engine.devices.device_of"]


# -- the checker catches planted breaks -------------------------------------------------------


def planted(found: dict[str, Source], module: str, code: str) -> dict[str, Source]:
    """A copy of ``found`` with ``code`` appended to ``module``'s source."""
    copy = dict(found)
    copy[module] = Source(found[module].path, found[module].text + "\n\n" + code + "\n")
    return copy


#: A planted break: (module, code appended to it, the start of the report it must make). The
#: line marked ``# planted`` is the one the report names.
PLANTED = {
    "a lazy engine import in the collision response": (
        "collider_client.response",
        "def _planted():\n    from collider_server.engine import collider  # planted\n    return collider",
        "collider_client.response:{line} (sdk) imports collider_server.engine (engine)"),
    "the service imported through importlib in the contract": (
        "collider_contract.answers",
        'import importlib\n\n_app = importlib.import_module("collider_server.service.app")  # planted',
        "collider_contract.answers:{line} (contract) imports collider_server.service.app (service)"),
    "torch in the contract": (
        "collider_contract.wire", "import torch  # planted",
        "collider_contract.wire:{line} (contract) imports torch (third-party torch)"),
    "__import__ of the engine in the simulator": (
        "collider_client.sim.run", 'engine = __import__("collider_server.engine")  # planted',
        "collider_client.sim.run:{line} (simulator) imports collider_server.engine (engine)"),
    "a relative dynamic import of the service in the engine": (
        "collider_server.engine.collider",
        'import importlib\n\n_app = importlib.import_module("..service.app", __package__)  # planted',
        "collider_server.engine.collider:{line} (engine) imports collider_server.service.app (service)"),
    "an HTTP library in the batcher": (
        "collider_server.service.batching", "def _planted():\n    import starlette.requests  # planted",
        "collider_server.service.batching:{line} (batcher) imports starlette.requests"),
    "FastAPI in the engine": (
        "collider_server.engine.collider", "from fastapi import HTTPException  # planted",
        "collider_server.engine.collider:{line} (engine) imports fastapi (third-party fastapi)"),
    "httpx in the engine, through importlib": (
        "collider_server.engine.repository", 'import importlib\n\nimportlib.import_module("httpx")  # planted',
        "collider_server.engine.repository:{line} (engine) imports httpx (third-party httpx)"),
    "torch in the SDK outside the embedded backend": (
        "collider_client._client", "def _planted():\n    import torch  # planted",
        "collider_client._client:{line} (sdk) imports torch"),
    "the engine in the SDK's client module": (
        "collider_client._client", "from collider_server.engine.repository import ModelRepository  # planted",
        "collider_client._client:{line} (sdk) imports collider_server.engine.repository (engine)"),
    "a dynamic import whose name is computed": (
        "collider_client.sim.scene",
        'import importlib\n\n_m = importlib.import_module("collider_" + "server")  # planted',
        "collider_client.sim.scene:{line} (simulator): a dynamic import whose module name"),
    "a private module of another package": (
        "collider_cli.commands.models", "from collider_client._base import refusal  # planted",
        "collider_cli.commands.models:{line} (cli) imports the private collider_client._base.refusal"),
}


@pytest.mark.parametrize("case", PLANTED, ids=list(PLANTED))
def test_a_planted_break_is_reported(found, page, case):
    module, code, expected = PLANTED[case]
    broken = planted(found, module, code)
    line = 1 + next(i for i, text in enumerate(broken[module].text.splitlines()) if "# planted" in text)
    reported = violations(broken, page)
    assert any(r.startswith(expected.format(line=line)) for r in reported), reported


def test_the_embedded_backend_may_import_the_engine_and_torch(found, page):
    """The "(embedded only)" rows allow exactly the embedded backend: the same lazy import in
    ``_embedded.py`` is no violation."""
    code = "def _planted():\n    import torch\n    from collider_server.engine import collider\n"
    assert violations(planted(found, "collider_client._embedded", code), page) == []


def test_a_module_missing_from_the_table_is_reported(found, page):
    path = ROOT / "server" / "collider_server" / "engine" / "kinds" / "planted.py"
    missing = unnamed_modules({**found, "collider_server.engine.kinds.planted": Source(path, "")}, page)
    row = "collider_server.engine.kinds.planted (server/collider_server/engine/kinds/planted.py) in the row of engine"
    assert missing == [row]


def test_the_graph_checks_see_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
    assert layer_of("collider_cli.views.page") == "views" and layer_of("collider_cli.main") == "cli"
    assert layer_of("collider_client._embedded") == "sdk"
    assert layer_of("somebody_else") is None


# -- the packages' public names ---------------------------------------------------------------


def _defines_all(source: Source) -> bool:
    return any(isinstance(node, (ast.Assign, ast.AnnAssign)) and any(
        isinstance(target, ast.Name) and target.id == "__all__"
        for target in (node.targets if isinstance(node, ast.Assign) else [node.target]))
        for node in ast.parse(source.text).body)


def test_the_four_packages_declare_their_public_names(found):
    with_all = [name for name, source in found.items() if _defines_all(source)]
    assert {"collider_contract", "collider_client", "collider_server", "collider_cli"} <= set(with_all)


@pytest.mark.parametrize("module", [name for name, source in sources().items() if _defines_all(source)])
def test_star_import_gives_exactly_all(module):
    """``from MODULE import *`` works for every module with an ``__all__`` (every name it lists
    is defined or imported there), and gives those names, each once."""
    namespace: dict = {}
    exec(f"from {module} import *", namespace)  # noqa: S102 (the module is one of this project's)
    listed = importlib.import_module(module).__all__
    assert len(listed) == len(set(listed))
    assert set(namespace) - {"__builtins__"} == set(listed)
