"""The reward stage's card and run (``trafficrlhf_sdk.reward.card``), and what the probes count."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.reward.contrast import probe_reward_model
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.testing.feedback import tiny_context

ROOT = Path(__file__).resolve().parent.parent
COMMITTED = ROOT / "reference_models" / "reward" / "ctg_no_collision"


class _Model:
    def __init__(self) -> None:
        self.card_info = {"data": {"pairs": 12}}


class _Dataset:
    context_keys = ({"source": "nuscenes_pred", "split": "train"}, {"source": "nuscenes_pred", "split": "train"})


def test_model_card_records_data_test_metrics_and_notes() -> None:
    from trafficrlhf_sdk.reward.card import model_card

    card = model_card({"val_accuracy": 0.8}, _Model(), dataset=_Dataset(), campaigns=("a", "b"),
                      test_metrics={"accuracy": 0.7}, test_campaign="t", title="T", notes=("one", "two"),
                      commands=("trafficrlhf rm train ...",))
    assert card["metrics"] == {"val_accuracy": 0.8, "test_accuracy": 0.7}
    assert card["data"] == {"pairs": 12, "test_campaign": "t", "test_annotators": "all", "campaign": ["a", "b"],
                            "annotators": "all", "scenes": ["nuscenes_pred/train"]}
    assert card["title"] == "T" and card["notes"] == "one\n\ntwo" and card["commands"] == ["trafficrlhf rm train ..."]
    assert model_card({}, _Model()) == {"metrics": {}}  # an exported dataset: no campaign to record


def test_a_test_campaign_without_a_database_fails_before_training(tmp_path: Path) -> None:
    from trafficrlhf_sdk.reward import RewardConfig
    from trafficrlhf_sdk.reward.card import train_and_save

    with pytest.raises(TrafficRLHFError, match="--test-campaign 'held' needs --db"):
        train_and_save(RewardConfig(), object(), str(tmp_path / "m"), test_campaign="held")
    assert not (tmp_path / "m").exists()


def test_describe_reward_model_reports_the_committed_model() -> None:
    from trafficrlhf_sdk.reward.card import describe_reward_model

    summary = describe_reward_model(str(COMMITTED))
    assert summary["weights_sha256_ok"] and summary["registered"] and "weights_problem" not in summary
    assert summary["num_parameters"] > 0 and summary["metrics"]


class _LikesTheLog:
    def __init__(self, log: ScenarioTensor) -> None:
        self.log = log

    def score(self, scenario: ScenarioTensor) -> torch.Tensor:
        return -(scenario.xy - self.log.xy).norm(dim=-1).mean((1, 2))


def test_probes_count_windows_and_the_scenes_they_come_from() -> None:
    one, two = tiny_context(["faithful"], 0)[0], tiny_context(["faithful"], 1)[0]
    windows = ScenarioTensor.concat([one, one, two])  # two windows of one scene, one of another
    entry = probe_reward_model(_LikesTheLog(windows), windows, ("faster",))["faster"]
    assert entry["windows"] == 3 and entry["scenes"] == 2 and entry["pass_rate"] == 1.0


@pytest.mark.data
def test_contrast_items_of_the_kinds_asked_for_are_in_the_card(data_root: str, tmp_path: Path) -> None:
    from trafficrlhf_sdk.feedback import FeedbackStore, SyntheticAnnotator, SyntheticAnnotatorConfig
    from trafficrlhf_sdk.reward import RewardConfig
    from trafficrlhf_sdk.reward.card import train_and_save
    from trafficrlhf_sdk.reward.evaluation import load_preferences
    from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

    store = FeedbackStore(str(tmp_path / "fb.db"))
    campaign = make_tiny_campaign(store, num_contexts=3)
    SyntheticAnnotator(store, "oracle", SyntheticAnnotatorConfig()).label(campaign)
    dataset, _ = load_preferences(store.path, campaign.name, None, ["oracle"])
    trained = train_and_save(RewardConfig(max_epochs=1, batch_size=4, progress=False), dataset,
                             str(tmp_path / "rm"), store=store, campaigns=[campaign.name], contrast_scenes=2,
                             contrast_kinds=("stall",), source="nuscenes_pred")
    contrast = trained.card["data"]["contrast"]
    assert contrast["kinds"] == ["stall"] and contrast["pairs"] > 0
