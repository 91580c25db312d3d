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
        assert all(0 <= probe["judges"] <= 1 for probe in entry["probes"].values())  # the stand-ins took them too
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


@pytest.mark.parametrize(("scenes", "start", "count"),
                         [(5, 0, 3), (5, 0, 5), (5, 0, 12), (5, 3, 4), (5, 7, 9), (1, 0, 3)])
def test_passes_take_scenes_in_order_and_never_repeat_one_within_a_pass(scenes: int, start: int, count: int) -> None:
    from trafficrlhf_sdk.loop import _passes

    train = [f"s{i}" for i in range(scenes)]
    passes = _passes(train, start, count)
    flat = [scene for part in passes for scene in part]
    assert flat == [train[(start + i) % scenes] for i in range(count)]  # in order, wrapping round
    assert all(len(set(part)) == len(part) for part in passes)  # no scene twice within a campaign
    assert len(passes) == -(-((start % scenes) + count) // scenes)  # a new pass exactly at each wrap


def test_passes_refuse_an_empty_split() -> None:
    from trafficrlhf_sdk.errors import TrafficRLHFError
    from trafficrlhf_sdk.loop import _passes

    with pytest.raises(TrafficRLHFError, match="no scene left"):
        _passes([], 0, 3)


def test_a_round_labels_more_contexts_than_there_are_scenes(data_root: str, tmp_path, monkeypatch) -> None:
    from trafficrlhf_nuscenes_pred.source import NuScenesPredSource
    from trafficrlhf_sdk.feedback.store import FeedbackStore

    listed = NuScenesPredSource.scene_ids
    monkeypatch.setattr(NuScenesPredSource, "scene_ids", lambda self, split: listed(self, split)[:3])  # 3 scenes
    scenes = NuScenesPredSource(root=os.path.join(data_root, "nuscenes_pred")).scene_ids("train")
    config = RLHFConfig(**{**SMALL, "rounds": 1, "contexts_per_round": len(scenes) + 2, "contrast_scenes": 0,
                           "probe_scenes": 0, "annotators": ["attentive"],
                           "reward": {**SMALL["reward"], "ensemble_size": 1}})
    result = rlhf(config, str(tmp_path / "run"), log=lambda line: None)
    assert result["rounds"][0]["campaigns"] == ["round0", "round0_pass1"]
    store = FeedbackStore(str(tmp_path / "run" / "feedback.sqlite"))
    first, second = (store.context_keys(store.campaign(name)) for name in ("round0", "round0_pass1"))
    assert len(first) == len(scenes) and [key["scene_id"] for key in second] == scenes[:2]  # the first two, drawn again
    assert store.campaign("round0").config["seed"] != store.campaign("round0_pass1").config["seed"]
    store.close()


def test_weak_probes_are_told_apart_by_what_the_stand_ins_see() -> None:
    from trafficrlhf_sdk.loop import _probe_warnings

    assert _probe_warnings({"faster": {"pass_rate": 0.95, "judges": 0.9}}) == []
    missed, unseen = _probe_warnings({"faster": {"pass_rate": 0.6, "judges": 0.95},
                                      "slower": {"pass_rate": 0.56, "judges": 0.32},
                                      "weave": {"pass_rate": 0.97, "judges": 0.99}})
    assert "faster (0.60)" in missed and "contrast_weight help" in missed and "slower" not in missed
    assert "slower (0.56; the stand-in annotators 0.320)" in unseen and "will not help" in unseen
    assert "faster" not in unseen and "weave" not in unseen
    # just under the line: the annotators' rate is printed finely enough to show it is under
    assert "off_lane (0.10; the stand-in annotators 0.899)" in _probe_warnings(
        {"off_lane": {"pass_rate": 0.1, "judges": 71 / 79}})[0]
    # without the annotators' own probes (labels from people) a weak probe reads as the reward model's miss
    assert len(_probe_warnings({"slower": {"pass_rate": 0.5}})) == 1
