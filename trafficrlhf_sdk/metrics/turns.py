"""Which agents turn in the log: the split the speed and failure metrics report turning and straight agents by."""

from __future__ import annotations

import torch

from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.dynamics import wrap_angle

__all__ = ["TURN_RAD", "turning_agents"]

TURN_RAD = 0.6  # an agent whose logged heading changes by more than this over the rollout turns (about 34 degrees)


def turning_agents(logged: ScenarioTensor, steps: torch.Tensor) -> torch.Tensor:
    """``(B, A)``: agents whose logged heading at their last step of ``steps (B, A, T)`` (steps of ``logged``)
    differs from that at their first by more than :data:`TURN_RAD`."""
    t = torch.arange(steps.shape[-1], device=steps.device)
    first = torch.where(steps, t, steps.shape[-1]).amin(-1).clamp_max(steps.shape[-1] - 1)
    last = torch.where(steps, t, -1).amax(-1).clamp_min(0)
    yaw = logged.states[..., 3].double()
    turn = wrap_angle(yaw.gather(-1, last[..., None]) - yaw.gather(-1, first[..., None]))[..., 0]
    return steps.any(-1) & (turn.abs() > TURN_RAD)
