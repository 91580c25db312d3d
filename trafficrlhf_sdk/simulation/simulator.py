"""Batched closed-loop simulator (CTG's protocol: 3 s history, 10 s at 0.1 s, replan every 0.5 s)."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator

from trafficrlhf_sdk.errors import ScenarioValidationError
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import ClosedLoopPolicy, LogReplayPolicy

__all__ = ["Rollout", "SimulationConfig", "log_rollout", "simulate"]


class SimulationConfig(BaseModel):
    """How a closed-loop rollout runs. Defaults follow CTG's ``SceneEditingConfig`` (see shared/reference §1.5)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    duration_s: float = Field(10.0, gt=0, description="Simulated time after the start step (s).")
    replan_every: int = Field(5, ge=1, description="Steps executed from each plan before replanning (5 = 2 Hz).")
    plan_horizon: int = Field(
        5, ge=1, description="Steps requested from the policy at each replan (>= replan_every; models may plan more)."
    )
    start_index: int | None = Field(
        None, ge=1, description="Step the rollout starts from; None uses the scenario's current_index (3 s)."
    )
    remove_offroad_at_start: bool = Field(
        True, description="Agents whose centre is off the drivable layer at the start are not controlled (upstream)."
    )
    late_agents: Literal["drop", "replay"] = Field(
        "drop", description="Agents absent from the log at the start step: 'drop' (upstream CTG, whose simulation "
        "freezes the set of agents at the start) leaves them out of the rollout, so they are neither context nor "
        "collision partners; 'replay' replays them from the log from the step they appear."
    )
    after_log_end: Literal["end", "continue"] = Field(
        "end", description="A driven agent after the last step of its logged track: 'end' (default) removes it "
        "from the scene from then on, so no metric counts it where neither the log nor the map says it could "
        "be; 'continue' (upstream) keeps driving it to the end of the rollout."
    )

    @model_validator(mode="after")
    def _horizon_covers_replan(self) -> SimulationConfig:
        if self.plan_horizon < self.replan_every:
            raise ValueError(
                f"`plan_horizon` ({self.plan_horizon}) must be >= `replan_every` ({self.replan_every}): each plan "
                "must cover the steps executed before the next replan; raise `plan_horizon`."
            )
        return self


@dataclass(frozen=True)
class Rollout:
    """Result of a closed-loop run over a batch of scenes.

    Fields:
        simulated: the scene with simulated states, steps ``0 .. end_index`` (history is the log).
        logged: the logged scene cut to the same steps (``valid`` False where the log has no data).
        controlled: bool ``(B, A)``: agents the policy drove (after removing off-road starters).
        start_index, end_index: the rollout covers steps ``start_index+1 .. end_index`` (inclusive).
        wall_time_s: seconds spent in the loop, policy included; ``policy_time_s``: in ``policy.plan``.
    """

    simulated: ScenarioTensor
    logged: ScenarioTensor
    controlled: torch.Tensor
    start_index: int
    end_index: int
    wall_time_s: float = 0.0
    policy_time_s: float = 0.0

    @property
    def num_steps(self) -> int:
        """Simulated steps per agent."""
        return self.end_index - self.start_index

    def window(self, which: str = "simulated") -> ScenarioTensor:
        """Steps ``start_index .. end_index`` (inclusive) of the simulated or logged scene."""
        scenario = self.simulated if which == "simulated" else self.logged
        return scenario.time_slice(self.start_index, self.end_index + 1)


def _prepare(scenario: ScenarioTensor, config: SimulationConfig) -> tuple[ScenarioTensor, torch.Tensor, int, int]:
    start = config.start_index if config.start_index is not None else scenario.current_index
    steps = round(config.duration_s / scenario.dt)
    end = start + steps
    if start >= scenario.num_steps:
        raise ScenarioValidationError(
            f"start step {start} is outside the scenario's {scenario.num_steps} steps; lower `start_index`."
        )
    if end >= scenario.num_steps:  # pad the log with invalid steps so every tensor covers the window
        pad = end + 1 - scenario.num_steps
        scenario = scenario.replace_unchecked(
            states=torch.nn.functional.pad(scenario.states, (0, 0, 0, pad)),
            valid=torch.nn.functional.pad(scenario.valid, (0, pad)),
        )
    logged = scenario.time_slice(0, end + 1)
    logged = logged.replace_unchecked(current_index=start)
    if config.late_agents == "drop":
        present = logged.valid[:, :, start]
        valid = logged.valid.clone()
        valid[:, :, start + 1 :] &= present[:, :, None]
        logged = logged.replace_unchecked(valid=valid)
    controlled = logged.controlled & logged.valid[:, :, start]
    if config.remove_offroad_at_start and logged.map is not None and "drivable" in logged.map.layers:
        candidates = controlled
        controlled = controlled & logged.map.lookup(logged.xy[:, :, start].double())  # as the off-road metric
        lost = (candidates.any(-1) & ~controlled.any(-1)).nonzero().flatten().tolist()
        if lost:
            names = [str(logged.scene_ids[i]) if i < len(logged.scene_ids) else str(i) for i in lost]
            warnings.warn(f"{len(lost)} scene(s) lose every controlled agent because none starts on the drivable "
                          f"layer of its map: {', '.join(names[:10])}{' ...' if len(names) > 10 else ''} (source "
                          f"{logged.source!r}); their metrics are empty. Check the map files' origin and scale.",
                          stacklevel=3)
    return logged, controlled, start, end


def _alive(logged: ScenarioTensor, config: SimulationConfig) -> torch.Tensor:
    """bool ``(B, A, T)``: steps at which a driven agent may exist: up to the last valid step of its logged track
    (``after_log_end="end"``), or every step (``"continue"``)."""
    valid = logged.valid
    if config.after_log_end == "continue":
        return torch.ones_like(valid)
    steps = torch.arange(valid.shape[-1], device=valid.device)
    last = torch.where(valid, steps, torch.full_like(steps, -1)).amax(-1)  # (B, A); -1: never valid
    return steps <= last[..., None]


def simulate(
    policy: ClosedLoopPolicy,
    scenario: ScenarioTensor,
    config: SimulationConfig | None = None,
    progress: bool = False,
) -> Rollout:
    """Run ``policy`` in closed loop on every scene of ``scenario`` at once.

    At each replanning step t the policy sees the simulated past (steps 0..t) and returns a plan; the
    controlled agents execute its first ``replan_every`` steps, the others replay the log. One batched
    ``policy.plan`` call covers all scenes and agents.

    Args:
        policy: any :class:`ClosedLoopPolicy` (built-in policies, traffic-model adapters).
        scenario: logged scenes ``(B, A, T)`` with at least ``current_index`` steps of history.
        config: :class:`SimulationConfig`; defaults to CTG's protocol.
        progress: show a progress bar over replanning steps.

    Returns:
        A :class:`Rollout` holding the simulated and logged scenes over the same steps.
    """
    config = config or SimulationConfig()
    if config.plan_horizon < config.replan_every:
        raise ValueError(
            f"`plan_horizon` ({config.plan_horizon}) must be >= `replan_every` ({config.replan_every}); raise it."
        )
    logged, controlled, start, end = _prepare(scenario, config)
    policy.reset(logged)
    states = logged.states.clone()
    valid = logged.valid.clone()
    # controlled agents exist for the whole rollout (or until their logged track ends) unless their plan says
    # otherwise
    alive = _alive(logged, config)
    valid[:, :, start + 1 :] |= controlled[:, :, None] & alive[:, :, start + 1 :]
    scene_of, agent_of = controlled.nonzero(as_tuple=True)  # controlled rows: only they take the plan

    replans = range(start, end, config.replan_every)
    if progress:
        from trafficrlhf_sdk.console import progress as progress_bar

        replans = progress_bar(replans, desc="closed loop", unit="replan", leave=False)
    began = time.perf_counter()
    policy_time = 0.0
    for t in replans:
        context = logged.replace_unchecked(states=states[:, :, : t + 1], valid=valid[:, :, : t + 1], current_index=t)
        tic = time.perf_counter()
        plan = policy.plan(context, config.plan_horizon)
        policy_time += time.perf_counter() - tic
        n = min(config.replan_every, end - t)
        plan_states = getattr(plan, "states", None)
        if not isinstance(plan_states, torch.Tensor):
            raise ScenarioValidationError(
                f"policy {type(policy).__name__}.plan returned {type(plan).__name__}; expected a Plan(states, valid)."
            )
        planned = plan_states[:, :, :n]
        expected = (logged.num_scenes, logged.num_agents, n, 4)
        if planned.dim() != 4 or tuple(planned.shape) != expected:
            raise ScenarioValidationError(
                f"policy {type(policy).__name__} returned plan states of shape {tuple(plan_states.shape)}; expected "
                f"({logged.num_scenes}, {logged.num_agents}, >= {n}, 4)."
            )
        window = slice(t + 1, t + 1 + n)
        planned = planned.to(device=states.device, dtype=states.dtype)
        states[scene_of, agent_of, window] = planned[scene_of, agent_of]
        if plan.valid is not None:
            plan_valid = plan.valid[:, :, :n]
            if tuple(plan_valid.shape) != (logged.num_scenes, logged.num_agents, n) or plan_valid.dtype != torch.bool:
                raise ScenarioValidationError(
                    f"policy {type(policy).__name__} returned plan valid of shape {tuple(plan.valid.shape)} and dtype "
                    f"{plan.valid.dtype}; expected bool ({logged.num_scenes}, {logged.num_agents}, >= {n})."
                )
            valid[scene_of, agent_of, window] = plan_valid.to(valid.device)[scene_of, agent_of] \
                & alive[scene_of, agent_of, window]
    wall = time.perf_counter() - began
    # Only the controlled agents' simulated steps changed. Zero the steps their plans marked invalid with where()
    # (a policy may leave NaN there, and NaN * 0 is NaN), then require the valid ones to be finite.
    future = slice(start + 1, end + 1)
    driven = torch.where(valid[:, :, future][controlled][..., None], states[:, :, future][controlled],
                         torch.zeros((), dtype=states.dtype, device=states.device))  # (N controlled, steps, 4)
    if not torch.isfinite(driven).all():
        row, step = (int(v) for v in (~torch.isfinite(driven)).any(-1).nonzero()[0])
        scene, agent = (int(v) for v in controlled.nonzero()[row])
        raise ScenarioValidationError(
            f"policy {type(policy).__name__} produced NaN or inf states (first at scene {scene}, agent {agent}, "
            f"step {start + 1 + step}); return finite states for every valid planned step."
        )
    states[:, :, future][controlled] = driven
    simulated = logged.replace_unchecked(states=states, valid=valid, controlled=controlled)
    logged = logged.replace_unchecked(controlled=controlled)
    return Rollout(simulated, logged, controlled, start, end, wall, policy_time)


def log_rollout(scenario: ScenarioTensor, config: SimulationConfig | None = None) -> Rollout:
    """The logged data as a rollout (log replay), the reference every metric compares against."""
    return simulate(LogReplayPolicy(), scenario, config)
