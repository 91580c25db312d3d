"""The scenarios an :class:`~trafficrlhf_sdk.alignment.AlignTrainer` scores: each sample's future spliced into its
context (sampled agents take the sample, everyone else the log), optionally driven on in closed loop by the model
(``continue_s``), cut to the window the reward model scores."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import torch

from trafficrlhf_sdk.alignment.config import REWARD_HISTORY_STEPS
from trafficrlhf_sdk.models.adapter import extend_constant_velocity
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.simulation.guidance import guidance_swapped
from trafficrlhf_sdk.simulation.policies import policy_seed, seed_policy
from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

__all__ = ["SampleScenarios"]


class SampleScenarios:
    """Scenario building mixed into :class:`~trafficrlhf_sdk.alignment.AlignTrainer`, whose ``model``,
    ``guidance``, ``horizon`` (the model's sample steps), ``continue_steps`` (closed-loop steps after them),
    ``future_steps`` (their sum) and ``reward_steps`` (future steps the reward sees) it reads. Shapes: contexts
    ``(B, A, T)``; futures ``(B, S, A, H, 4)`` (x, y m, speed m/s, yaw rad); agents bool ``(B, A)``, the sampled
    agents."""

    model: Any
    guidance: Any
    horizon: int
    continue_steps: int
    future_steps: int
    reward_steps: int

    def _future_states(self, contexts: ScenarioTensor, futures: torch.Tensor,
                       agents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(states (B, S, A, F, 4), valid (B, S, A, F))``: sample ``s``'s future (extended to ``future_steps``
        at constant velocity) for the sampled ``agents (B, A)``, the logged future for every other agent."""
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

    def _continued(self, contexts: ScenarioTensor, states: torch.Tensor, valid: torch.Tensor, agents: torch.Tensor,
                   seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``states, valid (B, S, A, F, ...)`` with the steps after the model's horizon driven in closed loop: the
        model (no gradient, the trainer's guidance, replanning at 2 Hz) drives the sampled ``agents`` on from the
        end of each sample, the log drives everyone else. Sample index ``s`` of every context runs as one batch
        from the same ``seed``, so one context's continuations share their random numbers (common random
        numbers: they differ by where their samples left the agents)."""
        c, h, now = self.continue_steps, self.horizon, contexts.current_index
        if c == 0 or not bool(agents.any()):
            return states, valid
        # a sample that ended off the road keeps its agent driven; log agents appearing later replay; a driven
        # agent outlives its logged track, as in the sample itself
        config = SimulationConfig(duration_s=c * contexts.dt, start_index=now + h, remove_offroad_at_start=False,
                                  late_agents="replay", after_log_end="continue")
        states, valid = states.clone(), valid.clone()
        with torch.no_grad(), guidance_swapped(self.model, self.guidance), _seeded(self.model, seed):
            for k in range(states.shape[1]):
                scene = contexts.with_future(states[:, k], valid[:, k]).replace_unchecked(controlled=agents)
                driven = simulate(self.model, scene, config).simulated
                states[:, k, :, h:] = driven.states[:, :, now + 1 + h:].to(states.dtype)
                valid[:, k, :, h:] = driven.valid[:, :, now + 1 + h:]
        return states * valid[..., None], valid

    def sample_scenarios(self, contexts: ScenarioTensor, futures: torch.Tensor, agents: torch.Tensor,
                         seed: int = 0) -> ScenarioTensor:
        """``B * S`` scenarios (context-major): each context's history, then sample ``s``'s future for the
        sampled ``agents (B, A)`` and the logged future for every other agent, continued in closed loop for
        ``continue_steps`` from ``seed``; cut to the reward window."""
        states, valid = self._future_states(contexts, futures, agents)
        return self._scenarios(contexts, *self._continued(contexts, states, valid, agents, seed))


@contextlib.contextmanager
def _seeded(policy: Any, seed: int) -> Iterator[None]:
    """Inside the block ``policy`` samples from ``seed`` (re-seeded at every rollout's reset); its own seed after."""
    previous = policy_seed(policy, seed)
    seed_policy(policy, seed)
    try:
        yield
    finally:
        seed_policy(policy, previous)
