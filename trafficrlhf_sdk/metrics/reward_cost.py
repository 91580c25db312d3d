"""Reward cost: how much a rollout falls short of a reward model's ideal, sampled at 2 Hz."""

from __future__ import annotations

from collections.abc import Callable

import torch

from trafficrlhf_sdk.metrics.base import Metric, MetricResult
from trafficrlhf_sdk.metrics.failure import nanmean
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.simulator import Rollout

__all__ = ["RewardCostMetric", "RewardFn"]

RewardFn = Callable[[ScenarioTensor], torch.Tensor]
"""Maps a scenario ``(B, A, T)`` to per-step rewards ``(B, T)`` in [-1, 1]."""


class RewardCostMetric(Metric):
    """cost = sum over 2 Hz steps of (1 - r_t) / 2 for the simulated window (0 .. 20 for 10 s); mean over scenes.

    Args:
        reward_fn: per-step reward of a scenario, ``(B, T) in [-1, 1]`` (e.g. a reward model's ``step_rewards``).
        sample_dt: reward sampling period (s); 0.5 s = 2 Hz as in the paper.
    """

    name = "reward_cost"

    def __init__(self, reward_fn: RewardFn, sample_dt: float = 0.5) -> None:
        self.reward_fn = reward_fn
        self.sample_dt = sample_dt

    def compute(self, rollout: Rollout) -> MetricResult:
        """``reward_cost`` and ``reward_mean``; scenes without controlled agents are NaN."""
        window = rollout.window("simulated")
        stride = max(1, round(self.sample_dt / window.dt))
        sampled = window.replace_unchecked(
            states=window.states[:, :, stride::stride], valid=window.valid[:, :, stride::stride],
            dt=stride * window.dt, current_index=0,
        )
        with torch.no_grad():
            rewards = self.reward_fn(sampled)
        if rewards.shape != (sampled.num_scenes, sampled.num_steps):
            raise ValueError(
                f"`reward_fn` returned shape {tuple(rewards.shape)}; expected (B, T) = "
                f"({sampled.num_scenes}, {sampled.num_steps})."
            )
        if not torch.isfinite(rewards).all() or rewards.abs().max() > 1 + 1e-6:
            raise ValueError("`reward_fn` must return finite per-step rewards in [-1, 1].")
        cost = ((1 - rewards) / 2).sum(1)
        has_agents = rollout.controlled.any(1)
        cost = torch.where(has_agents, cost, torch.full_like(cost, float("nan")))
        mean_reward = torch.where(has_agents, rewards.mean(1), torch.full_like(cost, float("nan")))
        return MetricResult(values={"reward_cost": nanmean(cost), "reward_mean": nanmean(mean_reward)},
                            per_scene={"reward_cost": cost})
