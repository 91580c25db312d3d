"""Reward models: the paper's architecture, Bradley–Terry training, safetensors folders that refuse bad files."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch
from pydantic import BaseModel

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, UnknownComponentError
from trafficrlhf_sdk.feedback import FeedbackStore, SyntheticAnnotator, SyntheticAnnotatorConfig, export_preferences
from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.plugins import get_plugin_manager
from trafficrlhf_sdk.reward import (
    CTGMLPRewardModel,
    RewardConfig,
    RewardEnsemble,
    RewardModel,
    RewardTrainer,
    bradley_terry_loss,
    build_pair_data,
    evaluate_pairs,
)
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

SMALL = {"hidden_sizes": [32, 16], "map_channels": [4, 8], "map_embedding": 8}  # fast variant for training tests


@pytest.fixture(scope="module")
def model() -> CTGMLPRewardModel:
    torch.manual_seed(0)
    return CTGMLPRewardModel().eval()


@pytest.fixture(scope="module")
def scenes(scored_futures: ScenarioTensor) -> ScenarioTensor:
    """Four tiny contexts, each with the history and one candidate future (T = 41, A = 3)."""
    return scored_futures


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """A labeled tiny campaign (10 contexts, noise-free annotator) exported with 2 val contexts."""
    store = FeedbackStore(str(tmp_path_factory.mktemp("rm") / "feedback.db"))
    make_tiny_campaign(store, num_contexts=10)
    SyntheticAnnotator(store, "oracle", SyntheticAnnotatorConfig(beta=None)).label("tiny")
    return export_preferences(store, "tiny", val_fraction=0.2)


def test_paper_architecture(model: CTGMLPRewardModel) -> None:
    widths = [m.out_features for m in model.mlp if isinstance(m, torch.nn.Linear)]
    assert widths == [512, 512, 512, 128, 32, 1]
    assert all(isinstance(m, torch.nn.Tanh) for m in list(model.mlp)[1::2])  # Tanh after every layer, output too
    assert isinstance(list(model.mlp)[-1], torch.nn.Tanh)


@pytest.mark.parametrize(("steps", "extra_agents"), [(41, 0), (12, 0), (1, 0), (41, 5), (60, 2)])
def test_any_length_and_agent_count(model: CTGMLPRewardModel, scenes: ScenarioTensor, steps: int,
                                    extra_agents: int) -> None:
    scenario = scenes.time_slice(0, min(steps, scenes.num_steps)).replace_unchecked(current_index=0)
    if steps > scenes.num_steps or extra_agents:  # pad with invalid steps and real extra agents
        b, a, t = scenario.valid.shape
        t2 = max(steps, t)
        states = torch.zeros(b, a + extra_agents, t2, 4)
        valid = torch.zeros(b, a + extra_agents, t2, dtype=torch.bool)
        states[:, :a, :t], valid[:, :a, :t] = scenario.states, scenario.valid
        states[:, a:, :t] = scenario.states[:, :1] + torch.tensor([30.0, 0.0, 0.0, 0.0])
        valid[:, a:, :t] = scenario.valid[:, :1]
        scenario = ScenarioTensor(states, valid, torch.full((b, a + extra_agents, 2), 4.0),
                                  torch.ones(b, a + extra_agents, dtype=torch.long), valid.any(-1), dt=scenario.dt,
                                  map=scenario.map)
    with torch.no_grad():
        per_step = model.step_rewards(scenario)
        score = model(scenario)
    assert per_step.shape == (scenario.num_scenes, scenario.num_steps)
    assert score.shape == (scenario.num_scenes,)
    assert per_step.abs().max() <= 1 and score.abs().max() <= 1
    assert torch.isfinite(per_step).all() and torch.isfinite(score).all()


def test_padding_agents_and_steps_change_nothing(model: CTGMLPRewardModel, scenes: ScenarioTensor) -> None:
    t = scenes.num_steps
    padded = ScenarioTensor(
        states=torch.nn.functional.pad(scenes.states, (0, 0, 0, 7, 0, 4), value=123.0),
        valid=torch.nn.functional.pad(scenes.valid, (0, 7, 0, 4)), extent=torch.nn.functional.pad(scenes.extent,
                                                                                                 (0, 0, 0, 4)),
        agent_type=torch.nn.functional.pad(scenes.agent_type, (0, 4)),
        controlled=torch.nn.functional.pad(scenes.controlled, (0, 4)), dt=scenes.dt,
        current_index=scenes.current_index, map=scenes.map)
    with torch.no_grad():
        assert torch.allclose(model(padded), model(scenes), atol=1e-6)
        assert torch.allclose(model.step_rewards(padded)[:, :t], model.step_rewards(scenes), atol=1e-6)
        assert (model.step_rewards(padded)[:, t:] == 0).all()  # no valid agent there


def test_only_controlled_agents_are_averaged(model: CTGMLPRewardModel, scenes: ScenarioTensor) -> None:
    steps = len(range(scenes.current_index + 5, scenes.num_steps, 5))  # 2 Hz after "now" at dt = 0.1 s
    one = scenes.replace_unchecked(controlled=torch.tensor([[True, False, False]] * scenes.num_scenes))
    assert len(model.prepare(one)) == scenes.num_scenes * steps  # agent 0 alone is scored
    none = scenes.replace_unchecked(controlled=torch.zeros(scenes.num_scenes, 3, dtype=torch.bool))
    assert len(model.prepare(none)) == scenes.num_scenes * steps * 3  # no controlled agent: all of them
    with torch.no_grad():
        assert not torch.allclose(model(one), model(none))


def test_save_and_reload_identical(model: CTGMLPRewardModel, scenes: ScenarioTensor, tmp_path: Path) -> None:
    model.save_pretrained(tmp_path / "rm", card={"notes": "test model"})
    assert sorted(os.listdir(tmp_path / "rm")) == ["README.md", "config.json", "model.safetensors"]
    loaded = RewardModel.from_pretrained(tmp_path / "rm")
    assert type(loaded) is CTGMLPRewardModel and loaded.config == model.config
    with torch.no_grad():
        assert torch.equal(loaded(scenes), model(scenes))
        assert torch.equal(loaded.step_rewards(scenes), model.step_rewards(scenes))
    card = (tmp_path / "rm" / "README.md").read_text()
    assert "license: cc-by-nc-sa-4.0" in card and "ctg_mlp" in card and "test model" in card


def test_ensemble_round_trip_and_spread(scenes: ScenarioTensor, tmp_path: Path) -> None:
    torch.manual_seed(1)
    ensemble = RewardEnsemble(members=[CTGMLPRewardModel(SMALL), CTGMLPRewardModel(SMALL)]).eval()
    with torch.no_grad():
        assert (ensemble.uncertainty(scenes) > 0).all()
    ensemble.save_pretrained(tmp_path / "ens")
    loaded = RewardModel.from_pretrained(tmp_path / "ens")
    assert isinstance(loaded, RewardEnsemble) and len(loaded.members) == 2
    with torch.no_grad():
        assert torch.equal(loaded(scenes), ensemble(scenes))


@pytest.fixture()
def saved(model: CTGMLPRewardModel, tmp_path: Path) -> Path:
    return Path(model.save_pretrained(tmp_path / "rm"))


def test_tampered_weights_are_refused(saved: Path) -> None:
    path = saved / "model.safetensors"
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF  # one weight changed: safetensors alone would load it silently
    path.write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match=r"SHA-256.*modified or truncated"):
        RewardModel.from_pretrained(saved)


def test_truncated_weights_are_refused(saved: Path) -> None:
    path = saved / "model.safetensors"
    path.write_bytes(path.read_bytes()[:5000])
    with pytest.raises(DataFormatError, match="modified or truncated"):
        RewardModel.from_pretrained(saved)
    with pytest.raises(DataFormatError, match="not a readable safetensors file"):
        RewardModel.from_pretrained(saved, verify=False)


def _edit_config(folder: Path, **changes: object) -> None:
    config = json.loads((folder / "config.json").read_text())
    config.update(changes)
    (folder / "config.json").write_text(json.dumps(config))


def test_unknown_architecture_is_refused(saved: Path) -> None:
    _edit_config(saved, architecture="transformer_xl")
    with pytest.raises(UnknownComponentError, match=r"'transformer_xl'.*registered: .*ctg_mlp.*plugin"):
        RewardModel.from_pretrained(saved)


def test_shape_mismatch_is_refused(saved: Path) -> None:
    config = json.loads((saved / "config.json").read_text())
    _edit_config(saved, config={**config["config"], "hidden_sizes": [512, 512, 256, 128, 32]})
    with pytest.raises(DataFormatError, match=r"shape \(512, 512\).*needs \(256, 512\)"):
        RewardModel.from_pretrained(saved)


def test_bad_config_and_missing_files_are_refused(saved: Path, tmp_path: Path) -> None:
    _edit_config(saved, config={"hidden_sizes": [], "bogus": 1})
    with pytest.raises(DataFormatError, match="does not fit architecture 'ctg_mlp'"):
        RewardModel.from_pretrained(saved)
    (saved / "config.json").write_text("{not json")
    with pytest.raises(DataFormatError, match="not valid JSON"):
        RewardModel.from_pretrained(saved)
    with pytest.raises(DataNotFoundError, match="not found"):
        RewardModel.from_pretrained(tmp_path / "nowhere")


def test_plugin_architecture_is_resolved(scenes: ScenarioTensor, tmp_path: Path) -> None:
    class ConstantReward(RewardModel):
        architecture = "test_constant"

        class Config(BaseModel):
            value: float = 0.25

        def __init__(self, config: object = None) -> None:
            super().__init__(config)  # type: ignore[arg-type]
            self.bias = torch.nn.Parameter(torch.tensor(self.config.value))  # type: ignore[attr-defined]

        def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
            return torch.tanh(self.bias).expand(scenario.num_scenes, scenario.num_steps)

        def forward(self, scenario: ScenarioTensor) -> torch.Tensor:
            return self.step_rewards(scenario).mean(1)

    class Plugin:
        @hookimpl
        def register_reward_model_architectures(self, register):  # type: ignore[no-untyped-def]
            register("test_constant", ConstantReward)

    pm = get_plugin_manager()
    pm.register(Plugin(), name="test-reward-plugin")
    try:
        ConstantReward().save_pretrained(tmp_path / "c")
        loaded = RewardModel.from_pretrained(tmp_path / "c")
        assert isinstance(loaded, ConstantReward)
        assert torch.allclose(loaded(scenes), torch.tanh(torch.tensor(0.25)).expand(4))
    finally:
        pm.unregister(name="test-reward-plugin")
    with pytest.raises(UnknownComponentError, match="test_constant"):
        RewardModel.from_pretrained(tmp_path / "c")


class SpeedReward(RewardModel):
    """A plugin-style architecture without a fast path: r = tanh(w * speed), averaged over valid agent-steps."""

    architecture = "test_speed"

    class Config(BaseModel):
        """Its one option."""

        scale: float = 0.1

    def __init__(self, config: object = None) -> None:
        super().__init__(config)  # type: ignore[arg-type]
        self.weight = torch.nn.Parameter(torch.tensor(0.0))

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        per_agent = torch.tanh(self.weight * self.config.scale * scenario.speed)  # type: ignore[attr-defined]
        valid = scenario.valid.float()
        return (per_agent * valid).sum(1) / valid.sum(1).clamp_min(1)

    def forward(self, scenario: ScenarioTensor) -> torch.Tensor:
        return self.step_rewards(scenario)[:, scenario.current_index + 1:].mean(1)


def test_trainer_runs_a_plugin_architecture_through_the_generic_path(tiny_dataset) -> None:  # type: ignore[no-untyped-def]
    class Plugin:
        @hookimpl
        def register_reward_model_architectures(self, register):  # type: ignore[no-untyped-def]
            register("test_speed", SpeedReward)

    pm = get_plugin_manager()
    pm.register(Plugin(), name="test-speed-plugin")
    try:
        config = RewardConfig(architecture="test_speed", max_epochs=3, batch_size=4, learning_rate=0.1,
                              progress=False, ema_decay=None)
        result = RewardTrainer(config, train_dataset=tiny_dataset).train()
    finally:
        pm.unregister(name="test-speed-plugin")
    assert isinstance(result.model, SpeedReward) and len(result.history) == 3
    assert float(result.model.weight.detach()) != 0.0  # it was trained


def test_bradley_terry_loss_matches_hand_computation() -> None:
    chosen, rejected = torch.tensor([0.5, -0.2]), torch.tensor([0.1, 0.3])
    by_hand = -(torch.log(torch.sigmoid(torch.tensor(0.4))) + torch.log(torch.sigmoid(torch.tensor(-0.5)))) / 2
    assert torch.allclose(bradley_terry_loss(chosen, rejected), by_hand)
    with_margin = -(torch.log(torch.sigmoid(torch.tensor(2 * 0.4 - 0.1)))
                    + torch.log(torch.sigmoid(torch.tensor(2 * -0.5 - 0.1)))) / 2
    assert torch.allclose(bradley_terry_loss(chosen, rejected, margin=0.1, logit_scale=2.0), with_margin)
    centred = by_hand + 0.01 * ((0.6**2) + (0.1**2)) / 2
    assert torch.allclose(bradley_terry_loss(chosen, rejected, center_rewards_coefficient=0.01), centred)


def test_soft_tie_labels_give_symmetric_gradients() -> None:
    chosen = torch.tensor([0.3, -0.4], requires_grad=True)
    rejected = torch.tensor([-0.1, 0.2], requires_grad=True)
    bradley_terry_loss(chosen, rejected, labels=torch.full((2,), 0.5), margin=0.2).backward()
    assert torch.allclose(chosen.grad, -rejected.grad)  # type: ignore[arg-type]
    swapped = bradley_terry_loss(rejected.detach(), chosen.detach(), labels=torch.full((2,), 0.5), margin=0.2)
    assert torch.allclose(swapped, bradley_terry_loss(chosen.detach(), rejected.detach(), torch.full((2,), 0.5),
                                                      margin=0.2))
    # a tie pulls the rewards together: the gradient step shrinks |r_w - r_l|
    assert float(chosen.grad[0]) > 0 and float(chosen.grad[1]) < 0  # type: ignore[index]


def test_trainer_learns_the_tiny_problem(tiny_dataset) -> None:  # type: ignore[no-untyped-def]
    config = RewardConfig(architecture_config=SMALL, max_epochs=25, batch_size=2, learning_rate=3e-3,
                          early_stopping_patience=None, progress=False, seed=0)
    torch.manual_seed(0)
    before = evaluate_pairs(CTGMLPRewardModel(SMALL), build_pair_data(CTGMLPRewardModel(SMALL).prepare, tiny_dataset))
    rows: list[dict[str, float]] = []
    trainer = RewardTrainer(config, train_dataset=tiny_dataset, log=rows.append)
    assert trainer.dataset_info["train_contexts"] == 8 and trainer.dataset_info["val_contexts"] == 2
    result = trainer.train()
    assert len(rows) == 25 and {"train_loss", "train_accuracy", "train_margin", "val_loss", "val_accuracy",
                                "val_margin", "val_min_reward", "val_max_reward"} <= set(rows[0])
    after = trainer.evaluate(tiny_dataset.subset("train"))
    assert after["accuracy"] >= 0.9 and after["accuracy"] > before["accuracy"] - 1e-9
    assert after["loss"] < rows[0]["train_loss"]
    assert result.metrics["val_accuracy"] >= 0.75
    assert result.model.card_info["data"]["train_pairs"] == 32


def test_early_stopping_stops_and_restores_best(tiny_dataset) -> None:  # type: ignore[no-untyped-def]
    config = RewardConfig(architecture_config=SMALL, max_epochs=10, batch_size=4, learning_rate=1e-12,
                          early_stopping_patience=2, progress=False)
    result = RewardTrainer(config, train_dataset=tiny_dataset).train()
    assert len(result.history) == 3 and result.best_epochs == [1]


def test_bootstrap_ensemble_reports_spread(tiny_dataset) -> None:  # type: ignore[no-untyped-def]
    config = RewardConfig(architecture_config=SMALL, max_epochs=2, batch_size=4, ensemble_size=3, progress=False)
    result = RewardTrainer(config, train_dataset=tiny_dataset).train()
    assert isinstance(result.model, RewardEnsemble) and len(result.model.members) == 3
    assert result.metrics["val_uncertainty"] > 0
    assert "val_accuracy_member_std" in result.metrics
    assert {row["member"] for row in result.history} == {0, 1, 2}


def test_config_rejects_unknown_keys() -> None:
    with pytest.raises(Exception, match="extra"):
        RewardConfig(learning_rate=1e-3, lr=1e-3)  # type: ignore[call-arg]
    with pytest.raises(UnknownComponentError, match="Unknown reward-model architecture: 'nope'"):
        RewardTrainer(RewardConfig(architecture="nope"), train_dataset=None)  # type: ignore[arg-type]
