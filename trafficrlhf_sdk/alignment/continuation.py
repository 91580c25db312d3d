"""Closed-loop continuations of sampled futures: what executing the first steps of a sample leads to once the
model replans, for rewards that credit a plan with its closed-loop consequences.

In the evaluation protocol a plan is executed for 0.5 s and then replaced, so an open-loop score of the whole
sample is a proxy for what the executed part causes. :func:`continuation_scenarios` runs the proxy's missing
part: sample ``s``'s first ``executed`` steps are executed by the sampled agents, then the *current* model
drives them in closed loop (replanning every 0.5 s) for ``steps`` more steps while everyone else follows the
context's own continuation. The continuations of one context's samples share their random numbers (common
random numbers): each sample index runs the same batch with the sampling generator reseeded to the same value,
so two samples of a context differ by their executed steps alone and not by the noise of later plans.
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.simulation.guidance import GuidanceSet, guidance_swapped
from trafficrlhf_sdk.models.adapter import TrafficModelAdapter
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import Plan

__all__ = ["continuation_scenarios"]


class _ReseededPolicy:
    """``model`` as a closed-loop policy whose sampling generator restarts from ``seed`` at every reset."""

    def __init__(self, model: TrafficModelAdapter, seed: int) -> None:
        self.model = model
        self.seed = seed

    def reset(self, scenario: ScenarioTensor) -> None:
        self.model.reset(scenario)
        self.model._generator.manual_seed(self.seed)  # the generator the base class's plan() draws from

    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        return self.model.plan(context, horizon)


def continuation_scenarios(model: TrafficModelAdapter, contexts: ScenarioTensor, states: torch.Tensor,
                           valid: torch.Tensor, agents: torch.Tensor, executed: int, steps: int, seed: int,
                           guidance: GuidanceSet | None = None, replan_every: int = 5) -> ScenarioTensor:
    """``B * S`` scenarios (context-major), each ending ``executed + steps`` steps after the context's now.

    Args:
        model: the adapter being aligned; drives the continuations (no gradient).
        contexts: ``(B, A, T)`` contexts, ``current_index`` = now, with at least ``executed + steps`` steps after
            now (the non-sampled agents follow them).
        states, valid: ``(B, S, A, F, 4)`` / ``(B, S, A, F)`` futures after now, ``F >= executed + steps``: each
            sample for the sampled agents and the context's own steps for the others (as built by the trainer).
        agents: bool ``(B, A)``, the sampled agents: they execute ``executed`` steps of their sample, then the
            model drives them.
        executed: steps of each sample executed before the model takes over (5 = one 2 Hz replan).
        steps: closed-loop steps after that (0: the executed steps only).
        seed: the generator seed every sample index's continuation starts from (common random numbers).
        guidance: the guidance the model plans with in the continuation (None: its own).
        replan_every: steps executed from each plan of the continuation.

    Returns:
        ``B * S`` scenes whose ``current_index`` is the context's now: history, the executed steps, then the
        closed-loop continuation; ``controlled`` = ``agents``.
    """
    from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

    b, s = states.shape[:2]
    now, dt = contexts.current_index, contexts.dt
    total = executed + steps
    if states.shape[3] < total:
        raise ValueError(f"`states` holds {states.shape[3]} future steps; the continuation needs executed + steps "
                         f"= {total}. Keep more future steps in the contexts.")
    base = contexts.replace_unchecked(controlled=agents)
    policy = _ReseededPolicy(model, seed)
    per_sample: list[ScenarioTensor] = []
    with guidance_swapped(model, guidance):
        for k in range(s):
            scene = base.with_future(states[:, k, :, :total], valid[:, k, :, :total])
            if steps == 0:
                per_sample.append(scene)
                continue
            config = SimulationConfig(duration_s=steps * dt, start_index=now + executed, replan_every=replan_every,
                                      plan_horizon=replan_every, remove_offroad_at_start=False)
            with torch.no_grad():
                rollout = simulate(policy, scene, config)
            per_sample.append(rollout.simulated.replace_unchecked(current_index=now, controlled=agents))
    order = torch.arange(b * s).reshape(s, b).T.reshape(-1)  # sample-major -> context-major
    return ScenarioTensor.concat(per_sample)[order]
