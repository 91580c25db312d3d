"""The TrafficGen-style reward model (``trafficgen_mcg``): the paper's head on a multi-context-gating encoder, the
reward-model contract (any length, any agents, padding masked, rewards in [-1, 1]) and training through the
generic trainer."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trafficrlhf_sdk.feedback import FeedbackStore, SyntheticAnnotator, SyntheticAnnotatorConfig, export_preferences
from trafficrlhf_sdk.reward import (
    RewardConfig,
    RewardModel,
    RewardTrainer,
    TrafficGenMCGRewardModel,
    get_reward_model_architecture,
)
from trafficrlhf_sdk.reward.trafficgen_mcg import ContextGating, neighbour_vectors
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign
from trafficrlhf_sdk.testing.strategies import scenario_tensors

SMALL = {"hidden_sizes": [16, 8], "width": 8, "gating_blocks": 2, "crop_size": 8}
PROPERTY = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                          HealthCheck.data_too_large])


@pytest.fixture(scope="module")
def model() -> TrafficGenMCGRewardModel:
    torch.manual_seed(0)
    return TrafficGenMCGRewardModel().eval()


@pytest.fixture(scope="module")
def small() -> TrafficGenMCGRewardModel:
    torch.manual_seed(1)
    return TrafficGenMCGRewardModel(SMALL).eval()


def _pad(scenes: ScenarioTensor, agents: int, steps: int) -> ScenarioTensor:
    """``scenes`` with ``agents`` never-valid agents and ``steps`` invalid steps appended (garbage states)."""
    pad = torch.nn.functional.pad
    return ScenarioTensor(states=pad(scenes.states, (0, 0, 0, steps, 0, agents), value=77.0),
                          valid=pad(scenes.valid, (0, steps, 0, agents)),
                          extent=pad(scenes.extent, (0, 0, 0, agents)), agent_type=pad(scenes.agent_type, (0, agents)),
                          controlled=pad(scenes.controlled, (0, agents)), dt=scenes.dt,
                          current_index=scenes.current_index, map=scenes.map)


def test_registered_with_the_paper_head(model: TrafficGenMCGRewardModel) -> None:
    assert get_reward_model_architecture("trafficgen_mcg") is TrafficGenMCGRewardModel
    widths = [m.out_features for m in model.mlp if isinstance(m, torch.nn.Linear)]
    assert widths == [512, 512, 512, 128, 32, 1]
    assert all(isinstance(m, torch.nn.Tanh) for m in list(model.mlp)[1::2])
    assert len(model.agent_gating.blocks) == 3 and len(model.map_gating.blocks) == 3


def test_scores_the_tiny_futures_in_range(model: TrafficGenMCGRewardModel, scored_futures: ScenarioTensor) -> None:
    with torch.no_grad():
        score, per_step, agents = model(scored_futures), model.step_rewards(scored_futures), \
            model.agent_scores(scored_futures)
    assert score.shape == (4,) and per_step.shape == (4, scored_futures.num_steps) and agents.shape == (4, 3)
    for value in (score, per_step, agents):
        assert torch.isfinite(value).all() and value.abs().max() <= 1


def test_padding_agents_and_steps_change_nothing(model: TrafficGenMCGRewardModel,
                                                 scored_futures: ScenarioTensor) -> None:
    padded = _pad(scored_futures, agents=5, steps=6)
    t = scored_futures.num_steps
    with torch.no_grad():
        torch.testing.assert_close(model(padded), model(scored_futures), atol=1e-6, rtol=0)
        torch.testing.assert_close(model.step_rewards(padded)[:, :t], model.step_rewards(scored_futures), atol=1e-6,
                                   rtol=0)
        assert (model.step_rewards(padded)[:, t:] == 0).all()


@PROPERTY
@given(scenario=scenario_tensors(max_scenes=2, max_agents=4, max_steps=14, with_map=None),
       extra=st.integers(1, 3))
def test_property_rewards_bounded_and_padding_invariant(small: TrafficGenMCGRewardModel, scenario: ScenarioTensor,
                                                        extra: int) -> None:
    with torch.no_grad():
        score = small(scenario)
        per_step = small.step_rewards(scenario)
        padded = small(_pad(scenario, agents=extra, steps=0))
    assert score.shape == (scenario.num_scenes,) and per_step.shape == (scenario.num_scenes, scenario.num_steps)
    assert torch.isfinite(score).all() and score.abs().max() <= 1 and per_step.abs().max() <= 1
    torch.testing.assert_close(padded, score, atol=1e-5, rtol=0)


@PROPERTY
@given(scenario=scenario_tensors(max_scenes=2, max_agents=5, max_steps=8, with_map=False))
def test_property_neighbour_vectors_mask_absent_agents(scenario: ScenarioTensor) -> None:
    step = torch.full((scenario.num_scenes * scenario.num_agents,), scenario.num_steps - 1)
    scene = torch.arange(scenario.num_scenes).repeat_interleave(scenario.num_agents)
    agent = torch.arange(scenario.num_agents).repeat(scenario.num_scenes)
    vectors = neighbour_vectors(scenario, scene, agent, step, k=3, radius_m=40.0)
    assert vectors.shape == (len(scene), 3, 9) and torch.isfinite(vectors).all()
    valid = vectors[..., -1]
    assert set(valid.unique().tolist()) <= {0.0, 1.0}
    assert (vectors[valid == 0] == 0).all()  # an absent neighbour is all zero
    others = scenario.valid[scene, :, step].sum(1) - scenario.valid[scene, agent, step].long()
    assert (valid.sum(1) <= others.clamp(max=3)).all()  # never more neighbours than valid other agents


def test_context_gating_ignores_masked_elements() -> None:
    torch.manual_seed(0)
    block = ContextGating(6)
    elements, context = torch.randn(3, 5, 6), torch.randn(3, 6)
    mask = torch.tensor([[True, True, False, False, False], [True] * 5, [False] * 5])
    _, pooled = block(elements, mask, context)
    changed = elements.clone()
    changed[~mask] = 1000.0
    _, again = block(changed, mask, context)
    torch.testing.assert_close(pooled, again)
    assert (pooled[2] == 0).all()  # no valid element: a zero context


def test_save_reload_and_training_through_the_generic_trainer(tmp_path: Path,
                                                              scored_futures: ScenarioTensor) -> None:
    store = FeedbackStore(str(tmp_path / "feedback.db"))
    make_tiny_campaign(store, num_contexts=8)
    SyntheticAnnotator(store, "oracle", SyntheticAnnotatorConfig(beta=None)).label("tiny")
    data = export_preferences(store, "tiny", val_fraction=0.25)
    config = RewardConfig(architecture="trafficgen_mcg", architecture_config=SMALL, max_epochs=3, batch_size=4,
                          progress=False)
    result = RewardTrainer(config, train_dataset=data).train()
    assert isinstance(result.model, TrafficGenMCGRewardModel) and len(result.history) >= 1
    assert all(torch.isfinite(torch.tensor(row["train_loss"])) for row in result.history)
    result.model.save_pretrained(str(tmp_path / "rm"))
    loaded = RewardModel.from_pretrained(str(tmp_path / "rm"))
    assert isinstance(loaded, TrafficGenMCGRewardModel)
    with torch.no_grad():
        torch.testing.assert_close(loaded(scored_futures), result.model(scored_futures))
