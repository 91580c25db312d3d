"""The import graph of the SDK, the adapters, the plugins and the reference models has no cycles, and no module
reaches for another package's private names.

The graph is read from the source with ``ast`` (nothing is imported): every ``import`` and ``from ... import``
counts, at module level, inside functions and under ``if TYPE_CHECKING:`` alike, since each is a dependency a
reader has to follow. Importing a module's own parent packages is not an edge (Python initialises them anyway).
"""

from __future__ import annotations

import ast
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = ("trafficrlhf_sdk", "adapters", "plugins", "reference_models")
SKIPPED_DIRS = {"tests", "__pycache__", "node_modules"}


def find_modules(root: Path, dirs: tuple[str, ...] = PACKAGE_DIRS) -> dict[str, Path]:
    """``{dotted module name: file}`` of every ``.py`` file under ``root/dirs`` (tests left out). A module is named
    from the outermost folder with an ``__init__.py`` (``adapters/ctg/trafficrlhf_ctg/x.py`` is
    ``trafficrlhf_ctg.x``)."""
    modules: dict[str, Path] = {}
    for top in dirs:
        for folder, subdirs, files in os.walk(root / top):
            subdirs[:] = [d for d in subdirs if d not in SKIPPED_DIRS and not d.startswith(".")
                          and not d.endswith(".egg-info")]
            for file in files:
                if not file.endswith(".py"):
                    continue
                parts = (Path(folder) / file).relative_to(root).with_suffix("").parts
                start = 0
                while start < len(parts) - 1 and not (root.joinpath(*parts[: start + 1]) / "__init__.py").exists():
                    start += 1
                name = ".".join(parts[start:]).removesuffix(".__init__")
                modules[name] = Path(folder) / file
    return modules


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _home(name: str, modules: dict[str, Path]) -> str:
    """The package a module belongs to (a package's ``__init__`` belongs to the package itself)."""
    return name if _is_package(modules[name]) else name.rpartition(".")[0]


def imported_names(name: str, modules: dict[str, Path]) -> Iterator[tuple[str, str | None, int]]:
    """``(target module path, imported name or None, line)`` of every import in module ``name``, relative imports
    resolved."""
    tree = ast.parse(modules[name].read_text(encoding="utf-8"))
    home = _home(name, modules).split(".")
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, None, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = home[: len(home) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                yield target, alias.name, node.lineno


def _known(dotted: str, modules: dict[str, Path]) -> str | None:
    """The longest known module that ``dotted`` starts with."""
    while dotted and dotted not in modules:
        dotted = dotted.rpartition(".")[0]
    return dotted or None


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """``{module: modules it imports}`` among ``modules``, edges to the module's own parent packages left out."""
    graph: dict[str, set[str]] = {}
    for name in modules:
        edges = set()
        for target, imported, _ in imported_names(name, modules):
            for dotted in (target, f"{target}.{imported}" if imported else None):
                found = _known(dotted, modules) if dotted else None
                if found and found != name and not name.startswith(found + "."):
                    edges.add(found)
        graph[name] = edges
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted; every import cycle lies
    in one."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def _private(part: str) -> bool:
    return part.startswith("_") and not part.startswith("__")


def private_imports(modules: dict[str, Path]) -> list[str]:
    """``"module:line imports package.name"`` for every import of a private name (``_x``, or any name in a private
    module ``_m``) that belongs to another package than the importer's."""
    found = []
    for name in modules:
        home = _home(name, modules)
        for target, imported, line in imported_names(name, modules):
            dotted = f"{target}.{imported}" if imported else target
            module = _known(target, modules)
            if module is None:
                continue  # a third-party module
            parts = dotted.split(".")
            for depth, part in enumerate(parts):
                if not _private(part):
                    continue
                owner = ".".join(parts[:depth])
                if depth == len(parts) - 1 and imported is not None and dotted not in modules:
                    owner = _home(module, modules)  # a private name defined in module `target`
                if home != owner:
                    found.append(f"{name}:{line} imports {dotted} (private to {owner})")
                break
    return sorted(found)


def _describe(graph: dict[str, set[str]], cycle: list[str]) -> str:
    """The component, and one loop through it (``a -> b -> a``), so the imports to move are named."""
    members = set(cycle)
    path, seen = [cycle[0]], {cycle[0]}
    while True:
        nxt = sorted(graph[path[-1]] & members)
        step = next((m for m in nxt if m == cycle[0]), None) if len(path) > 1 else None
        if step is not None or not nxt:
            path.append(cycle[0])
            break
        unvisited = [m for m in nxt if m not in seen]
        if not unvisited:
            path.append(nxt[0])
            break
        path.append(unvisited[0])
        seen.add(unvisited[0])
    return " <-> ".join(cycle) + "   (e.g. " + " -> ".join(path) + ")"


def test_the_import_graph_has_no_cycles() -> None:
    modules = find_modules(ROOT)
    assert "trafficrlhf_sdk.scenario.tensor" in modules and "trafficrlhf_ctg" in modules  # the graph was read
    graph = import_graph(modules)
    cycles = find_cycles(graph)
    assert not cycles, "import cycles (move the code to the lower stage it belongs to):\n" + "\n".join(
        _describe(graph, c) for c in cycles)


def test_no_module_imports_another_packages_private_names() -> None:
    found = private_imports(find_modules(ROOT))
    assert not found, "private names imported across packages (make them public, or move the code):\n" + \
        "\n".join(found)


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")


def test_the_checks_catch_a_cycle_and_a_private_import(tmp_path: Path) -> None:
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "from pkg.b import thing\n",
        "pkg/b.py": "def f():\n    from pkg import c\n",  # a function-level import still counts
        "pkg/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.a import x\n",
        "pkg/d.py": "from . import e\nfrom pkg import e as again\n",
        "pkg/e.py": "import pkg\n",  # the module's own parent package: no edge
        "pkg/sub/__init__.py": "from pkg.e import _hidden\nfrom pkg.sub.f import _ok\n",
        "pkg/sub/f.py": "from .._private_mod import x\n",
        "pkg/_private_mod.py": "",
    })
    modules = find_modules(tmp_path, ("pkg",))
    graph = import_graph(modules)
    assert find_cycles(graph) == [["pkg.a", "pkg.b", "pkg.c"]]
    assert "pkg.a -> pkg.b -> pkg.c -> pkg.a" in _describe(graph, ["pkg.a", "pkg.b", "pkg.c"])
    assert graph["pkg.d"] == {"pkg.e"} and graph["pkg.e"] == set()
    found = private_imports(modules)
    assert len(found) == 2, found
    assert found[0].startswith("pkg.sub.f:1 imports pkg._private_mod.x (private to pkg)")
    assert found[1].startswith("pkg.sub:1 imports pkg.e._hidden (private to pkg)")


@pytest.mark.parametrize("name", ["trafficrlhf_sdk.scenario.io", "trafficrlhf_sdk.reward.serialization",
                                  "trafficrlhf_sdk.parallel", "ctg_reference.networks"])
def test_lower_stages_import_nothing_above_them(name: str) -> None:
    """The modules that used to close a cycle stay below the ones that use them."""
    modules = find_modules(ROOT)
    graph = import_graph(modules)
    above = {"trafficrlhf_sdk.scenario.io": "trafficrlhf_sdk.scenario.tensor",
             "trafficrlhf_sdk.reward.serialization": "trafficrlhf_sdk.reward.model",
             "trafficrlhf_sdk.parallel": "trafficrlhf_sdk.feedback.campaign",
             "ctg_reference.networks": "ctg_reference.model"}[name]
    assert above not in graph[name] and name in graph[above]


def test_no_module_inside_the_sdk_imports_the_package_root() -> None:
    """Inside the SDK, names come from the module that defines them (``trafficrlhf_sdk.plugins``, ``.version``),
    never from ``trafficrlhf_sdk`` itself, whose face imports the stages: that edge would be a hidden cycle."""
    modules = find_modules(ROOT, ("trafficrlhf_sdk",))
    found = [f"{name}:{line} imports {target}{'.' + imported if imported else ''}"
             for name in modules if name != "trafficrlhf_sdk"
             for target, imported, line in imported_names(name, modules) if target == "trafficrlhf_sdk"]
    assert not found, "import these from their own module:\n" + "\n".join(sorted(found))
