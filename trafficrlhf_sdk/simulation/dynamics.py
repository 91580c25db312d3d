"""Batched, differentiable unicycle dynamics with the bounds used by tbsim/CTG.

State ``(x, y, v, yaw)`` in metres, m/s and radians; action ``(acceleration m/s^2, yaw rate rad/s)``.
One step (tbsim ``Unicycle.step``, see shared/reference/upstream-models-and-metrics.md §2.4)::

    x' = x + dt * cos(yaw) * (v + a * dt / 2)
    y' = y + dt * sin(yaw) * (v + a * dt / 2)
    v' = v + dt * a
    yaw' = yaw + dt * w

with the action first clipped to state-dependent bounds. Leading dimensions are free (``...``).
"""

from __future__ import annotations

import math

import torch
from pydantic import BaseModel, ConfigDict, Field

__all__ = ["UnicycleBounds", "action_bounds", "unicycle_rollout", "unicycle_step", "wrap_angle"]


class UnicycleBounds(BaseModel):
    """Action and speed bounds. Defaults are the values CTG's configs set (tbsim class defaults differ)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    acc_min: float = Field(-10.0, description="Lowest acceleration (m/s^2).")
    acc_max: float = Field(8.0, description="Highest acceleration (m/s^2).")
    max_yaw_rate: float = Field(2 * math.pi, description="Yaw-rate cap at low speed, divided by |v| (rad/s).")
    max_steer: float = Field(0.5, description="Yaw-rate cap per unit speed (rad/m), i.e. |w| <= max_steer * |v|.")
    v_min: float = Field(-10.0, description="Lowest speed the dynamics allow (m/s).")
    v_max: float = Field(30.0, description="Highest speed the dynamics allow (m/s).")


DEFAULT_BOUNDS = UnicycleBounds()


def wrap_angle(angle: torch.Tensor) -> torch.Tensor:
    """Wrap angles (rad, any shape) to [-pi, pi)."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


def action_bounds(
    speed: torch.Tensor, bounds: UnicycleBounds = DEFAULT_BOUNDS
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper action bounds ``(..., 2)`` for speeds ``(...)`` (m/s)."""
    v_clip = speed.abs().clamp_min(0.1)
    yaw_bound = torch.minimum(bounds.max_steer * v_clip, bounds.max_yaw_rate / v_clip).clamp_min(0.1)
    acc_lb = (bounds.v_min - speed).clamp(max=bounds.acc_max).clamp(min=bounds.acc_min)
    acc_ub = (bounds.v_max - speed).clamp(min=bounds.acc_min).clamp(max=bounds.acc_max)
    return torch.stack([acc_lb, -yaw_bound], -1), torch.stack([acc_ub, yaw_bound], -1)


def unicycle_step(
    state: torch.Tensor, action: torch.Tensor, dt: float = 0.1, bounds: UnicycleBounds | None = DEFAULT_BOUNDS
) -> torch.Tensor:
    """Advance ``state (..., 4)`` by one step of ``dt`` s under ``action (..., 2)``; returns ``(..., 4)``.

    ``bounds=None`` disables clipping. Yaw is wrapped to [-pi, pi). Differentiable in state and action
    (clipping passes zero gradient outside the bounds, as ``torch.clamp`` does).
    """
    x, y, v, yaw = state.unbind(-1)
    if bounds is not None:
        lb, ub = action_bounds(v, bounds)
        action = torch.maximum(torch.minimum(action, ub), lb)
    acc, yaw_rate = action.unbind(-1)
    travel = dt * (v + 0.5 * dt * acc)
    return torch.stack(
        [x + travel * torch.cos(yaw), y + travel * torch.sin(yaw), v + dt * acc, wrap_angle(yaw + dt * yaw_rate)],
        -1,
    )


def unicycle_rollout(
    initial_state: torch.Tensor,
    actions: torch.Tensor,
    dt: float = 0.1,
    bounds: UnicycleBounds | None = DEFAULT_BOUNDS,
) -> torch.Tensor:
    """Roll ``initial_state (..., 4)`` through ``actions (..., H, 2)``; returns the H next states ``(..., H, 4)``.

    With ``bounds=None`` the rollout is closed-form (cumulative sums), otherwise it loops over H because the
    bounds depend on the running speed.
    """
    if bounds is None:
        acc, yaw_rate = actions.unbind(-1)
        v0, yaw0 = initial_state[..., 2:3], initial_state[..., 3:4]
        v = v0 + dt * torch.cumsum(acc, -1)
        yaw_unwrapped = yaw0 + dt * torch.cumsum(yaw_rate, -1)
        v_prev = torch.cat([v0, v[..., :-1]], -1)
        yaw_prev = torch.cat([yaw0, yaw_unwrapped[..., :-1]], -1)
        travel = dt * (v_prev + 0.5 * dt * acc)
        x = initial_state[..., 0:1] + torch.cumsum(travel * torch.cos(yaw_prev), -1)
        y = initial_state[..., 1:2] + torch.cumsum(travel * torch.sin(yaw_prev), -1)
        return torch.stack([x, y, v, wrap_angle(yaw_unwrapped)], -1)
    states = []
    state = initial_state
    for t in range(actions.shape[-2]):
        state = unicycle_step(state, actions[..., t, :], dt, bounds)
        states.append(state)
    return torch.stack(states, -2)
