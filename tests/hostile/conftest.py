"""Fixtures of the hostile-input suite: the fork server every case runs in, the data it edits copies of, and the
``hostile`` marker's default deselection.

The small form (unmarked cases) runs in the default test run; the large form is marked ``hostile`` and runs only
when the marker expression names it::

    pytest -m hostile tests/hostile

``python tests/hostile/hostile_table.py`` runs the large form and rewrites the table in
docs/reference/hostile-inputs.md.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from hostile_harness import ForkServer
from hostile_inputs import NUSCENES, SCENE


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Leave out the large form (``hostile`` cases) unless ``-m`` names the marker."""
    if "hostile" in (config.option.markexpr or ""):
        return
    kept, dropped = [], []
    for item in items:
        (dropped if item.get_closest_marker("hostile") else kept).append(item)
    if dropped:
        config.hook.pytest_deselected(items=dropped)
        items[:] = kept


@pytest.fixture(scope="session")
def fork_server() -> Iterator[ForkServer]:
    """One fork server for the session (imports torch and the CLI once)."""
    server = ForkServer().start()
    try:
        yield server
    finally:
        server.stop()
        shutil.rmtree(server.scratch, ignore_errors=True)


@pytest.fixture(scope="session")
def nuscenes_root() -> Path:
    """The real nuscenes_pred folder (skips when absent)."""
    if not (NUSCENES / "label" / "val" / f"{SCENE}.txt").is_file():
        pytest.skip(f"real data not found under {NUSCENES} (set TRAFFICRLHF_DATA to the shared data folder)")
    return NUSCENES


@pytest.fixture
def workdir(tmp_path: Path) -> Path:
    """The folder a case runs in (its relative paths land there)."""
    path = tmp_path / "cwd"
    path.mkdir()
    os.chmod(path, 0o755)
    return path
