"""The steering heads of the compact CTG's sampler and what they read along a plan: the drivable layer
(:func:`road_profile`), the other agents' proximity (:func:`neighbour_proximity`) and the agent ahead in the
plan's path (:func:`lead_gaps`, read by the gap-keeping :class:`FollowHead`).

Plain PyTorch; :class:`~ctg_reference.model.CTGModel` calls the head at every DDIM step when ``CTGConfig.steer`` is set.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from reference_common.layers import mlp
from torch import nn

from ctg_reference.networks import SinusoidalEmbedding

if TYPE_CHECKING:
    from ctg_reference.config import CTGConfig

__all__ = ["MAP_BEHIND_FRACTION", "FollowHead", "SteerHead", "lead_gaps", "neighbour_proximity", "road_profile"]

MAP_BEHIND_FRACTION = 0.25  # share of the map crop's rows behind the agent (the rest is ahead)
LEAD_GAP_CLIP = 30.0  # m: gaps are read up to this; no agent ahead in the path reads as this gap


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



class FollowHead(nn.Module):
    """Learned gap keeping: per DDIM step, a shift of the acceleration channel's mean by
    ``sigma_k * gate * tanh(g)``, with ``g = MLP(x0_k, k, lead)`` and ``lead`` the per-step gap to the agent ahead
    in the plan's path, its closing speed and the headway hazard (:func:`lead_gaps`). The gate (computed by the
    model) is the plan's largest headway hazard, so a plan with nobody ahead closer than the desired gap is drawn
    exactly as without the head. Its output layer starts at zero; the yaw-rate channel is never moved."""

    def __init__(self, cfg: CTGConfig) -> None:
        super().__init__()
        self.horizon, self.x0_clip = cfg.horizon, cfg.x0_clip
        self.step_embedding = SinusoidalEmbedding(cfg.time_dim)
        self.net = mlp([2 * cfg.horizon + cfg.time_dim + 1 + 3 * cfg.horizon, cfg.follow_hidden, cfg.follow_hidden,
                        cfg.horizon])
        last = self.net[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, x0: torch.Tensor, k: torch.Tensor | int, v0: torch.Tensor, lead: torch.Tensor) -> torch.Tensor:
        """Shift in units of the step's sigma, in (-1, 1): ``(M, H, 2)`` (the second channel 0) from the normalized
        clean prediction ``x0 (M, H, 2)``, step ``k`` (int or ``(M,)``), speed now ``v0 (M,)`` m/s and ``lead
        (M, H, 3)``: gap / :data:`LEAD_GAP_CLIP`, closing speed / 10 m/s and headway hazard."""
        m = x0.shape[0]
        if not isinstance(k, torch.Tensor):
            k = torch.full((m,), int(k), dtype=torch.long, device=x0.device)
        inputs = [x0.reshape(m, -1) / self.x0_clip, self.step_embedding(k), v0.reshape(m, 1) / 10.0,
                  lead.reshape(m, -1)]
        acceleration = torch.tanh(self.net(torch.cat(inputs, -1)))
        return torch.stack([acceleration, torch.zeros_like(acceleration)], -1)


def lead_gaps(neighbours: torch.Tensor, neighbour_valid: torch.Tensor, extent: torch.Tensor, states: torch.Tensor,
              dt: float, lane_margin: float, standstill: float, headway: float,
              ttc: float | None = None, min_heading_cos: float | None = None) -> torch.Tensor:
    """The agent ahead in each plan's path, per planned step: ``(N, S, H, 3)`` = (gap m, closing speed m/s, headway
    hazard in [0, 1]).

    At plan step h (``(h + 1) * dt`` s ahead, each neighbour driven on at constant velocity) a neighbour is in the
    path when its centre lies ahead of the planned position along the planned heading and at most half of both
    widths plus ``lane_margin`` m to the side. The gap is bumper to bumper (centre distance along the heading less
    half of both lengths, 0 below it), clipped to :data:`LEAD_GAP_CLIP` (also the reading with nobody ahead); the
    closing speed is the planned speed less the lead's speed along the planned heading; the hazard is
    ``clamp(1 - gap / (standstill + headway * planned speed), 0, 1)``: 0 from the desired gap (m, s) on, 1 at contact.
    With ``ttc`` (s) the hazard is the time-to-collision one instead, ``clamp(1 - (gap / closing speed) / ttc, 0, 1)``
    while closing in and 0 otherwise: a follower keeping its distance, however short, reads no hazard. With
    ``min_heading_cos`` only neighbours heading the plan's way count (cosine of the heading difference at least that):
    oncoming and crossing agents, driven on straight at constant velocity, cut across curved plans they never meet.

    Args:
        neighbours: ``(N, K, 7)`` in the row's agent frame now (x, y in m, cos and sin of relative yaw, speed in
            m/s, length and width in m).
        neighbour_valid: ``(N, K)`` bool.
        extent: ``(N, 2)`` the row's own length and width (m).
        states: agent-frame plans ``(N, S, H, 4)`` (x, y, speed, yaw).
    """
    h = states.shape[2]
    ahead_s = torch.arange(1, h + 1, dtype=states.dtype, device=states.device) * dt  # (H,)
    heading = neighbours[..., 2:4].to(states.dtype)  # (N, K, 2)
    velocity = neighbours[..., 4:5].to(states.dtype) * heading
    moved = neighbours[:, :, None, :2].to(states.dtype) + velocity[:, :, None] * ahead_s[:, None]  # (N, K, H, 2)
    yaw = states[..., 3]
    forward = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)  # (N, S, H, 2)
    offset = moved.permute(0, 2, 1, 3)[:, None] - states[..., None, :2]  # (N, S, H, K, 2)
    along = (offset * forward[..., None, :]).sum(-1)
    across = (offset[..., 1] * forward[..., None, 0] - offset[..., 0] * forward[..., None, 1]).abs()
    half_widths = (extent[:, 1:2] + neighbours[..., 6]) / 2  # (N, K)
    half_lengths = (extent[:, 0:1] + neighbours[..., 5]) / 2
    in_path = (along > 0) & (across <= (half_widths + lane_margin)[:, None, None]) & neighbour_valid[:, None, None]
    if min_heading_cos is not None:
        alike = (forward[..., None, :] * heading[:, None, None]).sum(-1)  # (N, S, H, K)
        in_path = in_path & (alike >= min_heading_cos)
    gap = (along - half_lengths[:, None, None]).clamp(0, LEAD_GAP_CLIP)
    gap = torch.where(in_path, gap, torch.full_like(gap, LEAD_GAP_CLIP))
    if gap.shape[-1] == 0:
        lead_gap = states.new_full(states.shape[:3], LEAD_GAP_CLIP)
        lead_speed = states[..., 2]
    else:
        lead_gap, lead = gap.min(-1)  # (N, S, H)
        lead_velocity = velocity[:, None, None].expand(*gap.shape, 2).gather(
            -2, lead[..., None, None].expand(*lead.shape, 1, 2)).squeeze(-2)
        lead_speed = torch.where(lead_gap < LEAD_GAP_CLIP, (lead_velocity * forward).sum(-1), states[..., 2])
    closing = states[..., 2] - lead_speed
    if ttc is None:
        desired = standstill + headway * states[..., 2].clamp_min(0)
    else:  # the gap covered in ttc s at the closing speed; 0 (no hazard) unless closing in
        desired = ttc * closing.clamp_min(0)
    hazard = torch.where(desired > 0, (1 - lead_gap / desired.clamp_min(1e-6)).clamp(0, 1), torch.zeros_like(desired))
    return torch.stack([lead_gap, closing, hazard], -1)
