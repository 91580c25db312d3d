"""SDK-side featurization for the compact CTG: turns a ``ScenarioTensor`` at its ``current_index`` into the
per-agent tensors :class:`ctg_reference.model.CTGModel` consumes, and into training targets.

Shared by the training script and the ``trafficrlhf-ctg`` adapter so both see identical inputs. (The model
module itself does not import the SDK.)
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.dynamics import wrap_angle
from trafficrlhf_sdk.models.features import agent_poses, history_features, map_crops, neighbour_features, to_agent_frame
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

from ctg_reference.model import CTGConfig

__all__ = ["FEATURE_KEYS", "agent_features", "future_targets", "select_rows", "window_mask"]

FEATURE_KEYS = ("map", "history", "history_valid", "extent", "neighbours", "neighbour_valid", "v0")


def agent_features(context: ScenarioTensor, cfg: CTGConfig, map_dtype: torch.dtype = torch.float32
                   ) -> dict[str, torch.Tensor]:
    """Features of every agent slot at ``context.current_index``, each with leading dims ``(B, A)``.

    map ``(B, A, C, S, S)`` (``cfg.map_resolution`` m per cell, a quarter of the crop behind the agent),
    history ``(B, A, Th, 5)`` and history_valid, extent ``(B, A, 2)``,
    neighbours ``(B, A, K, 7)`` and neighbour_valid, v0 ``(B, A)``.
    """
    crops = map_crops(context, size_px=cfg.map_size, resolution_m=cfg.map_resolution, behind_fraction=0.25)
    history, history_valid = history_features(context, cfg.history_steps)
    neighbours, neighbour_valid = neighbour_features(context, cfg.num_neighbours)
    return {
        "map": crops.to(map_dtype),
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


def window_mask(scenario: ScenarioTensor, now: int, horizon: int, history_steps: int) -> torch.Tensor:
    """bool ``(B, A)``: vehicles valid over ``now-history_steps .. now+horizon`` (usable training windows)."""
    if now - history_steps < 0 or now + horizon >= scenario.num_steps:
        return torch.zeros(scenario.num_scenes, scenario.num_agents, dtype=torch.bool, device=scenario.device)
    ok = scenario.valid[:, :, now - history_steps : now + horizon + 1].all(-1)
    return ok & (scenario.agent_type == int(AgentType.VEHICLE))


def future_targets(scenario: ScenarioTensor, now: int, horizon: int, actions: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Logged actions ``(B, A, H, 2)`` after ``now`` (inverse dynamics; frame-independent) and the logged
    future states ``(B, A, H, 4)`` in each agent's frame at ``now``. ``actions`` may pass a precomputed
    ``scenario.actions()``."""
    actions = scenario.actions() if actions is None else actions
    acts = actions[:, :, now : now + horizon]
    future = scenario.states[:, :, now + 1 : now + 1 + horizon]
    pose = agent_poses(scenario.replace_unchecked(current_index=now))
    local = to_agent_frame(future[..., :2], pose)
    yaw = wrap_angle(future[..., 3] - pose[..., 2:3])
    return acts, torch.cat([local, future[..., 2:3], yaw[..., None]], -1)
