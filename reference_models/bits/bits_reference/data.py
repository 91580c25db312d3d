"""SDK-side featurization for the compact BITS: turns a ``ScenarioTensor`` into the per-agent tensors
:class:`bits_reference.model.BITSModel` consumes, and into training targets.

Shared by the training script and the ``trafficrlhf-bits`` adapter so both see identical inputs (the model
module itself does not import the SDK).
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.models.features import agent_poses, history_features, map_crops, neighbour_features, to_agent_frame
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

from bits_reference.model import BITSConfig

__all__ = ["FEATURE_KEYS", "agent_features", "future_targets", "scene_windows", "select_rows", "window_mask"]

FEATURE_KEYS = ("map", "history", "history_valid", "extent", "neighbours", "neighbour_valid", "v0")


def agent_features(context: ScenarioTensor, cfg: BITSConfig, crop_agents: torch.Tensor | None = None
                   ) -> dict[str, torch.Tensor]:
    """Features of every agent slot at ``context.current_index``, each with leading dims ``(B, A)``; with
    ``crop_agents (B, A)`` the map crops of only those slots (the rows a caller selects), the others left 0.

    map ``(B, A, C, S, S)`` ({0, 1}, ``cfg.resolution_m`` per cell, ``cfg.behind_fraction`` of it behind the
    agent), history ``(B, A, Th, 5)`` and history_valid, extent ``(B, A, 2)``, neighbours ``(B, A, K, 7)`` and
    neighbour_valid, v0 ``(B, A)`` (m/s).
    """
    crops = map_crops(context, size_px=cfg.map_size, resolution_m=cfg.resolution_m,
                      behind_fraction=cfg.behind_fraction, agents=crop_agents)
    history, history_valid = history_features(context, cfg.history_steps)
    neighbours, neighbour_valid = neighbour_features(context, cfg.num_neighbours)
    return {
        "map": crops[:, :, : cfg.map_channels],
        "history": history,
        "history_valid": history_valid,
        "extent": context.extent,
        "neighbours": neighbours,
        "neighbour_valid": neighbour_valid,
        "v0": context.speed[:, :, context.current_index],
    }


def select_rows(features: dict[str, torch.Tensor], mask: torch.Tensor) -> dict[str, torch.Tensor]:
    """Rows of ``(B, A, ...)`` features where ``mask (B, A)``: ``(N, ...)``."""
    return {k: v[mask] for k, v in features.items()}


def window_mask(scenario: ScenarioTensor, now: int, horizon: int) -> torch.Tensor:
    """bool ``(B, A)``: vehicles valid at every step ``now .. now + horizon`` (usable training windows)."""
    if now + horizon >= scenario.num_steps:
        return torch.zeros(scenario.num_scenes, scenario.num_agents, dtype=torch.bool, device=scenario.device)
    ok = scenario.valid[:, :, now : now + horizon + 1].all(-1)
    return ok & (scenario.agent_type == int(AgentType.VEHICLE))


def future_targets(scenario: ScenarioTensor, now: int, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Logged actions ``(B, A, H, 2)`` after ``now`` (inverse dynamics) and logged future states ``(B, A, H, 4)``
    in each agent's frame at ``now`` (x, y, speed, relative yaw). The goal is the last state."""
    acts = scenario.actions()[:, :, now : now + horizon]
    future = scenario.states[:, :, now + 1 : now + 1 + horizon]
    pose = agent_poses(scenario.replace_unchecked(current_index=now))
    local = to_agent_frame(future[..., :2], pose)
    yaw = wrap_angle(future[..., 3] - pose[..., 2:3])
    return acts, torch.cat([local, future[..., 2:3], yaw[..., None]], -1)


def scene_windows(scene: ScenarioTensor, cfg: BITSConfig, stride: int, first: int | None = None
                  ) -> dict[str, torch.Tensor] | None:
    """Every usable (vehicle, now) window of one scene (B = 1), now every ``stride`` steps from ``first``
    (default: ``history_steps``): features (map crops as uint8), ``actions (N, H, 2)`` and agent-frame
    ``states (N, H, 4)``. Returns None when the scene has no usable window.

    Windows are featurized together: the candidate "now" steps become the batch axis of a history-only context
    (no map) for history and neighbour features, and the selected rows become the agents of one single-step
    context for the map crops.
    """
    h, th = cfg.horizon, cfg.history_steps
    first = th if first is None else first
    steps = torch.arange(first, scene.num_steps - h, stride)
    if len(steps) == 0:
        return None
    valid = scene.valid[0]
    future_span = steps[:, None] + torch.arange(0, h + 1)
    mask = valid[:, future_span].all(-1).T & (scene.agent_type[0] == int(AgentType.VEHICLE))  # (n, A)
    if not mask.any():
        return None
    n, a = len(steps), scene.num_agents
    hist_idx = (steps[:, None] + torch.arange(-th + 1, 1)).clamp_min(0)  # (n, th)
    hist_ok = (steps[:, None] + torch.arange(-th + 1, 1)) >= 0
    stacked = scene.replace_unchecked(
        states=scene.states[0][:, hist_idx].permute(1, 0, 2, 3).contiguous(),
        valid=(valid[:, hist_idx] & hist_ok[None]).permute(1, 0, 2).contiguous(),
        extent=scene.extent.expand(n, a, 2), agent_type=scene.agent_type.expand(n, a),
        controlled=scene.controlled.expand(n, a), map=None, origin=None, current_index=th - 1,
    )
    history, history_valid = history_features(stacked, th)
    neighbours, neighbour_valid = neighbour_features(stacked, cfg.num_neighbours)
    rows = stacked.states[:, :, -1][mask]  # (N, 4)
    single = scene.replace_unchecked(
        states=rows[None, :, None], valid=torch.ones(1, len(rows), 1, dtype=torch.bool),
        extent=stacked.extent[mask][None], agent_type=stacked.agent_type[mask][None],
        controlled=torch.ones(1, len(rows), dtype=torch.bool), current_index=0,
    )
    crops = map_crops(single, size_px=cfg.map_size, resolution_m=cfg.resolution_m,
                      behind_fraction=cfg.behind_fraction)[0, :, : cfg.map_channels]
    fut_idx = steps[:, None] + torch.arange(1, h + 1)
    future = scene.states[0][:, fut_idx].permute(1, 0, 2, 3)[mask]  # (N, H, 4)
    actions = scene.actions()[0][:, fut_idx - 1].permute(1, 0, 2, 3)[mask]
    pose = torch.stack([rows[:, 0], rows[:, 1], rows[:, 3]], -1)[None]
    local = to_agent_frame(future[None, :, :, :2], pose)[0]
    yaw = wrap_angle(future[..., 3] - rows[:, 3:4])
    return {
        "map": crops.to(torch.uint8), "history": history[mask], "history_valid": history_valid[mask],
        "extent": stacked.extent[mask], "neighbours": neighbours[mask], "neighbour_valid": neighbour_valid[mask],
        "v0": rows[:, 2], "actions": actions, "states": torch.cat([local, future[..., 2:3], yaw[..., None]], -1),
    }
