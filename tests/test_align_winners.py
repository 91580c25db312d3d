"""Reward-ranked imitation beside PPO (``winner_coef``): the best sample of each context (agent) as a target."""

from __future__ import annotations

import math

import torch

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer, align
from trafficrlhf_sdk.reward.builtin import FailureReward
from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.testing.rewards import SlowDownReward

FAST = dict(epochs=1, contexts_per_epoch=4, samples_per_context=4, minibatch_contexts=2, ppo_epochs=1,
            progress_bar=False, log_formats=("csv",))


def test_winner_scene_holds_each_agents_best_sample(  # type: ignore[no-untyped-def]
        train_scene_list: list[ScenarioTensor], make_gru_adapter) -> None:
    model = make_gru_adapter()
    trainer = AlignTrainer(model, FailureReward(), AlignConfig(credit="agent", winner_coef=1.0, **FAST),
                           scenes=train_scene_list)
    contexts, _ = trainer._contexts(0)
    out = trainer._sample(contexts, torch.Generator().manual_seed(0))
    futures, agents = out.futures.detach(), out.trace.agents
    b, s, a, h = futures.shape[:4]
    rewards = torch.randn(b, s, a)
    rewards[:, :, 0] = 0.5  # agent 0: all samples tie -> nothing to learn from it
    winners = trainer.winner_scenarios(contexts, futures, agents, rewards)
    hist = min(model.history_steps, contexts.current_index)  # the GRU reads 31 steps; contexts hold 30
    assert winners.num_steps == hist + 1 + h and winners.current_index == hist
    # the history is the context's, unchanged
    now = contexts.current_index
    assert torch.equal(winners.states[:, :, : hist + 1], contexts.states[:, :, now - hist : now + 1])
    best = rewards.argmax(1)
    for i in range(b):
        for j in range(a):
            future_valid = winners.valid[i, j, hist + 1 :]
            if not agents[i, j] or j == 0:
                assert not future_valid.any()
                continue
            assert future_valid.all()
            expected = futures[i, best[i, j], j]
            got = winners.states[i, j, hist + 1 :]
            assert torch.allclose(got[:, :3], expected[:, :3])
            assert torch.allclose(got[:, 3], wrap_angle(expected[:, 3]), atol=1e-6)
    # a gap above every spread keeps no winner at all
    config = AlignConfig(credit="agent", winner_coef=1.0, winner_min_gap=100.0, **FAST)
    strict = AlignTrainer(model, FailureReward(), config, scenes=train_scene_list)
    assert not strict.winner_scenarios(contexts, futures, agents, rewards).valid[:, :, hist + 1 :].any()


def test_winner_term_is_off_by_default_and_logged_when_on(  # type: ignore[no-untyped-def]
        train_scene_list: list[ScenarioTensor], make_gru_adapter) -> None:
    plain = AlignTrainer(make_gru_adapter(), SlowDownReward(), AlignConfig(**FAST), scenes=train_scene_list)
    assert plain._rollout(0).winners is None
    history = align(make_gru_adapter(), SlowDownReward(), alpha=1.0, scenes=train_scene_list, winner_coef=1.0,
                    **FAST).history
    assert math.isfinite(history[0]["winner_loss"]) and history[0]["first_ratio_max_dev"] == 0.0


def test_imitating_winners_alone_raises_the_mean_reward(  # type: ignore[no-untyped-def]
        train_scene_list: list[ScenarioTensor], make_gru_adapter) -> None:
    # no PPO surrogate and no logged imitation: only the best sample of each context is learned from
    config = {**FAST, "epochs": 12, "contexts_per_epoch": 6, "minibatch_contexts": 3, "ppo_epochs": 2,
              "imitation_coef": 0.0, "winner_coef": 1.0, "learning_rate": 3e-3}
    history = align(make_gru_adapter(), SlowDownReward(), alpha=0.0, scenes=train_scene_list, **config).history
    first = sum(h["reward_mean"] for h in history[:3]) / 3
    last = sum(h["reward_mean"] for h in history[-3:]) / 3
    assert last > first + 0.05, (first, last)
