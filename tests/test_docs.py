"""Documentation stays in step with the code and free of development history."""

from __future__ import annotations

import ast
import importlib
import os
import pkgutil
import re
import subprocess

import pytest

import trafficrlhf_sdk
from trafficrlhf_sdk.plugins import get_plugin_manager

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = os.path.join(ROOT, "docs")
REFERENCE = os.path.join(DOCS, "reference")


def _hook_names() -> list[str]:
    return sorted(name for name in dir(get_plugin_manager().hook) if name.startswith("register_"))


@pytest.mark.parametrize("hook", _hook_names())
def test_plugin_hook_is_documented(hook: str) -> None:
    """Every hook has a heading with its signature in docs/reference/plugin_hooks.md."""
    with open(os.path.join(REFERENCE, "plugin_hooks.md"), encoding="utf-8") as f:
        text = f.read()
    assert re.search(rf"^## {hook}\((register|cli)\)$", text, re.M), f"document {hook} in plugin_hooks.md"


def test_doc_links_resolve() -> None:
    """Relative links between docs pages point at files that exist."""
    broken = []
    for folder, _, files in os.walk(DOCS):
        for name in files:
            if not name.endswith(".md"):
                continue
            with open(os.path.join(folder, name), encoding="utf-8") as f:
                text = f.read()
            for target in re.findall(r"\]\(([^)#:]+\.md)", text):
                if not os.path.exists(os.path.normpath(os.path.join(folder, target))):
                    broken.append(f"{name} -> {target}")
    assert not broken, broken


def test_readme_is_short() -> None:
    """The README is a front door, not a manual: at most 150 lines."""
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        lines = f.read().splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines; move detail into docs/"


def test_readme_links_resolve() -> None:
    """Relative links in the README point at files that exist."""
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        text = f.read()
    missing = [t for t in re.findall(r"\]\((?![a-z]+:)([^)#\s]+)", text) if not os.path.exists(os.path.join(ROOT, t))]
    assert not missing, missing


SESSION = re.compile(r"[Ss]ession [0-9]+")


def test_no_development_history_in_tracked_files() -> None:
    """No tracked file speaks of work sessions (the word followed by a number): history lives in git, not in the
    product."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    hits = []
    for path in listed.stdout.decode("utf-8").split("\0"):
        if not path or path.endswith(".lock"):
            continue
        full = os.path.join(ROOT, path)
        if not os.path.isfile(full):
            continue  # deleted in the work tree
        with open(full, "rb") as f:
            data = f.read()
        if b"\0" in data[:8192]:
            continue  # binary
        text = data.decode("utf-8", errors="replace")
        for number, line in enumerate(text.splitlines(), 1):
            if SESSION.search(line):
                hits.append(f"{path}:{number}: {line.strip()[:100]}")
    assert not hits, f"{len(hits)} lines mention a session:\n" + "\n".join(hits[:50])


# --- the API reference covers every public name ------------------------------------------------------------------

def _core_packages() -> list[str]:
    """trafficrlhf_sdk and every subpackage of it."""
    names = ["trafficrlhf_sdk"]
    for info in pkgutil.walk_packages(trafficrlhf_sdk.__path__, "trafficrlhf_sdk."):
        if info.ispkg:
            names.append(info.name)
    return names


def _statically_bound(module_name: str) -> set[str]:
    """Names a module binds at its top level (defs, classes, assignments, imports): what a static documentation
    tool sees. Names offered only through a module ``__getattr__`` (lazy exports) are not among them."""
    module = importlib.import_module(module_name)
    path = getattr(module, "__file__", None)
    if not path or not path.endswith(".py"):
        return set()
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read())
    names: set[str] = set()

    def visit(body: list[ast.stmt]) -> None:
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names.add(node.name)
            elif isinstance(node, (ast.Import, ast.ImportFrom)):
                for alias in node.names:
                    names.add((alias.asname or alias.name).split(".")[0])
            elif isinstance(node, ast.Assign):
                for target in node.targets:
                    names.update(n.id for n in ast.walk(target) if isinstance(n, ast.Name))
            elif isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(node.target, ast.Name):
                names.add(node.target.id)
            elif isinstance(node, (ast.If, ast.Try)):
                visit(node.body)
                visit(getattr(node, "orelse", []))
                for handler in getattr(node, "handlers", []):
                    visit(handler.body)

    visit(tree.body)
    return names


_BLOCK = re.compile(r"^:::\s*([\w.]+)[ \t]*\n((?:[ \t]+.*\n|[ \t]*\n)*)", re.M)


def _block_members(options: str) -> list[str] | bool | None:
    """The ``members`` option of a mkdocstrings block: a list, False, or None when not set."""
    match = re.search(r"^\s+members:\s*(.*)$", options, re.M)
    if not match:
        return None
    value = match.group(1).strip()
    if value.lower() in ("false", "no", "[]"):
        return False
    if value.startswith("["):
        return [m.strip(" '\"") for m in value.strip("[]").split(",") if m.strip()]
    after = options[match.end():]
    return re.findall(r"^\s+-\s*([\w]+)\s*$", after.split("\n\n")[0], re.M)


def _documented(name: str, blocks: list[tuple[str, list[str] | bool | None]]) -> bool:
    """Whether a ``::: identifier`` block documents ``name``: a block for the object itself, or a block for a module
    that binds ``name`` statically and renders it (in its ``__all__``, or in the block's ``members`` list)."""
    for identifier, members in blocks:
        if identifier.rsplit(".", 1)[-1] == name:
            return True  # a block for the object (or submodule) itself
        try:
            module = importlib.import_module(identifier)
        except ImportError:
            continue
        if members is False:
            continue
        if isinstance(members, list):
            if name in members and name in _statically_bound(identifier):
                return True
            continue
        public = getattr(module, "__all__", None)
        if public is not None and name in public and name in _statically_bound(identifier):
            return True
        if public is None and not name.startswith("_") and name in _statically_bound(identifier):
            return True
    return False


def _reference_pages() -> dict[str, str]:
    pages = {}
    for name in sorted(os.listdir(REFERENCE)):
        if name.endswith(".md"):
            with open(os.path.join(REFERENCE, name), encoding="utf-8") as f:
                pages[name] = f.read()
    return pages


@pytest.mark.parametrize("package", _core_packages())
def test_public_names_are_in_the_api_reference(package: str) -> None:
    """Every name in the ``__all__`` of trafficrlhf_sdk and its subpackages is in docs/reference/: documented by a
    ``::: module`` block (mkdocstrings) or named in the text as `` `name` `` or an autoref ``[...][...name]``."""
    module = importlib.import_module(package)
    public = getattr(module, "__all__", None)
    if public is None:
        pytest.skip(f"{package} has no __all__")
    pages = _reference_pages()
    text = "\n".join(pages.values())
    blocks = [(m.group(1), _block_members(m.group(2))) for page in pages.values() for m in _BLOCK.finditer(page)]
    missing = []
    for name in public:
        mentioned = re.search(rf"`{re.escape(name)}`|\]\[[\w.]*\b{re.escape(name)}\]", text)
        if not mentioned and not _documented(name, blocks):
            missing.append(name)
    assert not missing, f"document in docs/reference/ (a ::: block or `name`): {package}: {missing}"


def test_reference_blocks_name_real_objects() -> None:
    """Every ``::: identifier`` in the reference imports (a module) or resolves (an attribute of one)."""
    bad = []
    for page, text in _reference_pages().items():
        for match in _BLOCK.finditer(text):
            identifier = match.group(1)
            try:
                importlib.import_module(identifier)
                continue
            except ImportError:
                pass
            parent, _, attribute = identifier.rpartition(".")
            try:
                getattr(importlib.import_module(parent), attribute)
            except (ImportError, AttributeError):
                bad.append(f"{page}: {identifier}")
    assert not bad, bad
