"""Reward-model training and scoring on a chosen torch device.

The CPU-only checks run everywhere: the device is validated before featurizing, a missing CUDA device is one
clear error (also from the CLI), and a model moved to the ``meta`` device scores CPU-prepared inputs, which
fails if any step builds a tensor on the CPU instead of the model's device. The CUDA checks run where torch sees
a GPU.
"""

from __future__ import annotations

from pathlib import Path

import pydantic
import pytest
import torch

from trafficrlhf_sdk.cli import main
from trafficrlhf_sdk.errors import DeviceUnavailableError
from trafficrlhf_sdk.feedback import FeedbackStore, SyntheticAnnotator, SyntheticAnnotatorConfig, export_preferences
from trafficrlhf_sdk.reward import CTGMLPRewardModel, RewardConfig, RewardTrainer
from trafficrlhf_sdk.reward.model import ScenarioInputs, prepared_device
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign, tiny_context

SMALL = {"hidden_sizes": [32, 16], "map_channels": [4, 8], "map_embedding": 8}
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@pytest.fixture(scope="module")
def scenes(scored_futures: ScenarioTensor) -> ScenarioTensor:
    """Four tiny contexts, each with the history and one candidate future (T = 41, A = 3)."""
    return scored_futures


@pytest.fixture(scope="module")
def tiny_db(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = str(tmp_path_factory.mktemp("device") / "feedback.db")
    store = FeedbackStore(path)
    make_tiny_campaign(store, num_contexts=10)
    SyntheticAnnotator(store, "oracle", SyntheticAnnotatorConfig(beta=None)).label("tiny")
    return path


def test_malformed_device_is_refused_by_the_config() -> None:
    with pytest.raises(pydantic.ValidationError, match=r"`device` must be a torch device.*'gpu'"):
        RewardConfig(device="gpu")
    assert RewardConfig(device="cuda:1").device == "cuda:1"  # well formed; availability is checked on training


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the CPU-only message")
def test_missing_cuda_is_one_clear_error_before_featurizing(tiny_db: str, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(DeviceUnavailableError, match="'cuda' but this machine has 0 CUDA device"):
        RewardTrainer(RewardConfig(device="cuda"), train_dataset=None)  # type: ignore[arg-type]
    with pytest.raises(SystemExit) as exit_info:
        main(["rm", "train", "--db", tiny_db, "--campaign", "tiny", "--out", str(tmp_path / "m"),
              "--device", "cuda", "--quiet"])
    err = capsys.readouterr().err
    assert exit_info.value.code != 0 and "--device cpu" in err and "Traceback" not in err
    assert not (tmp_path / "m").exists()


def test_scoring_follows_the_model_device(scenes: ScenarioTensor) -> None:
    """A model on another device scores CPU-prepared inputs there: every intermediate tensor must follow it."""
    torch.manual_seed(0)
    model = CTGMLPRewardModel(SMALL).eval()
    prepared = model.prepare(scenes)
    assert prepared_device(prepared) == torch.device("cpu")
    model.to("meta")
    assert model.device == torch.device("meta")
    scores = model.score_prepared(prepared)
    assert scores.device.type == "meta" and scores.shape == (scenes.num_scenes,)
    assert model.agent_scores(scenes).shape == (scenes.num_scenes, scenes.num_agents)
    assert model(scenes).device.type == "meta"
    assert prepared_device(ScenarioInputs(scenes)) == torch.device("cpu")


@cuda
def test_training_on_cuda_learns_like_on_cpu(tiny_db: str, tmp_path: Path) -> None:
    dataset = export_preferences(FeedbackStore(tiny_db), "tiny", val_fraction=0.2)
    results = {}
    for device in ("cpu", "cuda"):
        config = RewardConfig(architecture_config=SMALL, max_epochs=25, batch_size=2, learning_rate=3e-3,
                              early_stopping_patience=None, progress=False, seed=0, device=device)
        results[device] = RewardTrainer(config, train_dataset=dataset).train()
    gpu = results["cuda"].model
    assert gpu.device.type == "cuda" and gpu.card_info["training"]["device"].startswith("cuda")
    assert results["cuda"].metrics["val_accuracy"] >= 0.75
    # the same seed and data: float32 kernels differ in rounding only
    assert abs(results["cuda"].metrics["val_loss"] - results["cpu"].metrics["val_loss"]) < 0.05
    gpu.save_pretrained(tmp_path / "gpu")
    loaded = CTGMLPRewardModel.from_pretrained(tmp_path / "gpu")
    scenario, candidates, valid, _, _ = tiny_context(["faithful"], 0)
    scene = scenario.with_future(candidates, valid)
    torch.testing.assert_close(loaded(scene), gpu(scene).cpu(), rtol=1e-5, atol=1e-5)


@cuda
def test_a_gpu_reward_model_scores_cpu_rollouts_for_the_fine_tuner(scenes: ScenarioTensor) -> None:
    """The fine-tuner's scoring takes CPU rollouts; a reward model on the GPU featurizes them on the CPU, scores
    on the GPU and hands back CPU scores equal to a CPU copy's."""
    from trafficrlhf_sdk.reward.scoring import agent_scores, scenario_scores

    torch.manual_seed(0)
    cpu_model = CTGMLPRewardModel(SMALL).eval()
    gpu_model = CTGMLPRewardModel(SMALL).eval()
    gpu_model.load_state_dict(cpu_model.state_dict())
    gpu_model.to("cuda")
    for score in (scenario_scores, agent_scores):
        expected, got = score(cpu_model, scenes), score(gpu_model, scenes)
        assert got.device.type == "cpu"
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
