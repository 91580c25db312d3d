"""The scenarios an :class:`~trafficrlhf_sdk.alignment.AlignTrainer` scores: each sample's future spliced into its
context (sampled agents take the sample, everyone else the log), cut to the window the reward model scores."""

from __future__ import annotations

import torch

from trafficrlhf_sdk.alignment.config import REWARD_HISTORY_STEPS
from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.models.adapter import extend_constant_velocity
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["SampleScenarios"]


class SampleScenarios:
    """Scenario building mixed into :class:`~trafficrlhf_sdk.alignment.AlignTrainer`, whose ``model``,
    ``reward_model``, ``config``, ``future_steps`` (steps a sample is extended to) and ``reward_steps`` (future
    steps the reward sees) it reads. Shapes: contexts ``(B, A, T)``; futures ``(B, S, A, H, 4)`` (x, y m, speed
    m/s, yaw rad); agents bool ``(B, A)``, the sampled agents."""

    def _future_states(self, contexts: ScenarioTensor, futures: torch.Tensor,
                       agents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(states (B, S, A, H, 4), valid (B, S, A, H))``: sample ``s``'s future (extended to the reward
        horizon) for the sampled ``agents (B, A)``, the logged future for every other agent."""
        b, s = futures.shape[:2]
        now, h = contexts.current_index, self.future_steps
        futures = extend_constant_velocity(futures.detach(), h, contexts.dt).to(contexts.states.dtype)
        futures = torch.cat([futures[..., :3], wrap_angle(futures[..., 3:])], -1)
        log_states = contexts.states[:, :, now + 1: now + 1 + h]
        log_valid = contexts.valid[:, :, now + 1: now + 1 + h]
        pick = agents[:, None, :, None]  # (B, 1, A, 1)
        states = torch.where(pick[..., None], futures, log_states[:, None])  # (B, S, A, H, 4)
        valid = torch.where(pick, torch.ones_like(log_valid[:, None]), log_valid[:, None]).expand(b, s, -1, -1)
        return states * valid[..., None], valid

    def _scenarios(self, contexts: ScenarioTensor, states: torch.Tensor, valid: torch.Tensor) -> ScenarioTensor:
        """One scenario per row of ``states (B, R, A, H, 4)`` (context-major): the context's history, then that
        future; cut to the reward window."""
        b, r = states.shape[:2]
        scenario = contexts.repeat_scenes(r).with_future(states.reshape(b * r, *states.shape[2:]),
                                                         valid.reshape(b * r, *valid.shape[2:]))
        now = contexts.current_index
        return scenario.time_slice(max(0, now - REWARD_HISTORY_STEPS), now + 1 + self.reward_steps)

    def sample_scenarios(self, contexts: ScenarioTensor, futures: torch.Tensor,
                         agents: torch.Tensor) -> ScenarioTensor:
        """``B * S`` scenarios (context-major): each context's history, then sample ``s``'s future for the
        sampled ``agents (B, A)`` and the logged future for every other agent; cut to the reward window."""
        return self._scenarios(contexts, *self._future_states(contexts, futures, agents))
