"""How the fine-tuner reads a reward model: scene scores ``(B,)`` and per-agent scores ``(B, A)``, checked for
shape and finiteness, so a broken reward model fails with one clear error instead of a NaN loss later."""

from __future__ import annotations

from typing import Any, Protocol

import torch

from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["RewardLike", "agent_scores", "scenario_scores"]


class RewardLike(Protocol):
    """What the fine-tuner needs from a reward model: per-step rewards ``(B, T)`` in [-1, 1] of a scenario."""

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:  # pragma: no cover - protocol
        """Per-step rewards ``(B, T)`` in [-1, 1]."""


def scenario_scores(reward_model: Any, scenario: ScenarioTensor) -> torch.Tensor:
    """Scenario rewards ``(B,)``: the model's own ``score`` if it has one (a
    :class:`~trafficrlhf_sdk.reward.RewardModel`), else the mean of ``step_rewards`` over the steps after
    ``current_index``; a plain callable is treated as a per-step reward function ``(B, T)``."""
    with torch.no_grad():
        if callable(getattr(reward_model, "score", None)):
            scores = reward_model.score(scenario)
        else:
            fn = getattr(reward_model, "step_rewards", None) or reward_model
            if not callable(fn):
                raise TypeError("`reward_model` needs a `step_rewards(scenario) -> (B, T)` method (or a `score` "
                                f"method); got {type(reward_model).__name__}.")
            per_step = fn(scenario)
            if per_step.shape != (scenario.num_scenes, scenario.num_steps):
                raise ValueError(f"step_rewards returned shape {tuple(per_step.shape)}; expected (B, T) = "
                                 f"({scenario.num_scenes}, {scenario.num_steps}).")
            scores = per_step[:, scenario.current_index + 1:].float().mean(1)
    return _checked(scores, (scenario.num_scenes,), "score", "(B,)")


def agent_scores(reward_model: Any, scenario: ScenarioTensor, logged: ScenarioTensor | None = None) -> torch.Tensor:
    """Per-agent rewards ``(B, A)`` from the reward model's ``agent_scores`` (0 for agents it does not score).
    ``logged`` (the same scenarios with the logged future) is passed to rewards that set ``uses_log``."""
    with torch.no_grad():
        if getattr(reward_model, "uses_log", False):
            scores = reward_model.agent_scores(scenario, logged=logged)
        else:
            scores = reward_model.agent_scores(scenario)
    return _checked(scores, (scenario.num_scenes, scenario.num_agents), "agent_scores", "(B, A)")


def _checked(scores: torch.Tensor, shape: tuple[int, ...], method: str, names: str) -> torch.Tensor:
    """``scores`` as float32 on the CPU, after checking its shape and that it is finite."""
    if tuple(scores.shape) != shape:
        raise ValueError(f"the reward model's {method} returned shape {tuple(scores.shape)}; expected {names} = "
                         f"{shape}.")
    scores = scores.detach().float().cpu()
    if not torch.isfinite(scores).all():
        raise ValueError(f"the reward model's {method} returned non-finite values.")
    return scores
