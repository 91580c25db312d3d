"""The paper's reward model (``"ctg_mlp"``): a CTG-style context encoder and a 512-512-512-128-32 Tanh MLP.

For every selected agent and every scored step (every ``step_dt``, 2 Hz by default) the encoder builds the
agent-centric inputs of :mod:`trafficrlhf_sdk.reward.features`: a map crop (three layers, 16 x 16 cells of
1 m) through a small CNN, the agent's recent states, its neighbours and drivable-area look-ups. The MLP maps
them to a reward with Tanh after every layer, the 1-unit output included, so each (agent, step) reward lies in
[-1, 1]. The per-step reward is the mean over the agents present at that step and the scenario reward the mean
over the scored steps. Nothing depends on T or A: the model is applied step by step (iteratively over time),
so any length, any number of agents and any padding work; invalid steps and padding agents are skipped.
"""

from __future__ import annotations

from typing import Annotated, Any

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from trafficrlhf_sdk.reward.features import FeatureSpec, StepInputs, compute_step_inputs, scored_steps, selected_agents
from trafficrlhf_sdk.reward.model import RewardModel
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["MAX_LAYER_WIDTH", "CTGMLPConfig", "CTGMLPRewardModel", "ItemRewardModel", "LayerWidth", "tanh_head"]

MAX_LAYER_WIDTH = 8192  # one 8192 x 8192 layer is 268 MB of float32 weights; the paper's widest is 512
LayerWidth = Annotated[int, Field(ge=1, le=MAX_LAYER_WIDTH)]


class StepFeatureOptions(BaseModel):
    """The per-(agent, step) feature settings every built-in reward architecture shares (stored in its
    ``config.json``); :meth:`feature_spec` turns them into the :class:`FeatureSpec` of feature extraction."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    step_dt: float = Field(0.5, gt=0, description="Seconds between scored steps (2 Hz as the paper's reward cost).")
    history_steps: int = Field(0, ge=0, le=100, description="Raw past states seen per step, every `step_dt` (the "
                                                     "kinematics always use the last two); 0 generalises best.")
    num_neighbours: int = Field(6, ge=0, le=256, description="Nearest other agents seen per step.")
    neighbour_radius_m: float = Field(40.0, gt=0, description="Agents farther than this (m) are not neighbours.")
    crop_size: int = Field(16, ge=4, le=512, description="Map crop cells per side (a multiple of the architecture's "
                                                 "downsampling: 4 for ctg_mlp, `patch` for trafficgen_mcg).")
    crop_resolution_m: float = Field(1.0, gt=0, description="Size of a crop cell (m).")
    crop_supersample: int = Field(2, ge=1, le=15, description="Raster samples per cell side (averaged).")
    crop_behind_fraction: float = Field(0.25, ge=0, le=1, description="Share of the crop behind the agent.")
    map_layers: tuple[str, ...] = Field(("drivable", "road_divider", "lane_divider"),
                                        description="Map layers of the crop, by name (missing ones are empty).")
    agents: str = Field("controlled", pattern="^(controlled|all)$",
                        description="Agents averaged: 'controlled' (those a model drove, else all) or 'all'.")
    scene_context: bool = Field(True, description="Also see what an annotator sees around each agent since the "
                                "candidates started: events between 2 Hz samples, pace against its own history, "
                                "its lead and its neighbours' flow, weaving (see `reward.scene_context`).")

    def feature_spec(self) -> FeatureSpec:
        """The feature extraction settings."""
        return FeatureSpec(step_dt=self.step_dt, history_steps=self.history_steps, num_neighbours=self.num_neighbours,
                           neighbour_radius_m=self.neighbour_radius_m, crop_size=self.crop_size,
                           crop_resolution_m=self.crop_resolution_m, crop_supersample=self.crop_supersample,
                           crop_behind_fraction=self.crop_behind_fraction, map_layers=self.map_layers,
                           agents=self.agents, scene_context=self.scene_context)


class CTGMLPConfig(StepFeatureOptions):
    """Options of :class:`CTGMLPRewardModel` (stored in ``config.json``)."""

    hidden_sizes: tuple[LayerWidth, ...] = Field((512, 512, 512, 128, 32), min_length=1, max_length=32,
                                                 description="MLP widths (the paper's 512-512-512-128-32), each 1 to "
                                                             "8192; Tanh after each.")
    map_channels: tuple[LayerWidth, LayerWidth] = Field((16, 32), description="Channels of the two stride-2 conv "
                                                                              "layers (each 1 to 8192).")
    map_embedding: LayerWidth = Field(64, description="Size of the map code fed to the MLP (1 to 8192).")


def tanh_head(width: int, hidden_sizes: tuple[int, ...]) -> nn.Sequential:
    """The paper's reward head: Linear + Tanh for each of ``hidden_sizes`` and for the 1-unit output.

    Glorot init with the Tanh gain keeps activations alive through six Tanh layers (PyTorch's default shrinks
    them layer by layer); a small output layer starts every reward near 0, far from saturation.
    """
    layers: list[nn.Module] = []
    for size in (*hidden_sizes, 1):
        layers += [nn.Linear(width, size), nn.Tanh()]
        width = size
    head = nn.Sequential(*layers)
    linears = [m for m in head if isinstance(m, nn.Linear)]
    for i, linear in enumerate(linears):
        gain = 0.1 if i == len(linears) - 1 else nn.init.calculate_gain("tanh")
        nn.init.xavier_uniform_(linear.weight, gain=gain)
        nn.init.zeros_(linear.bias)
    return head


class ItemRewardModel(RewardModel):
    """Base of the reward models that score every (selected agent, scored step) item and average them.

    A subclass sets ``self.spec`` (a :class:`FeatureSpec`) and implements :meth:`item_rewards`; it may override
    :meth:`step_inputs` to add inputs to each item. The aggregation (mean over the agents present at a step, then
    over the scored steps) and the any-length, any-agents, valid-mask contract are shared.
    """

    spec: FeatureSpec

    def step_inputs(self, scenario: ScenarioTensor, steps: torch.Tensor | None = None) -> StepInputs:
        """Inputs of every selected agent at ``steps`` (default: the scored steps)."""
        return compute_step_inputs(scenario, self.spec, steps)

    def item_rewards(self, inputs: StepInputs) -> torch.Tensor:
        """Reward of every (agent, step) item ``(N,)`` in [-1, 1]."""
        raise NotImplementedError

    @staticmethod
    def _group_mean(key: torch.Tensor, rewards: torch.Tensor, groups: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean item reward per group ``(groups,)`` (0 where empty) and the number of items there."""
        key = key.to(rewards.device)
        total = torch.zeros(groups, dtype=rewards.dtype, device=rewards.device).index_add(0, key, rewards)
        count = torch.zeros(groups, dtype=rewards.dtype, device=rewards.device).index_add(0, key,
                                                                                         torch.ones_like(rewards))
        return total / count.clamp_min(1), count

    @classmethod
    def _per_step(cls, inputs: StepInputs, rewards: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean item reward per (scene, step) ``(B, T)`` and the number of items there ``(B, T)``."""
        b, t = inputs.num_scenes, inputs.num_steps
        mean, count = cls._group_mean(inputs.scene * t + inputs.step, rewards, b * t)
        return mean.reshape(b, t), count.reshape(b, t)

    # ----------------------------------------------------------------- contract
    def prepare(self, scenario: ScenarioTensor) -> StepInputs:
        """Inputs at the scored steps (no gradient needed; compute once, score many times)."""
        return self.step_inputs(scenario)

    def score_prepared(self, prepared: StepInputs) -> torch.Tensor:
        """Scenario rewards ``(B,)``: mean over scored steps of the mean over agents; 0 for empty scenes."""
        per_step, count = self._per_step(prepared, self.item_rewards(prepared))
        present = (count > 0).to(per_step.dtype)
        return (per_step * present).sum(1) / present.sum(1).clamp_min(1)

    def forward(self, scenario: ScenarioTensor) -> torch.Tensor:
        """Scenario rewards ``(B,)`` in [-1, 1].

        The mean of the per-step rewards every ``step_dt`` after ``current_index``; steps without a selected valid
        agent do not count and an empty scene scores 0.
        """
        return self.score_prepared(self.prepare(scenario))

    def agent_scores(self, scenario: ScenarioTensor) -> torch.Tensor:
        """Per-agent rewards ``(B, A)`` in [-1, 1]: each selected agent's item rewards averaged over the scored
        steps where it is valid (0 for other agents). :meth:`forward` averages over agents first, then steps."""
        inputs = self.prepare(scenario)
        steps = scored_steps(scenario, self.spec.step_dt)
        item_mask = scenario.valid[:, :, steps] & selected_agents(scenario, self.spec.agents)[:, :, None]
        scene, agent, _ = item_mask.nonzero(as_tuple=True)  # the item order of compute_step_inputs
        b, a = scenario.num_scenes, scenario.num_agents
        mean, _ = self._group_mean(scene * a + agent, self.item_rewards(inputs), b * a)
        return mean.reshape(b, a)

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        """Per-step rewards ``(B, T)`` in [-1, 1] at every step of ``scenario``.

        Each is the mean over the selected agents valid at that step (0 where there is none); each step sees the
        states ``step_dt`` and ``2 * step_dt`` before it.
        """
        inputs = self.step_inputs(scenario, torch.arange(scenario.num_steps))
        per_step, _ = self._per_step(inputs, self.item_rewards(inputs))
        return per_step


class CTGMLPRewardModel(ItemRewardModel):
    """CTG-style context encoder + 512-512-512-128-32 Tanh MLP + Linear(32, 1) + Tanh, per agent and step."""

    architecture = "ctg_mlp"
    Config = CTGMLPConfig

    def __init__(self, config: CTGMLPConfig | dict[str, Any] | None = None) -> None:
        super().__init__(config)
        cfg: CTGMLPConfig = self.config  # type: ignore[assignment]
        if cfg.crop_size % 4:
            raise ValueError(f"`crop_size` must be a multiple of 4 (two stride-2 convolutions); got {cfg.crop_size}.")
        self.spec = cfg.feature_spec()
        c1, c2 = cfg.map_channels
        side = cfg.crop_size // 4
        self.map_encoder = nn.Sequential(
            nn.Conv2d(len(cfg.map_layers), c1, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(c1, c2, 3, stride=2, padding=1), nn.ReLU(), nn.Flatten(),
            nn.Linear(c2 * side * side, cfg.map_embedding), nn.Tanh(),
        )
        self.mlp = tanh_head(self.spec.num_features + cfg.map_embedding, cfg.hidden_sizes)

    # ---------------------------------------------------------------- internals
    def item_rewards(self, inputs: StepInputs) -> torch.Tensor:
        """Reward of every (agent, step) item ``(N,)`` in [-1, 1]."""
        inputs = self.on_device(inputs)
        crops = inputs.crops.to(torch.float32) / inputs.crop_max
        code = self.map_encoder(crops)
        return self.mlp(torch.cat([inputs.features, code], -1)).squeeze(-1)
