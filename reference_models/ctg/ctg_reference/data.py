"""SDK-side featurization for the compact CTG: turns a ``ScenarioTensor`` at its ``current_index`` into the
per-agent tensors :class:`ctg_reference.model.CTGModel` consumes, and into training targets.

Shared by the training script and the ``trafficrlhf-ctg`` adapter so both see identical inputs. (The model
module itself does not import the SDK.)
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.models.features import agent_poses, history_features, map_crops, neighbour_features, to_agent_frame
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

from ctg_reference.config import CTGConfig
from ctg_reference.model import MAP_BEHIND_FRACTION, draw_device

__all__ = ["FEATURE_KEYS", "PLAN_KEYS", "agent_features", "co_denoised_rows", "drop_neighbour_plans", "future_targets",
           "logged_neighbour_plans", "neighbour_plan_features", "select_rows", "window_mask"]

FEATURE_KEYS = ("map", "history", "history_valid", "extent", "neighbours", "neighbour_valid", "v0")
PLAN_KEYS = ("neighbour_plan", "neighbour_plan_valid")


def agent_features(context: ScenarioTensor, cfg: CTGConfig, map_dtype: torch.dtype = torch.float32,
                   crop_agents: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Features of every agent slot at ``context.current_index``, each with leading dims ``(B, A)``; with
    ``crop_agents (B, A)`` the map crops of only those slots (the rows a caller selects), the others left 0.

    map ``(B, A, C, S, S)`` (``cfg.map_resolution`` m per cell, a quarter of the crop behind the agent),
    history ``(B, A, Th, 5)`` and history_valid, extent ``(B, A, 2)``,
    neighbours ``(B, A, K, 7)`` and neighbour_valid, neighbour_index ``(B, A, K)`` (their agent slots),
    v0 ``(B, A)``.
    """
    crops = map_crops(context, size_px=cfg.map_size, resolution_m=cfg.map_resolution,
                      behind_fraction=MAP_BEHIND_FRACTION, agents=crop_agents)
    history, history_valid = history_features(context, cfg.history_steps)
    neighbours, neighbour_valid, neighbour_index = neighbour_features(context, cfg.num_neighbours,
                                                                      return_index=True)
    return {
        "map": crops.to(map_dtype),
        "history": history,
        "history_valid": history_valid,
        "extent": context.extent,
        "neighbours": neighbours,
        "neighbour_valid": neighbour_valid,
        "neighbour_index": neighbour_index,
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


def neighbour_plan_features(context: ScenarioTensor, neighbours: torch.Tensor, neighbour_valid: torch.Tensor,
                            neighbour_index: torch.Tensor, positions: torch.Tensor, known: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each agent's nearest neighbours plan to be, in its frame at ``context.current_index``.

    Args:
        neighbours, neighbour_valid, neighbour_index: from :func:`agent_features` (``(B, A, K, 7)``, ``(B, A, K)``).
        positions: ``(B, S, A, F, 2)`` every agent slot's planned scene-frame position (m) at the F plan steps,
            per sample S; known: ``(B, S, A, F)`` bool, where a plan exists.

    Returns:
        plan ``(B, S, A, K, F, 2)`` (m, agent frame) and plan_valid ``(B, S, A, K, F)``: known, a picked
        neighbour, and ahead of the agent now (x > 0). Only neighbours ahead are shown: a follower's plan mostly
        reacts to its leader, so the model must not learn to read its own future from the agents behind it.
    """
    b, s = positions.shape[:2]
    scene = torch.arange(b, device=positions.device)[:, None, None, None]
    sample = torch.arange(s, device=positions.device)[None, :, None, None]
    slot = neighbour_index[:, None]  # (B, 1, A, K)
    picked = positions[scene, sample, slot]  # (B, S, A, K, F, 2)
    plan_known = known[scene, sample, slot]  # (B, S, A, K, F)
    local = to_agent_frame(picked.transpose(1, 2), agent_poses(context)).transpose(1, 2)
    shown = neighbour_valid & (neighbours[..., 0] > 0)  # (B, A, K)
    valid = plan_known & shown[:, None, :, :, None]
    return local * valid[..., None], valid


def logged_neighbour_plans(scenario: ScenarioTensor, cfg: CTGConfig, features: dict[str, torch.Tensor]
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """The logged future as the neighbours' plans (training): ``(B, A, K, F, 2)`` and valid ``(B, A, K, F)``
    at ``scenario.current_index``, from the :func:`agent_features` of the same context."""
    steps = torch.tensor(cfg.neighbour_plan_steps, device=scenario.device) + scenario.current_index
    inside = steps < scenario.num_steps
    steps = steps.clamp_max(scenario.num_steps - 1)
    positions = scenario.xy[:, :, steps][:, None]  # (B, 1, A, F, 2)
    known = (scenario.valid[:, :, steps] & inside)[:, None]  # (B, 1, A, F)
    plan, valid = neighbour_plan_features(scenario, features["neighbours"], features["neighbour_valid"],
                                          features["neighbour_index"], positions, known)
    return plan[:, 0], valid[:, 0]


def drop_neighbour_plans(valid: torch.Tensor, cfg: CTGConfig, generator: torch.Generator | None = None
                         ) -> torch.Tensor:
    """Training dropout of ``valid (N, K, F)``: a share ``cfg.plan_dropout_all`` of the rows sees no plan (as
    the proposal pass does), the others lose each neighbour's plan with probability ``cfg.plan_dropout_each``
    (as for neighbours that are not sampled)."""
    n, k = valid.shape[:2]
    at = draw_device(generator, valid.device)
    rows = torch.rand(n, 1, generator=generator, device=at).to(valid.device) >= cfg.plan_dropout_all
    each = torch.rand(n, k, generator=generator, device=at).to(valid.device) >= cfg.plan_dropout_each
    return valid & (rows & each)[..., None]


def co_denoised_rows(mask: torch.Tensor, neighbour_index: torch.Tensor, neighbour_valid: torch.Tensor
                     ) -> torch.Tensor:
    """Scene-level denoising: for the rows ``mask (W, A)`` (W scenes or windows, rows in row-major order), the row
    index of each of their neighbours ``neighbour_index (W, A, K)`` (valid where ``neighbour_valid``) that is
    itself a row of the same window, else -1: ``(N, K)`` long."""
    row_of = torch.full(mask.shape, -1, dtype=torch.long, device=mask.device)
    row_of[mask] = torch.arange(int(mask.sum()), device=mask.device)
    rows = row_of.gather(1, neighbour_index.flatten(1)).reshape(neighbour_index.shape)
    return torch.where(neighbour_valid, rows, torch.full_like(rows, -1))[mask]
