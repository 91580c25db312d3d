"""A reward model with a TrafficGen-style encoder (``"trafficgen_mcg"``) and the paper's 512-512-512-128-32 head.

TrafficGen encodes a scene with MultiPath++-style **multi-context gating** (MCG) rather than attention: a set of
agent vectors and a set of map vectors are each embedded by an MLP, then a stack of context-gating blocks
multiplies every element's features by a gate computed from a shared context vector and max-pools the gated
elements into the next context. The agent context conditions the map encoding. This module is a compact version
of that encoder, used as the backbone of a reward model so that Table 4 of the paper (reward models with the CTG
encoder and with the TrafficGen encoder) can be compared on the same feedback:

- **items**: as in :class:`~trafficrlhf_sdk.reward.ctg_mlp.CTGMLPRewardModel`, every selected agent at every scored
  step (2 Hz), seen in its own frame; the agent's own inputs are the same flat features
  (:mod:`trafficrlhf_sdk.reward.features`: its motion, kinematics, events, drivable look-ups);
- **agent set**: the agent itself and its ``num_neighbours`` nearest valid neighbours within
  ``neighbour_radius_m``, each a vector (x, y, velocity along and across the agent's heading, cosine and sine of the
  relative heading, length, width), TrafficGen's per-agent features;
- **map set**: the nuScenes maps here are rasters, not lane polylines, so the map vectors are the patches of the
  agent's map crop (``patch`` x ``patch`` cells each, with the patch centre's coordinates), TrafficGen's lane
  vectors' stand-in;
- **encoder**: agent set -> ``gating_blocks`` context-gating blocks (context: the agent's own embedding) -> agent
  context; map set -> as many blocks with the agent context -> map context;
- **head**: [own embedding, agent context, map context] -> Linear + Tanh for 512-512-512-128-32 and the 1-unit
  output (:func:`~trafficrlhf_sdk.reward.ctg_mlp.tanh_head`), so every (agent, step) reward lies in [-1, 1].

Padding agents, invalid steps and absent neighbours are masked out of every pooling, so any length, any number
of agents and any padding give the same rewards.
"""

from __future__ import annotations

from typing import Any

import torch
from pydantic import Field
from torch import nn

from trafficrlhf_sdk.reward.ctg_mlp import MAX_LAYER_WIDTH, ItemRewardModel, LayerWidth, StepFeatureOptions, tanh_head
from trafficrlhf_sdk.reward.features import (
    SIZE_SCALE,
    SPEED_SCALE,
    StepInputs,
    _rotate,
    compute_step_inputs,
    scored_steps,
    selected_agents,
)
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.dynamics import wrap_angle

__all__ = ["ContextGating", "TrafficGenMCGConfig", "TrafficGenMCGRewardModel", "neighbour_vectors"]

NEIGHBOUR_FEATURES = 9  # x, y, v_lon, v_lat, cos, sin, length, width, valid


class TrafficGenMCGConfig(StepFeatureOptions):
    """Options of :class:`TrafficGenMCGRewardModel` (stored in ``config.json``)."""

    hidden_sizes: tuple[LayerWidth, ...] = Field((512, 512, 512, 128, 32), min_length=1, max_length=32,
                                                 description="Head MLP widths (the paper's 512-512-512-128-32), each "
                                                             "1 to 8192; Tanh after each.")
    width: int = Field(64, ge=4, le=MAX_LAYER_WIDTH, description="Width of the agent and map embeddings and of "
                                                                  "every gating block (TrafficGen: 1024; compact "
                                                                  "here).")
    gating_blocks: int = Field(3, ge=1, le=64, description="Context-gating blocks per set (TrafficGen: 5).")
    num_neighbours: int = Field(8, ge=0, le=256, description="Nearest other agents in the agent set.")
    patch: int = Field(4, ge=1, le=64, description="Crop cells per side of one map vector.")


def neighbour_vectors(scenario: ScenarioTensor, scene: torch.Tensor, agent: torch.Tensor, step: torch.Tensor,
                      k: int, radius_m: float) -> torch.Tensor:
    """The ``k`` nearest valid other agents of every item, float32 ``(N, k, 9)`` in the item agent's frame.

    Per neighbour: x and y / ``radius_m``, velocity along and across the agent's heading / 10 m/s, cosine and sine
    of the relative heading, length and width / 5 m, and a valid flag; absent neighbours are all zero.
    """
    n = len(scene)
    out = torch.zeros(n, k, NEIGHBOUR_FEATURES)
    a_ = scenario.num_agents
    if n == 0 or k == 0 or a_ < 2:
        return out
    pose = scenario.states[scene, agent, step]  # (N, 4)
    others = scenario.states[scene, :, step]  # (N, A, 4)
    ok = scenario.valid[scene, :, step] & (torch.arange(a_)[None] != agent[:, None])
    rx, ry = _rotate(others[..., 0] - pose[:, None, 0], others[..., 1] - pose[:, None, 1], pose[:, None, 3])
    dist = torch.sqrt(rx * rx + ry * ry)
    ok &= dist <= radius_m
    take = min(k, a_)
    # nearest first, ties by agent index (a stable sort): padding agents, appended and never valid, cannot change
    # which of several equally near agents are taken
    order = torch.sort(torch.where(ok, dist, torch.full_like(dist, float("inf"))), dim=1, stable=True).indices[:, :take]
    pick = lambda t: t.gather(1, order)  # noqa: E731
    rel = wrap_angle(others[..., 3] - pose[:, None, 3])
    speed = others[..., 2]
    extent = scenario.extent[scene]  # (N, A, 2)
    valid = pick(ok).float()
    columns = [pick(rx) / radius_m, pick(ry) / radius_m, pick(speed * torch.cos(rel)) / SPEED_SCALE,
               pick(speed * torch.sin(rel)) / SPEED_SCALE, pick(torch.cos(rel)), pick(torch.sin(rel)),
               pick(extent[..., 0]) / SIZE_SCALE, pick(extent[..., 1]) / SIZE_SCALE]
    vectors = torch.stack([c * valid for c in columns] + [valid], -1).float()
    out[:, :take] = vectors.clamp(-5, 5)
    return out


class ContextGating(nn.Module):
    """One multi-context gating block: every element times a gate from the context; the next context is the
    max-pool of the gated elements over the valid ones (zero where there is none)."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.element = nn.Sequential(nn.Linear(width, width), nn.ReLU())
        self.context = nn.Sequential(nn.Linear(width, width), nn.ReLU())

    def forward(self, elements: torch.Tensor, mask: torch.Tensor,
                context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``elements (N, M, W)``, ``mask (N, M)`` bool, ``context (N, W)`` -> gated elements and new context."""
        gated = self.element(elements) * self.context(context)[:, None]
        pooled = torch.where(mask[..., None], gated, torch.full_like(gated, float("-inf"))).amax(1)
        pooled = torch.where(mask.any(1, keepdim=True), pooled, torch.zeros_like(pooled))
        return gated, pooled


class _GatingStack(nn.Module):
    """Blocks whose outputs are averaged with their inputs (MultiPath++'s running mean of the block outputs)."""

    def __init__(self, width: int, blocks: int) -> None:
        super().__init__()
        self.blocks = nn.ModuleList(ContextGating(width) for _ in range(blocks))

    def forward(self, elements: torch.Tensor, mask: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        e_sum, c_sum = elements, context
        for i, block in enumerate(self.blocks):
            e_new, c_new = block(e_sum / (i + 1), mask, c_sum / (i + 1))
            e_sum, c_sum = e_sum + e_new, c_sum + c_new
        return c_sum / (len(self.blocks) + 1)


class TrafficGenMCGRewardModel(ItemRewardModel):
    """TrafficGen-style multi-context-gating encoder + 512-512-512-128-32 Tanh MLP + Linear(32, 1) + Tanh."""

    architecture = "trafficgen_mcg"
    Config = TrafficGenMCGConfig

    def __init__(self, config: TrafficGenMCGConfig | dict[str, Any] | None = None) -> None:
        super().__init__(config)
        cfg: TrafficGenMCGConfig = self.config  # type: ignore[assignment]
        if cfg.crop_size % cfg.patch:
            raise ValueError(f"`crop_size` ({cfg.crop_size}) must be a multiple of `patch` ({cfg.patch}).")
        self.spec = cfg.feature_spec()
        w = cfg.width
        self.own = nn.Sequential(nn.Linear(self.spec.num_features, w), nn.ReLU(), nn.Linear(w, w), nn.ReLU())
        self.neighbour = nn.Sequential(nn.Linear(NEIGHBOUR_FEATURES, w), nn.ReLU(), nn.Linear(w, w), nn.ReLU())
        map_inputs = len(cfg.map_layers) * cfg.patch * cfg.patch + 2
        self.map_vector = nn.Sequential(nn.Linear(map_inputs, w), nn.ReLU(), nn.Linear(w, w), nn.ReLU())
        self.agent_gating = _GatingStack(w, cfg.gating_blocks)
        self.map_gating = _GatingStack(w, cfg.gating_blocks)
        self.mlp = tanh_head(3 * w, cfg.hidden_sizes)
        side = cfg.crop_size // cfg.patch
        centre = (torch.arange(side, dtype=torch.float32) + 0.5) / side - 0.5  # patch centres, crop sides = 1
        ahead, left = torch.meshgrid(centre + 0.5 - cfg.crop_behind_fraction, centre, indexing="ij")
        self.register_buffer("patch_centres", torch.stack([ahead.flatten(), left.flatten()], -1), persistent=False)

    # ---------------------------------------------------------------- inputs
    def step_inputs(self, scenario: ScenarioTensor, steps: torch.Tensor | None = None) -> StepInputs:
        """The items' own features and crops, with their neighbour vectors appended to the features."""
        cfg: TrafficGenMCGConfig = self.config  # type: ignore[assignment]
        inputs = compute_step_inputs(scenario, self.spec, steps)
        steps = scored_steps(scenario, self.spec.step_dt) if steps is None else torch.as_tensor(steps,
                                                                                               dtype=torch.long)
        item_mask = scenario.valid[:, :, steps] & selected_agents(scenario, self.spec.agents)[:, :, None]
        scene, agent, slot = item_mask.nonzero(as_tuple=True)  # the item order of compute_step_inputs
        vectors = neighbour_vectors(scenario, scene, agent, steps[slot], cfg.num_neighbours, cfg.neighbour_radius_m)
        features = torch.cat([inputs.features, vectors.flatten(1)], 1).contiguous()
        return StepInputs(features, inputs.crops, inputs.scene, inputs.step, inputs.num_scenes, inputs.num_steps,
                          inputs.crop_max)

    # ---------------------------------------------------------------- encoder
    def item_rewards(self, inputs: StepInputs) -> torch.Tensor:
        """Reward of every (agent, step) item ``(N,)`` in [-1, 1]."""
        cfg: TrafficGenMCGConfig = self.config  # type: ignore[assignment]
        inputs = self.on_device(inputs)
        n, f = len(inputs), self.spec.num_features
        own = self.own(inputs.features[:, :f])
        vectors = inputs.features[:, f:].reshape(n, cfg.num_neighbours, NEIGHBOUR_FEATURES)
        agent_set = torch.cat([own[:, None], self.neighbour(vectors)], 1)
        agent_mask = torch.cat([torch.ones(n, 1, dtype=torch.bool, device=own.device), vectors[..., -1] > 0], 1)
        agent_context = self.agent_gating(agent_set, agent_mask, own)
        crops = inputs.crops.to(torch.float32) / inputs.crop_max  # (N, C, S, S)
        p, side = cfg.patch, cfg.crop_size // cfg.patch
        patches = crops.reshape(n, crops.shape[1], side, p, side, p).permute(0, 2, 4, 1, 3, 5).reshape(
            n, side * side, crops.shape[1] * p * p)
        centres = self.patch_centres.to(crops.device).expand(n, -1, -1)
        map_set = self.map_vector(torch.cat([patches, centres], -1))
        map_mask = torch.ones(n, side * side, dtype=torch.bool, device=own.device)
        map_context = self.map_gating(map_set, map_mask, agent_context)
        return self.mlp(torch.cat([own, agent_context, map_context], -1)).squeeze(-1)
