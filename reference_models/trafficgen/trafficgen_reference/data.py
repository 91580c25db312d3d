"""SDK-side featurization for the compact TrafficGen: ``ScenarioTensor`` -> the tensors of
:mod:`trafficgen_reference.model`, training targets, and scene initialization with the initializer.

Shared by the training script and the ``trafficrlhf-trafficgen`` adapter so both see identical inputs. (The
model module itself does not import the SDK.)
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.models.features import (
    agent_poses,
    from_agent_frame,
    history_features,
    map_crops,
    neighbour_features,
    to_agent_frame,
)
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

from trafficgen_reference.model import TrafficGenConfig, TrafficGenModel

__all__ = [
    "FORECAST_KEYS",
    "context_agent_inputs",
    "context_slots",
    "forecaster_features",
    "future_targets",
    "initialize_scene",
    "select_rows",
    "window_mask",
]

FORECAST_KEYS = ("map", "history", "history_valid", "extent", "neighbours", "neighbour_valid")


# --------------------------------------------------------------------------------------------- forecaster
def forecaster_features(context: ScenarioTensor, cfg: TrafficGenConfig) -> dict[str, torch.Tensor]:
    """Features of every agent slot at ``context.current_index``, each with leading dims ``(B, A)``: map crop
    ``(C, S, S)`` at 1 m/px (a quarter behind the agent), history ``(Th, 5)`` + valid, extent ``(2,)``,
    neighbours ``(K, 7)`` + valid."""
    crops = map_crops(context, size_px=cfg.map_size, resolution_m=1.0, behind_fraction=0.25)
    history, history_valid = history_features(context, cfg.history_steps)
    neighbours, neighbour_valid = neighbour_features(context, cfg.num_neighbours)
    return {"map": crops, "history": history, "history_valid": history_valid, "extent": context.extent,
            "neighbours": neighbours, "neighbour_valid": neighbour_valid}


def select_rows(features: dict[str, torch.Tensor], mask: torch.Tensor) -> dict[str, torch.Tensor]:
    """Rows of ``(B, A, ...)`` features where ``mask (B, A)``: ``(N, ...)``."""
    return {k: v[mask] for k, v in features.items()}


def window_mask(scenario: ScenarioTensor, now: int, horizon: int) -> torch.Tensor:
    """bool ``(B, A)``: vehicles valid at ``now`` and at every step of the ``horizon`` after it (history may be
    partial; its validity is an input)."""
    if now + horizon >= scenario.num_steps:
        return torch.zeros(scenario.num_scenes, scenario.num_agents, dtype=torch.bool, device=scenario.device)
    ok = scenario.valid[:, :, now : now + horizon + 1].all(-1)
    return ok & (scenario.agent_type == int(AgentType.VEHICLE))


def future_targets(scenario: ScenarioTensor, now: int, horizon: int, actions: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Logged actions ``(B, A, H, 2)`` after ``now`` (inverse unicycle dynamics) and logged future positions
    ``(B, A, H, 2)`` in each agent's frame at ``now``. ``actions`` may pass a precomputed ``scenario.actions()``."""
    actions = scenario.actions() if actions is None else actions
    pose = agent_poses(scenario.replace_unchecked(current_index=now))
    future = scenario.xy[:, :, now + 1 : now + 1 + horizon]
    return actions[:, :, now : now + horizon], to_agent_frame(future, pose)


# --------------------------------------------------------------------------------------------- initializer
def context_slots(scenario: ScenarioTensor) -> torch.Tensor:
    """The context agent of each scene ``(B,)``: the first vehicle slot valid at ``current_index`` (upstream
    starts from the first logged agent, ``context_num=1``); -1 where a scene has none."""
    usable = scenario.valid[:, :, scenario.current_index] & (scenario.agent_type == int(AgentType.VEHICLE))
    first = torch.argmax(usable.to(torch.uint8), 1)
    return torch.where(usable.any(1), first, torch.full_like(first, -1))


def context_agent_inputs(scenario: ScenarioTensor, slots: torch.Tensor, cfg: TrafficGenConfig
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Initializer inputs around agent ``slots (B,)`` (valid at ``current_index``) of each scene.

    Returns the map crop ``(B, C, S, S)`` (centred on the agent, 1 m/px), context features ``(B, 3)``, the
    other agents valid now as ``(B, A, 6)`` = (x, y, heading, speed, length, width) in the context frame and
    their mask ``(B, A)`` (the context agent itself excluded).
    """
    b = scenario.num_scenes
    rows = torch.arange(b, device=scenario.device)
    now = scenario.current_index
    single = scenario.replace_unchecked(
        states=scenario.states[rows, slots][:, None], valid=scenario.valid[rows, slots][:, None],
        extent=scenario.extent[rows, slots][:, None], agent_type=scenario.agent_type[rows, slots][:, None],
        controlled=scenario.controlled[rows, slots][:, None],
    )
    crop = map_crops(single, size_px=cfg.init_crop_px, resolution_m=cfg.init_crop_res_m, behind_fraction=0.5)[:, 0]
    state = single.states[:, 0, now]
    extent = single.extent[:, 0]
    context = torch.stack([state[:, 2] / 10.0, extent[:, 0] / 5.0, extent[:, 1] / 2.0], -1)
    pose = agent_poses(single)  # (B, 1, 3)
    others = scenario.states[:, :, now]
    xy = to_agent_frame(others[:, None, :, :2], pose)[:, 0]  # (B, A, 2)
    heading = wrap_angle(others[..., 3] - pose[:, :, 2])
    agents = torch.cat([xy, heading[..., None], others[..., 2:3], scenario.extent], -1)
    mask = scenario.valid[:, :, now] & (scenario.agent_type == int(AgentType.VEHICLE))
    mask = mask & (torch.arange(scenario.num_agents, device=scenario.device)[None] != slots[:, None])
    return crop, context, agents, mask


def initialize_scene(scenario: ScenarioTensor, model: TrafficGenModel, seed: int = 0,
                     num_agents: int | None = None) -> ScenarioTensor:
    """Place vehicles on the map of a one-scene ``scenario`` with the initializer, under a fixed ``seed``.

    The first logged vehicle valid at ``current_index`` is kept as the context agent (slot 0); up to
    ``num_agents`` others (default: as many as the log has at that step) are placed around it (see
    :meth:`Initializer.initialize`). Returns a one-step scenario (``current_index`` 0) on the same map and
    origin: slot 0 the context agent, then the placed vehicles, all controlled.
    """
    if scenario.num_scenes != 1:
        raise ValueError(f"initialize_scene takes one scene; got {scenario.num_scenes}. Index it: scenario[i].")
    slots = context_slots(scenario)
    if int(slots[0]) < 0:
        raise ValueError("the scene has no vehicle valid at `current_index` to start the initialization from.")
    cfg = model.cfg
    crop, context, _, mask = context_agent_inputs(scenario, slots, cfg)
    if num_agents is None:
        num_agents = int(mask.sum())
    now = scenario.current_index
    slot = int(slots[0])
    extent = scenario.extent[0, slot]
    box = torch.tensor([0.0, 0.0, 0.0, float(extent[0]), float(extent[1])])
    generator = torch.Generator().manual_seed(seed)
    placed = model.initializer.initialize(crop[0].cpu(), context[0].cpu(), box, num_agents, generator)
    ctx_state = scenario.states[0, slot, now]
    pose = torch.stack([ctx_state[0], ctx_state[1], ctx_state[3]])[None, None].cpu()
    xy = torch.cat([torch.zeros(1, 2), placed[:, :2]])  # context agent at its own origin
    world = from_agent_frame(xy[None, None], pose)[0, 0]
    yaw = wrap_angle(torch.cat([torch.zeros(1), placed[:, 2]]) + ctx_state[3].cpu())
    speed = torch.cat([ctx_state[2:3].cpu(), placed[:, 3]])
    states = torch.cat([world, speed[:, None], yaw[:, None]], -1)[None, :, None].to(scenario.device)
    n = states.shape[1]
    extents = torch.cat([extent[None].cpu(), placed[:, 4:6]])[None].to(scenario.device)
    return ScenarioTensor(
        states=states.float(), valid=torch.ones(1, n, 1, dtype=torch.bool, device=scenario.device),
        extent=extents.float(), agent_type=torch.full((1, n), int(AgentType.VEHICLE), device=scenario.device),
        controlled=torch.ones(1, n, dtype=torch.bool, device=scenario.device), dt=scenario.dt, current_index=0,
        map=scenario.map, origin=scenario.origin,
        scene_ids=scenario.scene_ids, agent_ids=((scenario.agent_ids[0][slot] if scenario.agent_ids else "",)
                                                 + tuple(f"init_{i}" for i in range(n - 1)),),
        source=scenario.source, extras={**scenario.extras, "initialized": {"seed": seed, "context_slot": slot}},
    )

