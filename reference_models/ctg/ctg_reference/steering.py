"""The steering head of the compact CTG's sampler and what it reads along a plan: the drivable layer
(:func:`road_profile`) and the other agents' proximity (:func:`neighbour_proximity`).

Plain PyTorch; :class:`~ctg_reference.model.CTGModel` calls the head at every DDIM step when ``CTGConfig.steer`` is set.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from ctg_reference.networks import SinusoidalEmbedding, mlp

if TYPE_CHECKING:
    from ctg_reference.model import CTGConfig

__all__ = ["MAP_BEHIND_FRACTION", "SteerHead", "neighbour_proximity", "road_profile"]

MAP_BEHIND_FRACTION = 0.25  # share of the map crop's rows behind the agent (the rest is ahead)


class SteerHead(nn.Module):
    """Learned steering of the sampler: per DDIM step, a shift of the step's mean by ``sigma_k * tanh(g)``, with
    ``g = MLP(cond, x0_k, k[, road])`` read from the conditioning, the step's clean prediction, the step and, with
    ``steer_road``, the drivable layer along that prediction (:func:`road_profile`).

    Its output layer starts at zero, so a model with a fresh head samples exactly as without one; fine-tuning the
    head alone is policy optimization in the sampler's noise space (each step's shift is bounded by its own noise
    scale), with the trained encoder and denoiser frozen."""

    def __init__(self, cfg: CTGConfig) -> None:
        super().__init__()
        self.horizon, self.x0_clip = cfg.horizon, cfg.x0_clip
        self.step_embedding = SinusoidalEmbedding(cfg.time_dim)
        road = 3 * cfg.horizon * (int(cfg.steer_road) + int(cfg.steer_neighbours))
        self.net = mlp([cfg.cond_dim + 2 * cfg.horizon + cfg.time_dim + road, cfg.steer_hidden, cfg.steer_hidden,
                         2 * cfg.horizon])
        last = self.net[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, cond: torch.Tensor, x0: torch.Tensor, k: torch.Tensor | int,
                road: torch.Tensor | None = None) -> torch.Tensor:
        """Shift in units of the step's sigma, in (-1, 1): ``(M, H, 2)`` from ``cond (M, D)``, normalized clean
        prediction ``x0 (M, H, 2)``, step ``k`` (int or ``(M,)``) and, for a head that reads the plan's
        surroundings, ``road (M, H, 3)`` or ``(M, H, 6)`` in [0, 1]: :func:`road_profile` and/or
        :func:`neighbour_proximity`, concatenated in that order."""
        m = x0.shape[0]
        if not isinstance(k, torch.Tensor):
            k = torch.full((m,), int(k), dtype=torch.long, device=x0.device)
        inputs = [cond, x0.reshape(m, -1) / self.x0_clip, self.step_embedding(k)]
        if road is not None:
            inputs.append(road.reshape(m, -1))
        return torch.tanh(self.net(torch.cat(inputs, -1))).reshape(m, self.horizon, 2)


def road_profile(drivable: torch.Tensor, states: torch.Tensor, resolution: float, offset: float) -> torch.Tensor:
    """The drivable layer along plans: ``(N, S, H, 3)`` in [0, 1], bilinear in the crop, at each planned position
    and ``offset`` m to its left and right (across the planned heading); 0 outside the crop.

    Args:
        drivable: ``(N, 1, G, G)`` the rows' map crops (:data:`MAP_BEHIND_FRACTION` of the rows behind the agent,
            ``resolution`` m per cell, x ahead along rows and y to the left along columns).
        states: agent-frame plans ``(N, S, H, 4)`` (x, y, speed, yaw), e.g. :meth:`CTGModel.rollout`.
    """
    n, s, h, _ = states.shape
    xy, yaw = states[..., :2], states[..., 3]
    left = torch.stack([-torch.sin(yaw), torch.cos(yaw)], -1) * offset
    points = torch.stack([xy, xy + left, xy - left], 3)  # (N, S, H, 3, 2)
    size = drivable.shape[-1] * resolution
    # grid_sample's (x, y) are (column, row) in [-1, 1] over the crop's extent (align_corners=False)
    column = 2 * points[..., 1] / size
    row = 2 * points[..., 0] / size + 2 * MAP_BEHIND_FRACTION - 1
    grid = torch.stack([column, row], -1).reshape(n, 1, s * h * 3, 2)
    values = F.grid_sample(drivable.to(states.dtype), grid, mode="bilinear", padding_mode="zeros",
                           align_corners=False)
    return values.reshape(n, s, h, 3)


def neighbour_proximity(neighbours: torch.Tensor, neighbour_valid: torch.Tensor, extent: torch.Tensor,
                        states: torch.Tensor, dt: float, offset: float, scale: float) -> torch.Tensor:
    """How close the nearest neighbour comes to plans: ``(N, S, H, 3)`` in [0, 1], at each planned position and
    ``offset`` m to its left and right, ``exp(-clearance / scale)`` with clearance (m) the centre distance less
    both agents' mean half-extent ((length + width) / 4 each), 0 below it; 0 where no neighbour is valid.

    Args:
        neighbours: ``(N, K, 7)`` in the row's agent frame now (x, y in m, cos and sin of relative yaw, speed in
            m/s, length and width in m), each driven on at constant velocity: plan step h (0-based) is
            ``(h + 1) * dt`` s ahead.
        neighbour_valid: ``(N, K)`` bool.
        extent: ``(N, 2)`` the row's own length and width (m).
        states: agent-frame plans ``(N, S, H, 4)`` (x, y, speed, yaw).
    """
    h = states.shape[2]
    ahead = torch.arange(1, h + 1, dtype=states.dtype, device=states.device) * dt  # (H,) s
    heading = neighbours[..., 2:4].to(states.dtype)
    moved = neighbours[:, :, None, :2] + (neighbours[..., 4:5] * heading)[:, :, None] * ahead[:, None]  # (N, K, H, 2)
    xy, yaw = states[..., :2], states[..., 3]
    left = torch.stack([-torch.sin(yaw), torch.cos(yaw)], -1) * offset
    probes = torch.stack([xy, xy + left, xy - left], 3)  # (N, S, H, 3, 2)
    gap = probes[:, :, :, :, None] - moved.permute(0, 2, 1, 3)[:, None, :, None]  # (N, S, H, 3, K, 2)
    reach = (extent.sum(-1, keepdim=True) + neighbours[..., 5:7].sum(-1)) / 4  # (N, K)
    clearance = (torch.linalg.vector_norm(gap, dim=-1) - reach[:, None, None, None]).clamp_min(0)
    proximity = torch.exp(-clearance / scale) * neighbour_valid[:, None, None, None]
    return proximity.amax(-1) if proximity.shape[-1] else proximity.new_zeros(proximity.shape[:-1])

