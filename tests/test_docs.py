"""Documentation stays in step with the code (datasette's pattern)."""

from __future__ import annotations

import os
import re

import pytest

from trafficrlhf_sdk.plugins import get_plugin_manager

DOCS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs")


def _hook_names() -> list[str]:
    return sorted(name for name in dir(get_plugin_manager().hook) if name.startswith("register_"))


@pytest.mark.parametrize("hook", _hook_names())
def test_plugin_hook_is_documented(hook: str) -> None:
    """Every hook has a heading with its signature in docs/reference/plugin_hooks.md."""
    with open(os.path.join(DOCS, "reference", "plugin_hooks.md"), encoding="utf-8") as f:
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
