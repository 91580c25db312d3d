"""``continue_s``: the reward scores each sample and the closed-loop driving it leads to (alignment, stage III)."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
from trafficrlhf_sdk.alignment.config import REWARD_HISTORY_STEPS
from trafficrlhf_sdk.reward.builtin import FailureReward
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

gru = pytest.importorskip("trafficrlhf_example_gru")

FAST = dict(epochs=1, contexts_per_epoch=3, samples_per_context=3, minibatch_contexts=3, ppo_epochs=1,
            progress_bar=False, credit="agent")


def _trainer(scenes: list[ScenarioTensor], continue_s: float) -> AlignTrainer:
    torch.manual_seed(0)
    return AlignTrainer(gru.ExampleGRUAdapter(), FailureReward(), AlignConfig(continue_s=continue_s, **FAST),
                        scenes=scenes)


def _samples(trainer: AlignTrainer) -> tuple[ScenarioTensor, torch.Tensor, torch.Tensor]:
    contexts, _ = trainer._contexts(0)
    with torch.no_grad():
        out = trainer.model.sample(contexts, 3, generator=torch.Generator().manual_seed(1))
    futures = out.futures.clone()
    futures[:, 1] = futures[:, 0]  # two samples of every context leave their agents in the same place
    return contexts, futures, out.trace.agents


def test_the_reward_window_covers_the_sample_and_its_continuation(train_scene_list: list[ScenarioTensor]) -> None:
    trainer = _trainer(train_scene_list, continue_s=1.0)
    assert (trainer.horizon, trainer.continue_steps, trainer.reward_steps) == (20, 10, 30)
    contexts, futures, agents = _samples(trainer)
    assert contexts.num_steps == contexts.current_index + 1 + 30  # the log covers the continuation too
    scenario = trainer.sample_scenarios(contexts, futures, agents, seed=5)
    b, s, a = futures.shape[:3]
    assert scenario.num_scenes == b * s and scenario.num_steps == REWARD_HISTORY_STEPS + 1 + 30
    states = scenario.states.reshape(b, s, a, -1, 4)[:, :, :, REWARD_HISTORY_STEPS + 1:]
    valid = scenario.valid.reshape(b, s, a, -1)[:, :, :, REWARD_HISTORY_STEPS + 1:]
    pick = agents[:, None].expand(b, s, a)
    # the sample's own steps are the sample
    assert torch.allclose(states[..., :20, :2][pick], futures[..., :2][pick].to(states.dtype), atol=1e-5)
    assert valid[pick].all()
    # after them the model drove on from where each sample ended: the independent closed-loop run of sample 2
    scene = trainer._future_states(contexts, futures, agents)
    start = contexts.with_future(scene[0][:, 2], scene[1][:, 2]).replace_unchecked(controlled=agents)
    trainer.model.options = trainer.model.options.model_copy(update={"seed": 5})
    driven = simulate(trainer.model, start, SimulationConfig(
        duration_s=1.0, start_index=contexts.current_index + 20, remove_offroad_at_start=False,
        late_agents="replay", after_log_end="continue")).simulated
    expected = driven.states[:, :, contexts.current_index + 21:]
    assert torch.allclose(states[:, 2, :, 20:][agents], expected[agents].to(states.dtype), atol=1e-5)
    # not a constant-velocity extension of the sample
    extended = trainer._future_states(contexts, futures, agents)[0]
    assert not torch.allclose(states[:, 2, :, 20:][agents], extended[:, 2, :, 20:][agents].to(states.dtype))
    # common random numbers: equal samples of one context continue equally; another sample does not
    assert torch.equal(states[:, 0], states[:, 1])
    assert not torch.allclose(states[:, 0, :, 20:][agents], states[:, 2, :, 20:][agents])
    # the same seed gives the same continuation, another seed another one
    again = trainer.sample_scenarios(contexts, futures, agents, seed=5)
    other = trainer.sample_scenarios(contexts, futures, agents, seed=6)
    assert torch.equal(again.states, scenario.states)
    assert not torch.equal(other.states, scenario.states)


def test_without_continuation_the_reward_sees_the_sample_alone(train_scene_list: list[ScenarioTensor]) -> None:
    trainer = _trainer(train_scene_list, continue_s=0.0)
    assert (trainer.continue_steps, trainer.reward_steps) == (0, 20)
    contexts, futures, agents = _samples(trainer)
    first = trainer.sample_scenarios(contexts, futures, agents, seed=5)
    assert first.num_steps == REWARD_HISTORY_STEPS + 1 + 20
    assert torch.equal(first.states, trainer.sample_scenarios(contexts, futures, agents, seed=6).states)


def test_an_epoch_with_continuation_trains_and_restores_the_models_seed(train_scene_list: list[ScenarioTensor]) -> None:
    trainer = _trainer(train_scene_list, continue_s=0.5)
    seed = trainer.model.options.seed
    history = trainer.train()
    assert len(history) == 1
    for key in ("reward_mean", "reward_std", "approx_kl", "surrogate", "heldout_realism"):
        assert torch.isfinite(torch.tensor(history[0][key])), key
    assert trainer.model.options.seed == seed
