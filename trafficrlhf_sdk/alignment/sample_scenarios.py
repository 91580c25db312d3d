"""The scenarios an :class:`~trafficrlhf_sdk.alignment.AlignTrainer` scores: each sample's future spliced into its
context (sampled agents take the sample, everyone else the log), the counterfactual variants where one agent
varies at a time, and each context's winning samples for reward-ranked imitation."""

from __future__ import annotations

import torch

from trafficrlhf_sdk.reward.scoring import agent_scores
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
        return scenario.time_slice(max(0, now - self.config.reward_history_steps), now + 1 + self.reward_steps)

    def sample_scenarios(self, contexts: ScenarioTensor, futures: torch.Tensor,
                         agents: torch.Tensor) -> ScenarioTensor:
        """``B * S`` scenarios (context-major): each context's history, then sample ``s``'s future for the
        sampled ``agents (B, A)`` and the logged future for every other agent; cut to the reward window."""
        return self._scenarios(contexts, *self._future_states(contexts, futures, agents))

    def counterfactual_scenarios(self, contexts: ScenarioTensor, futures: torch.Tensor, agents: torch.Tensor,
                                 context: int) -> tuple[ScenarioTensor, torch.Tensor]:
        """``(scenarios, slots)`` for context ``context``: ``M * S`` scenarios (sampled agent-major) where its
        ``m``-th sampled agent (agent index ``slots[m]``) takes sample ``s`` and every other sampled agent sample
        0 (the rest the log), cut to the reward window. The copies share the context's map (expanded views), so
        a large raster is not copied M * S times."""
        slots = agents[context].nonzero().flatten()  # (M,)
        m, s = slots.numel(), futures.shape[1]
        scene = contexts[context]  # (B = 1): indexing copies the raster once
        states, valid = self._future_states(scene, futures[context: context + 1],
                                            agents[context: context + 1])  # (1, S, A, H, 4)
        states, valid = states[0], valid[0]
        own = slots[:, None] == torch.arange(states.shape[1])[None, :]  # (M, A): the agent that varies
        mixed = torch.where(own[:, None, :, None, None], states[None], states[None, :1])  # (M, S, A, H, 4)
        repeated = scene.repeat_scenes(m * s)
        scenario = repeated.with_future(mixed.reshape(m * s, *mixed.shape[2:]),
                                        valid[None].expand(m, *valid.shape).reshape(m * s, *valid.shape[1:]))
        now = contexts.current_index
        return scenario.time_slice(max(0, now - self.config.reward_history_steps), now + 1 + self.reward_steps), slots

    def _counterfactual_agent_scores(self, contexts: ScenarioTensor, futures: torch.Tensor, agents: torch.Tensor,
                                     reference: ScenarioTensor | None) -> torch.Tensor:
        """``(B, S, A)`` per-agent scores from :meth:`counterfactual_scenarios` (0 for agents not sampled);
        ``reference``: one window of the log per context, for rewards that compare with it."""
        b, s, a = futures.shape[:3]
        out = torch.zeros(b, s, a)
        for c in range(b):
            if not agents[c].any():
                continue
            scenarios, slots = self.counterfactual_scenarios(contexts, futures, agents, c)
            m = slots.numel()
            ref = None if reference is None else reference[c].repeat_scenes(m * s)
            scores = agent_scores(self.reward_model, scenarios, ref).reshape(m, s, a)
            out[c][:, slots] = scores[torch.arange(m), :, slots].T.to(out.dtype)  # (S, M): agent m's own score
        return out

    def winner_scenarios(self, contexts: ScenarioTensor, futures: torch.Tensor, agents: torch.Tensor,
                         rewards: torch.Tensor) -> ScenarioTensor:
        """Each context with, per sampled agent, the future of its highest-reward sample, as a scene of the
        model's history length + 1 + horizon steps (``current_index`` = its history length).

        Args:
            contexts: ``(B, A, T)`` contexts; futures: ``(B, S, A, H, 4)`` samples; agents: bool ``(B, A)``
                sampled agents; rewards: ``(B, S, A)`` per-agent rewards (a scene reward repeated over agents).

        Only agents whose best reward beats their worst by more than ``winner_min_gap`` keep a valid future;
        every other agent is valid in the history only, so the imitation loss learns from the winners alone.
        """
        now, h = contexts.current_index, futures.shape[-2]
        gap = rewards.amax(1) - rewards.amin(1)  # (B, A)
        keep = agents & (gap > self.config.winner_min_gap)
        choice = rewards.argmax(1)  # (B, A)
        index = choice[:, None, :, None, None].expand(-1, 1, -1, h, futures.shape[-1])
        best = futures.detach().gather(1, index)[:, 0].to(contexts.states.dtype)  # (B, A, H, 4)
        best = torch.cat([best[..., :3], wrap_angle(best[..., 3:])], -1) * keep[..., None, None]
        history = int(getattr(self.model, "history_steps", self.config.reward_history_steps))
        start = max(0, now - history)
        history_part = contexts.time_slice(start, now + 1)
        valid = torch.cat([history_part.valid, keep[:, :, None].expand(-1, -1, h)], 2)
        # an agent may be valid neither in this short history nor as a winner: it is no longer "controlled"
        return history_part.replace_unchecked(states=torch.cat([history_part.states, best], 2), valid=valid,
                                              controlled=history_part.controlled & valid.any(-1))
