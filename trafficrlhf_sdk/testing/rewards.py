"""Toy rewards for smoke-testing a fine-tuner on a new adapter: easy to learn, so a working ``align`` run must
raise them within a few epochs."""

from __future__ import annotations

import torch

from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["SlowDownReward"]


class SlowDownReward:
    """Per-step reward ``(B, T)`` in [-1, 1]: the mean speed drop (m/s, halved) of the controlled agents since
    ``current_index``, over agents valid now and at that step. A model that learns to brake scores higher."""

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        """``(B, T)`` speed drop of the controlled agents since ``current_index``, / 2 m/s, clipped to [-1, 1]."""
        now = scenario.current_index
        mask = (scenario.controlled[:, :, None] & scenario.valid & scenario.valid[:, :, now, None]).float()
        drop = (scenario.states[:, :, now, None, 2] - scenario.states[..., 2]) / 2.0
        return ((drop * mask).sum(1) / mask.sum(1).clamp_min(1)).clamp(-1, 1)
