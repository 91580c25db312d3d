"""Reward-ranked imitation (AlignConfig.best_sample_coef): each agent imitates its best sample of a context."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.alignment import AlignConfig, align
from trafficrlhf_sdk.alignment.sample_scenarios import SampleScenarios
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.testing.rewards import SlowDownReward

gru = pytest.importorskip("trafficrlhf_example_gru")

NOW, H, S = 5, 4, 3


class _Windows(SampleScenarios):
    future_steps = H


def _contexts() -> ScenarioTensor:
    b, a, t = 2, 3, NOW + H + 1
    states = torch.zeros(b, a, t, 4)
    states[..., 0] = torch.arange(t, dtype=torch.float32)  # x = step, so the history is recognizable
    states[..., 1] = torch.arange(a, dtype=torch.float32)[None, :, None] * 4
    return ScenarioTensor(states=states, valid=torch.ones(b, a, t, dtype=torch.bool),
                          extent=torch.tensor([[[4.5, 1.9]] * a] * b), agent_type=torch.ones(b, a, dtype=torch.long),
                          controlled=torch.ones(b, a, dtype=torch.bool), current_index=NOW)


def _futures() -> torch.Tensor:
    """``(B, S, A, H, 4)``: sample s of every agent drives at y = 100 s + agent."""
    futures = torch.zeros(2, S, 3, H, 4)
    futures[..., 1] = 100 * torch.arange(S, dtype=torch.float32)[None, :, None, None] + torch.arange(3.0)[:, None]
    futures[..., 2] = 1.0
    return futures


def test_each_agent_keeps_its_highest_advantage_sample_and_agents_without_a_choice_are_skipped() -> None:
    contexts, futures = _contexts(), _futures()
    agents = torch.tensor([[True, True, False], [True, True, True]])
    adv = torch.zeros(2, S, 3)
    adv[0, 2, 0] = 1.0  # agent 0 of context 0: sample 2
    adv[0, :, 1] = 0.5  # agent 1 of context 0: all samples alike, nothing to prefer
    adv[1, 1, :] = torch.tensor([2.0, -1.0, 0.3])  # context 1: sample 1 for agents 0 and 2, sample 0 for agent 1
    adv[1, 2, 1] = -2.0
    adv[0, 0, 2] = 3.0  # agent 2 of context 0 was not sampled
    best = _Windows().best_sample_windows(contexts, futures, agents, adv)
    assert best.num_steps == NOW + 1 + H and best.current_index == NOW
    assert torch.equal(best.states[:, :, : NOW + 1], contexts.states[:, :, : NOW + 1])  # the context's history
    future_valid = best.valid[:, :, NOW + 1:].all(-1)
    assert future_valid.tolist() == [[True, False, False], [True, True, True]]
    y = best.states[:, :, NOW + 1, 1]
    assert float(y[0, 0]) == 200.0  # sample 2, agent 0
    assert [float(v) for v in y[1]] == [100.0, 1.0, 102.0]
    assert not best.valid[0, 1, NOW + 1:].any() and not best.states[0, 1, NOW + 1:].any()


def test_scene_advantages_pick_one_sample_for_every_agent_of_a_context() -> None:
    contexts, futures = _contexts(), _futures()
    agents = torch.ones(2, 3, dtype=torch.bool)
    adv = torch.tensor([[0.0, 1.0, -1.0], [0.0, 0.0, 0.0]])  # context 1: every sample alike
    best = _Windows().best_sample_windows(contexts, futures, agents, adv)
    assert [float(v) for v in best.states[0, :, NOW + 1, 1]] == [100.0, 101.0, 102.0]
    assert not best.valid[1, :, NOW + 1:].any()


def test_the_best_sample_imitation_alone_raises_the_reward(nuscenes_source) -> None:  # type: ignore[no-untyped-def]
    scenes = nuscenes_source.load_batch("train", 6)
    config = dict(epochs=12, contexts_per_epoch=6, samples_per_context=4, minibatch_contexts=3, ppo_epochs=2,
                  imitation_coef=0.0, learning_rate=3e-3, progress_bar=False)
    torch.manual_seed(0)
    history = align(gru.ExampleGRUAdapter(), SlowDownReward(), alpha=0.0, scenes=scenes, best_sample_coef=1.0,
                    **config).history
    assert all(h["best_sample_loss"] == h["best_sample_loss"] for h in history)  # recorded, not NaN
    first = sum(h["reward_mean"] for h in history[:3]) / 3
    last = sum(h["reward_mean"] for h in history[-3:]) / 3
    assert last > first + 0.05, (first, last)
    torch.manual_seed(0)
    without = align(gru.ExampleGRUAdapter(), SlowDownReward(), alpha=0.0, scenes=scenes, **config).history
    assert all(h["best_sample_loss"] != h["best_sample_loss"] for h in without)  # NaN: the term is off
    assert sum(h["reward_mean"] for h in without[-3:]) / 3 < last


def test_best_sample_coef_is_checked() -> None:
    with pytest.raises(ValueError, match="best_sample_coef"):
        AlignConfig(best_sample_coef=-1.0)
