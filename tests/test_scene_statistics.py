"""Scene statistics of a source from Python (``trafficrlhf_sdk.scenario.statistics``; ``inspect`` prints them)."""

from __future__ import annotations

import os

import pytest

from trafficrlhf_sdk.scenario import default_data_root


def test_inspect_source_counts_what_it_loaded() -> None:
    if not os.path.isdir(os.path.join(default_data_root(), "nuscenes_pred", "label")):
        pytest.skip(f"nuscenes_pred not found under {default_data_root()!r}")
    from trafficrlhf_sdk import get_scenario_source
    from trafficrlhf_sdk.scenario import inspect_source, scene_statistics

    source = get_scenario_source("nuscenes_pred")
    report = inspect_source(source, "val", num_scenes=2)
    ids = source.scene_ids("val")
    assert report["scenes"]["loaded"] == 2 and report["scenes"]["long_enough"] == len(ids)
    assert report["scene_ids"] == ids[:2] and report["dt_s"] == [0.1]
    batch = source.load_batch("val", 2)
    stats = scene_statistics([batch])  # one batch of two scenes counts as two scenes
    assert stats["scenes_loaded"] == 2
    assert stats["agents"]["total"] == report["agents"]["total"] == int(batch.valid.any(-1).sum())
    assert sum(stats["agent_types"].values()) == stats["agents"]["total"]
