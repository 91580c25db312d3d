"""``builtin:random``: the null-control reward carries no information and is a fixed function of the states."""

from __future__ import annotations

import pytest
import torch
from scipy import stats

from trafficrlhf_sdk.reward.builtin import FailureReward, RandomReward
from trafficrlhf_sdk.reward.loading import load_reward
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario import ScenarioTensor


def _jittered(scenes: ScenarioTensor, copies: int, metres: float) -> ScenarioTensor:
    """``copies`` versions of every scene whose futures are moved by Gaussian noise of ``metres``."""
    many = scenes.repeat_scenes(copies)
    states = many.states.clone()
    future = slice(many.current_index + 1, None)
    gen = torch.Generator().manual_seed(0)
    states[:, :, future, :2] += metres * torch.randn(states[:, :, future, :2].shape, generator=gen)
    return many.replace_unchecked(states=states)


def test_scores_have_the_protocol_shapes_and_range_and_repeat_exactly(val_scenes: ScenarioTensor) -> None:
    reward = RandomReward(seed=3)
    agents, steps = reward.agent_scores(val_scenes), reward.step_rewards(val_scenes)
    assert agents.shape == (val_scenes.num_scenes, val_scenes.num_agents)
    assert steps.shape == (val_scenes.num_scenes, val_scenes.num_steps)
    assert agents.min() >= -1 and agents.max() < 1 and steps.min() >= -1 and steps.max() < 1
    # a function of the states: another instance with the same seed scores the same scenes the same way
    assert torch.equal(RandomReward(seed=3).agent_scores(val_scenes), agents)
    assert not torch.equal(RandomReward(seed=4).agent_scores(val_scenes), agents)


def test_scores_are_uniform_and_unrelated_to_failures(val_scenes: ScenarioTensor) -> None:
    scenes = _jittered(val_scenes, copies=12, metres=1.0)
    mask = scenes.controlled & scenes.valid[:, :, scenes.current_index]
    noise = RandomReward().agent_scores(scenes)[mask].double()
    failure = FailureReward(margins=True).agent_scores(scenes)[mask].double()
    assert noise.numel() > 150 and failure.std() > 0
    assert stats.kstest(noise.numpy(), stats.uniform(loc=-1, scale=2).cdf).pvalue > 1e-3
    assert abs(stats.spearmanr(noise.numpy(), failure.numpy()).statistic) < 0.2
    # futures a centimetre off the log score unrelated to the log's own, as samples of one context must
    logged = RandomReward().agent_scores(val_scenes.repeat_scenes(12))[mask].double()
    near = RandomReward().agent_scores(_jittered(val_scenes, copies=12, metres=0.01))[mask].double()
    assert abs(stats.pearsonr(near.numpy(), logged.numpy()).statistic) < 0.2


def test_cli_name_builds_it_and_takes_a_seed() -> None:
    assert isinstance(load_reward("builtin:random"), RandomReward)
    assert isinstance(load_reward("builtin:random", {"seed": 2}), RandomReward)
    with pytest.raises(TrafficRLHFError, match=r"margins.*RandomReward"):
        load_reward("builtin:random", {"margins": True})
