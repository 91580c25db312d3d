"""The iterative RLHF loop (trafficrlhf_sdk.loop) on real scenes: rounds, active selection, and a rerun that finds
every step done. Resuming after an interruption and refusing changed settings are tested without data in
tests/test_pipeline.py."""

from __future__ import annotations

import json
import os

import pytest

from trafficrlhf_sdk.loop import RLHFConfig, rlhf
from trafficrlhf_sdk.pipeline import read_manifest
from trafficrlhf_sdk.reward.contrast import PERTURBATIONS

pytest.importorskip("trafficrlhf_example_gru")
pytestmark = pytest.mark.data

SMALL = dict(model="example_gru", guidance=None, rounds=2, seed=0, contexts_per_round=2, candidate_pool=2, candidates=3,
             seconds=2.0, annotators=["attentive", "hurried"], contrast_scenes=3, probe_scenes=2,
             reward={"ensemble_size": 2, "max_epochs": 1, "batch_size": 2,
                     "architecture_config": {"hidden_sizes": [16, 8], "crop_size": 8}},
             align={"epochs": 1, "contexts_per_epoch": 2, "samples_per_context": 2, "num_scenes": 4})


def test_two_rounds_with_active_selection_then_a_rerun_does_nothing(data_root: str, tmp_path) -> None:
    config = RLHFConfig(**SMALL)
    out = str(tmp_path / "run")
    result = rlhf(config, out, log=lambda line: None)
    for r, entry in enumerate(result["rounds"]):
        assert os.path.isfile(os.path.join(entry["reward_model"], "model.safetensors"))
        assert os.path.isfile(os.path.join(entry["aligned"], "model.safetensors"))
        assert set(entry["probes"]) == set(PERTURBATIONS)
        assert entry["campaigns"] == [f"round{r}"]  # no guidance: one campaign per round
    assert read_manifest(os.path.join(out, "round_1", "rank"))["outputs"]["ranked"] == {"round1": 4}  # type: ignore
    # round 1's candidates come from round 0's aligned model, and its reward model saw both rounds' labels
    from trafficrlhf_sdk.feedback.store import FeedbackStore

    store = FeedbackStore(os.path.join(out, "feedback.sqlite"))
    assert len(store.context_keys(store.campaign("round1"))) == 4  # the pool: 2 x contexts_per_round
    assert len({lab.context_id for lab in store.labels(store.campaign("round1"))}) == 2  # the chosen ones
    assert store.campaign("round1").config["model_options"] == {"checkpoint": result["rounds"][0]["aligned"]}
    store.close()
    card = json.load(open(os.path.join(out, "round_1", "reward_model", "config.json")))
    assert card["data"]["campaign"] == ["round0", "round1"]
    assert card["data"]["contrast"]["decided_by"] == ["attentive", "hurried"]  # the stand-ins label the contrast
    assert card["data"]["contrast"]["scenes"] == 3 and card["data"]["contrast"]["pairs"] > 0
    lines: list[str] = []
    assert rlhf(config, out, log=lines.append) == result
    assert lines and all(line.endswith("skipped") for line in lines)  # every step was done


@pytest.mark.parametrize(("fields", "judged"), [
    ({"contrast_scenes": 5}, True),
    ({"contrast_scenes": 5, "contrast_labels": "log"}, False),
    ({"contrast_scenes": 5, "people": True}, False),
    ({"contrast_scenes": 0}, False),
])
def test_the_stand_ins_label_contrast_items_unless_told_the_log_wins(fields: dict, judged: bool) -> None:
    from trafficrlhf_sdk.loop import _judged_contrast

    assert _judged_contrast(RLHFConfig(model="ctg", **fields)) is judged
