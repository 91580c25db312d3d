"""The network: agent-centric encoder + autoregressive GRU decoder with a diagonal Gaussian head.

Everything here is plain PyTorch on tensors; :mod:`trafficrlhf_example_gru.adapter` turns a
:class:`~trafficrlhf_sdk.scenario.ScenarioTensor` into these tensors with the SDK's shared features.

Shapes: ``N`` is a flat batch of agents (scenes x samples x agents), ``H`` the number of decoded steps.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from trafficrlhf_sdk.simulation.dynamics import action_bounds, unicycle_step

__all__ = ["DecodeResult", "GRUConfig", "GRUPolicyNet"]

HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


class GRUConfig(BaseModel):
    """Architecture of :class:`GRUPolicyNet` (stored in ``config.json``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    horizon: int = Field(20, ge=1, description="Decoded steps (0.1 s each).")
    history_steps: int = Field(31, ge=1, description="History steps read up to now (incl. now), at 0.1 s.")
    history_stride: int = Field(5, ge=1, description="Keep every k-th history step (counted back from now).")
    num_neighbours: int = Field(8, ge=1, description="Nearest other agents encoded.")
    neighbour_radius_m: float = Field(40.0, gt=0, description="Neighbours farther than this are ignored (m).")
    use_map: bool = Field(True, description="Encode a low-resolution map crop around each agent.")
    map_layers: tuple[str, ...] = Field(("drivable", "road_divider", "lane_divider"), description="Crop channels.")
    map_size_px: int = Field(16, ge=4, description="Crop side (cells); a multiple of 4.")
    map_resolution_m: float = Field(2.0, gt=0, description="Crop cell size (m).")
    embed: int = Field(64, ge=8, description="Width of each encoder branch.")
    hidden: int = Field(96, ge=8, description="GRU hidden size.")
    action_scale: tuple[float, float] = Field(
        (1.0, 0.1), description="Typical |acceleration| (m/s^2) and |yaw rate| (rad/s)."
    )
    log_std_range: tuple[float, float] = Field((-3.0, 1.0), description="Bounds of log-std in action_scale units.")

    @property
    def history_points(self) -> int:
        """History steps actually encoded."""
        return len(range(self.history_steps - 1, -1, -self.history_stride))


def _mlp(inp: int, hidden: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inp, hidden), nn.ReLU(), nn.Linear(hidden, out), nn.ReLU())


class DecodeResult(NamedTuple):
    """Output of :meth:`GRUPolicyNet.decode`."""

    actions: torch.Tensor  # (N, H, 2) raw (unclipped) actions
    log_prob: torch.Tensor  # (N, H) Gaussian log-density of each action
    states: torch.Tensor  # (N, H, 4) rolled scene-frame states


class GRUPolicyNet(nn.Module):
    """Encoder (history MLP, neighbour set-MLP with max-pool, small map CNN) -> initial GRU state; a GRUCell
    decoder then emits, per step, a diagonal Gaussian over (acceleration, yaw rate).

    The mean is ``prev + gate * (target - prev)``: a learned per-step choice between keeping the previous
    (executed) action and moving to a new target. Logged nuScenes actions are piecewise constant over the 0.5 s
    between keyframes, so the decoder learns to keep within a keyframe interval and to switch at its end.
    """

    def __init__(self, config: GRUConfig) -> None:
        super().__init__()
        self.config = config
        e, h = config.embed, config.hidden
        self.history = _mlp(config.history_points * 6, e, e)
        self.neighbour = _mlp(8, e, e)
        branches = 2
        if config.use_map:
            c, s = len(config.map_layers), config.map_size_px
            self.map = nn.Sequential(
                nn.Conv2d(c, 8, 3, stride=2, padding=1), nn.ReLU(),
                nn.Conv2d(8, 16, 3, stride=2, padding=1), nn.ReLU(),
                nn.Flatten(), nn.Linear(16 * math.ceil(s / 4) ** 2, e), nn.ReLU(),
            )
            branches += 1
        self.fuse = nn.Sequential(nn.Linear(branches * e + 3, h), nn.Tanh())
        self.cell = nn.GRUCell(4, h)
        self.head = nn.Linear(h, 6)  # target (2), log-std (2), keep-or-switch gate (2)
        with torch.no_grad():  # start near "mean = half the previous action", mid-range spread
            self.head.weight.mul_(0.01)
            self.head.bias.zero_()
        self.register_buffer("action_scale", torch.tensor(config.action_scale, dtype=torch.float32))

    # ------------------------------------------------------------------ parts
    def encoder_modules(self) -> list[nn.Module]:
        """The modules of the encoder (for parameter groups)."""
        return [self.history, self.neighbour, *([self.map] if self.config.use_map else []), self.fuse]

    def decoder_modules(self) -> list[nn.Module]:
        """The modules of the decoder."""
        return [self.cell, self.head]

    def encode(self, history: torch.Tensor, neighbours: torch.Tensor, crops: torch.Tensor | None,
               current: torch.Tensor) -> torch.Tensor:
        """Initial hidden state ``(..., hidden)``.

        Args:
            history: ``(..., P, 6)`` normalized history features + valid flag.
            neighbours: ``(..., K, 8)`` normalized neighbour features + valid flag (invalid rows zero).
            crops: ``(..., C, S, S)`` map crops, or None when the config has no map.
            current: ``(..., 3)``: current speed / 10 and previous action in action_scale units.
        """
        lead = history.shape[:-2]
        parts = [self.history(history.flatten(-2))]
        nb = self.neighbour(neighbours)  # (..., K, E); ReLU output >= 0, so zeroing invalid rows is a masked max
        parts.append((nb * neighbours[..., -1:]).amax(-2))
        if self.config.use_map:
            assert crops is not None
            parts.append(self.map(crops.reshape(-1, *crops.shape[-3:])).reshape(*lead, -1))
        return self.fuse(torch.cat([*parts, current], -1))

    def decode(self, h0: torch.Tensor, state0: torch.Tensor, prev_action: torch.Tensor, dt: float,
               noise: torch.Tensor | None = None, actions: torch.Tensor | None = None) -> DecodeResult:
        """Roll the GRU for ``H`` steps, sampling (``noise (N, H, 2)``) or teacher-forced (``actions (N, H, 2)``).

        Each action moves the agent by one :func:`unicycle_step` (SDK bounds) from ``state0 (N, 4)``; the decoder
        sees the previous *executed* (clipped) action and the rolled speed. Returns the (raw, unclipped) actions,
        their Gaussian log-density per step ``(N, H)`` and the rolled states.
        """
        if (noise is None) == (actions is None):
            raise ValueError("pass exactly one of `noise` (sampling) or `actions` (teacher forcing)")
        steps = (noise if noise is not None else actions).shape[-2]  # type: ignore[union-attr]
        scale = self.action_scale
        log_scale = scale.log()
        lo, hi = self.config.log_std_range
        h, state, prev = h0, state0, prev_action
        out_actions, out_logp, out_states = [], [], []
        for t in range(steps):
            phase = torch.full_like(state[:, :1], (t + 1) / steps)
            h = self.cell(torch.cat([prev / scale, state[:, 2:3] / 10.0, phase], -1), h)
            out = self.head(h)
            gate = torch.sigmoid(out[:, 4:])  # 0: keep the previous action, 1: switch to the target
            mean = prev + gate * (out[:, :2] * scale - prev)
            log_std = log_scale + lo + (hi - lo) * torch.sigmoid(out[:, 2:4])
            std = log_std.exp()
            action = mean + std * noise[:, t] if noise is not None else actions[:, t]  # type: ignore[index]
            z = (action - mean) / std
            out_logp.append((-0.5 * z * z - log_std - HALF_LOG_2PI).sum(-1))
            lb, ub = action_bounds(state[:, 2])
            prev = torch.maximum(torch.minimum(action, ub), lb)
            state = unicycle_step(state, action, dt)
            out_actions.append(action)
            out_states.append(state)
        return DecodeResult(torch.stack(out_actions, 1), torch.stack(out_logp, 1), torch.stack(out_states, 1))

    def extra_repr(self) -> str:
        """The config in ``print(model)``."""
        return f"config={self.config.model_dump()!r}"

