"""The policy protocol the simulator drives, and three built-in policies for baselines and tests."""

from __future__ import annotations

from typing import NamedTuple, Protocol, runtime_checkable

import torch

from trafficrlhf_sdk.errors import ScenarioValidationError
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["ClosedLoopPolicy", "ConstantVelocityPolicy", "LogReplayPolicy", "NoisyLogPolicy", "Plan", "policy_seed",
           "seed_policy"]


class Plan(NamedTuple):
    """What a policy returns at a replanning step.

    states: float32 ``(B, A, H, 4)`` planned (x, y, speed, yaw) for the H steps after "now", scene frame.
    valid: optional bool ``(B, A, H)``; None means every planned step is valid.
    """

    states: torch.Tensor
    valid: torch.Tensor | None = None


@runtime_checkable
class ClosedLoopPolicy(Protocol):
    """Anything the simulator can drive: ``reset`` once per rollout, then ``plan`` at every replanning step.

    ``reset(scenario)`` receives the full logged scenario (log replay and guidance heuristics need the logged
    future; models must not condition on it). ``plan(context, horizon)`` receives the simulated past up to now
    (``context.current_index`` = now, absolute step index in the scene) and returns a :class:`Plan` of at least
    ``horizon`` steps for every agent (only controlled agents' plans are executed).
    """

    def reset(self, scenario: ScenarioTensor) -> None:
        """Start a new rollout of ``scenario`` (the whole logged scene, ``(B, A, T)``)."""

    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """States ``(B, A, horizon, 4)`` after ``context.current_index``, from the simulated past only."""


def seed_policy(policy: ClosedLoopPolicy, seed: int) -> None:
    """Set the sampling seed of ``policy`` where it has one (adapters' ``options.seed``, ``NoisyLogPolicy.seed``);
    deterministic policies have none. ``reset`` re-seeds the sampler from it at every rollout."""
    options = getattr(policy, "options", None)
    if options is not None and hasattr(options, "seed"):
        policy.options = options.model_copy(update={"seed": seed})  # type: ignore[attr-defined]
    elif isinstance(getattr(policy, "seed", None), int):
        policy.seed = seed  # type: ignore[attr-defined]


def policy_seed(policy: ClosedLoopPolicy, default: int) -> int:
    """The sampling seed ``policy`` was built with (``default`` for a policy without one)."""
    options = getattr(policy, "options", None)
    value = getattr(options, "seed", None) if options is not None else getattr(policy, "seed", None)
    return value if isinstance(value, int) else default


class LogReplayPolicy:
    """Replays the logged future (including its validity), so a rollout reproduces the log exactly."""

    name = "log_replay"

    def __init__(self) -> None:
        self._log: ScenarioTensor | None = None

    def reset(self, scenario: ScenarioTensor) -> None:
        """Remember the logged scenario."""
        self._log = scenario

    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """The logged states of steps ``now+1 .. now+horizon`` (invalid, zero, past the end of the log)."""
        if self._log is None:
            raise ScenarioValidationError("LogReplayPolicy.plan called before reset(scenario).")
        start = context.current_index + 1
        states = self._log.states[:, :, start : start + horizon]
        valid = self._log.valid[:, :, start : start + horizon]
        missing = horizon - states.shape[2]
        if missing > 0:
            states = torch.nn.functional.pad(states, (0, 0, 0, missing))
            valid = torch.nn.functional.pad(valid, (0, missing))
        return Plan(states, valid)


class ConstantVelocityPolicy:
    """Keeps each agent's current speed and heading (straight line). A zero-cost baseline."""

    name = "constant_velocity"

    def reset(self, scenario: ScenarioTensor) -> None:
        """Nothing to remember."""

    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """Straight-line extrapolation ``(B, A, horizon, 4)`` from the current state."""
        now = context.states[:, :, context.current_index]  # (B, A, 4)
        steps = torch.arange(1, horizon + 1, dtype=now.dtype, device=now.device) * context.dt
        travel = now[..., 2:3] * steps  # (B, A, H)
        heading = now[..., 3:4]
        x = now[..., 0:1] + travel * torch.cos(heading)
        y = now[..., 1:2] + travel * torch.sin(heading)
        return Plan(torch.stack([x, y, now[..., 2:3].expand_as(x), heading.expand_as(x)], -1))


class NoisyLogPolicy:
    """The logged future with a smooth random lateral/longitudinal perturbation that grows with time.

    Args:
        position_noise_m: standard deviation (m) of the offset reached after ``ramp_s`` seconds.
        ramp_s: time (s) over which the offset ramps up linearly from 0.
        seed: seed of the perturbation (the same seed gives the same rollout).
    """

    name = "noisy_log"

    def __init__(self, position_noise_m: float = 1.0, ramp_s: float = 5.0, seed: int = 0) -> None:
        if position_noise_m < 0 or ramp_s <= 0:
            raise ValueError(
                f"`position_noise_m` must be >= 0 and `ramp_s` > 0; got {position_noise_m}, {ramp_s}."
            )
        self.position_noise_m = position_noise_m
        self.ramp_s = ramp_s
        self.seed = seed
        self._log = LogReplayPolicy()
        self._offset: torch.Tensor | None = None

    def reset(self, scenario: ScenarioTensor) -> None:
        """Draw one offset direction per agent (seeded)."""
        self._log.reset(scenario)
        generator = torch.Generator().manual_seed(self.seed)
        self._offset = torch.randn(scenario.num_scenes, scenario.num_agents, 2, generator=generator).to(
            scenario.device
        )
        self._start = scenario.current_index

    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """Logged states shifted by an offset that ramps up with the time since the rollout started."""
        plan = self._log.plan(context, horizon)
        assert self._offset is not None
        steps = torch.arange(1, horizon + 1, device=context.device) + context.current_index - self._start
        ramp = (steps * context.dt / self.ramp_s).clamp(max=1.0).to(plan.states.dtype)  # (H,)
        shift = self.position_noise_m * self._offset[:, :, None, :] * ramp[None, None, :, None]
        states = plan.states.clone()
        states[..., :2] += shift
        return Plan(states, plan.valid)
