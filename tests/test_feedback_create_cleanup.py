"""A failed ``feedback create`` leaves nothing behind (``feedback.store.open_store``)."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from trafficrlhf_sdk.cli import get_cli
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.feedback.store import FeedbackStore, open_store


def test_a_mistyped_model_leaves_no_database(data_root: str, tmp_path: Path) -> None:
    db = tmp_path / "feedback.db"
    result = CliRunner().invoke(get_cli(), ["feedback", "create", "--db", str(db), "--name", "c", "--model", "ctgg",
                                            "--scenes", "1"])
    assert result.exit_code != 0 and "ctgg" in str(result.exception)
    assert not any(tmp_path.iterdir()), sorted(p.name for p in tmp_path.iterdir())


def test_open_store_removes_only_a_database_it_created(tmp_path: Path) -> None:
    fresh = tmp_path / "fresh.db"
    with pytest.raises(RuntimeError), open_store(fresh):
        raise RuntimeError("boom")
    assert not any(tmp_path.iterdir())
    kept = tmp_path / "kept.db"
    FeedbackStore(kept).close()
    with pytest.raises(RuntimeError), open_store(kept):
        raise RuntimeError("boom")
    assert kept.is_file()
    with pytest.raises(TrafficRLHFError, match="does not exist"):
        with open_store(tmp_path / "missing.db", must_exist=True):
            pass
