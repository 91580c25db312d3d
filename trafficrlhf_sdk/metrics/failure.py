"""Failure rate: share of controlled agents that ever collide or ever leave the road (tbsim ``CriticalFailure``)."""

from __future__ import annotations

import math
from typing import Literal

import torch

from trafficrlhf_sdk.metrics.base import Metric, MetricResult
from trafficrlhf_sdk.metrics.geometry import box_corners, colliding_pairs, pair_step_flags, pairwise_collisions
from trafficrlhf_sdk.metrics.turns import turning_agents
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.simulator import Rollout

__all__ = ["FailureMetric", "collision_partner_kinds", "collisions_per_step", "offroad_corner_share",
           "offroad_per_step", "scene_mean"]

OffroadMode = Literal["center", "corners"]


def collisions_per_step(scenario: ScenarioTensor) -> torch.Tensor:
    """bool ``(B, A, T)``: the agent's box overlaps another valid agent's box at that step (exact test in float64)."""
    return pairwise_collisions(scenario.xy, scenario.yaw, scenario.extent, scenario.valid)


def offroad_per_step(scenario: ScenarioTensor, mode: OffroadMode = "center") -> torch.Tensor:
    """bool ``(B, A, T)``: the agent's centre (``mode="center"``, upstream) or any box corner
    (``mode="corners"``, stricter) lies off the drivable layer at a valid step."""
    if scenario.map is None:
        raise ValueError("off-road needs a map: the scenario has `map=None`; load it from a source with rasters.")
    if mode not in ("center", "corners"):
        raise ValueError(f"`mode` must be 'center' or 'corners'; got {mode!r}.")
    if mode == "corners":
        return offroad_corner_share(scenario) > 0
    # only valid steps are looked up (most agent slots are padding); float64 pixel coordinates give the pixel of
    # the stored position, not of a float32-rounded transform of it
    scene, agent, step = scenario.valid.nonzero(as_tuple=True)
    on_road = scenario.map.lookup_points(scene, scenario.xy[scene, agent, step].double())
    offroad = torch.zeros_like(scenario.valid)
    offroad[scene, agent, step] = ~on_road
    return offroad


def offroad_corner_share(scenario: ScenarioTensor) -> torch.Tensor:
    """float ``(B, A, T)``: share (0, 0.25, ..., 1) of the agent's four box corners off the drivable layer at a
    valid step (0 at invalid steps). Needs a map."""
    if scenario.map is None:
        raise ValueError("off-road needs a map: the scenario has `map=None`; load it from a source with rasters.")
    scene, agent, step = scenario.valid.nonzero(as_tuple=True)
    corners = box_corners(scenario.xy[scene, agent, step].double(), scenario.yaw[scene, agent, step].double(),
                          scenario.extent[scene, agent].double())
    on_road = scenario.map.lookup_points(scene.repeat_interleave(4), corners.reshape(-1, 2)).reshape(-1, 4)
    share = torch.zeros(scenario.valid.shape, dtype=torch.float32, device=scenario.valid.device)
    share[scene, agent, step] = (~on_road).float().mean(-1)
    return share


def scene_mean(per_agent: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``per_agent (B, A)`` over agents where ``mask (B, A)``; NaN for scenes without any.

    float64, so a share of agents is the correctly rounded ratio of two counts (float32 turned 0.5265 into
    0.52649998...).
    """
    count = mask.sum(-1).double()
    total = (per_agent.double() * mask).sum(-1)
    return torch.where(count > 0, total / count.clamp_min(1), torch.full_like(total, float("nan")))


def nanmean(values: torch.Tensor) -> float:
    """Mean over finite entries (NaN if none), with an exactly rounded sum (``math.fsum``) so the result does not
    depend on the order or batching of the scenes."""
    finite = values[torch.isfinite(values)]
    return math.fsum(finite.double().tolist()) / finite.numel() if finite.numel() else float("nan")


def collision_partner_kinds(scene: torch.Tensor, i: torch.Tensor, j: torch.Tensor, controlled: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """bool ``(B, A)`` each, from the overlapping pairs ``(scene, i, j)`` of :func:`colliding_pairs`: the agent ever
    overlaps an agent the policy drives (``controlled (B, A)``), and ever overlaps one replayed from the log (which
    cannot react)."""
    own, replayed = torch.zeros_like(controlled), torch.zeros_like(controlled)
    for me, other in ((i, j), (j, i)):
        partner_driven = controlled[scene, other]
        own[scene[partner_driven], me[partner_driven]] = True
        replayed[scene[~partner_driven], me[~partner_driven]] = True
    return own, replayed


class FailureMetric(Metric):
    """Per scene, the share of controlled agents that collide or go off-road at any simulated 0.1 s step;
    averaged over scenes. Also the collision-only and off-road-only shares, and the collisions split by partner:
    ``collision_rate_own`` (ever touching another agent the policy drives) and ``collision_rate_replayed`` (ever
    touching a log-replayed agent, which cannot react; with ``offroad_mode="center"``, the default); an agent can
    be in both, so they may sum to more than ``collision_rate``. With that default, ``failure_rate_turning`` and
    ``failure_rate_straight`` are ``failure_rate`` over only the agents that turn in the log and over the others
    (:func:`~trafficrlhf_sdk.metrics.turns.turning_agents`, the speed metric's split; means over the scenes that
    have such agents).

    Args:
        offroad_mode: ``"center"`` (upstream: centre pixel on the drivable layer) or ``"corners"`` (all four
            box corners must be on it).
    """

    name = "failure"

    def __init__(self, offroad_mode: OffroadMode = "center") -> None:
        self.offroad_mode = offroad_mode

    def compute(self, rollout: Rollout) -> MetricResult:
        """failure_rate, collision_rate, offroad_rate, collision_rate_own, collision_rate_replayed,
        failure_rate_turning, failure_rate_straight (fractions of agents, mean over scenes)."""
        window = rollout.simulated.time_slice(rollout.start_index + 1, rollout.end_index + 1)
        scene, i, j, step = colliding_pairs(window.xy, window.yaw, window.extent, window.valid)
        # as collisions_per_step, from the pairs listed once (the partner kinds below read them too)
        collision_steps = pair_step_flags(window.valid, scene, i, j, step) & window.valid
        offroad_steps = offroad_per_step(window, self.offroad_mode)
        collided, offroad = collision_steps.any(-1), offroad_steps.any(-1)
        mask = rollout.controlled
        per_scene = {
            "failure_rate": scene_mean(collided | offroad, mask),
            "collision_rate": scene_mean(collided, mask),
            "offroad_rate": scene_mean(offroad, mask),
        }
        if self.offroad_mode == "center":
            own, replayed = collision_partner_kinds(scene, i, j, mask)
            logged = rollout.logged.time_slice(rollout.start_index + 1, rollout.end_index + 1)
            turning = turning_agents(logged, logged.valid & window.valid & mask[..., None])
            per_scene.update(collision_rate_own=scene_mean(own, mask),
                             collision_rate_replayed=scene_mean(replayed, mask),
                             failure_rate_turning=scene_mean(collided | offroad, mask & turning),
                             failure_rate_straight=scene_mean(collided | offroad, mask & ~turning))
        suffix = "" if self.offroad_mode == "center" else "_corners"
        per_scene = {f"{k}{suffix}" if not k.startswith("collision_rate") else k: v for k, v in per_scene.items()}
        return MetricResult(
            values={k: nanmean(v) for k, v in per_scene.items()},
            per_scene=per_scene,
            # (B, A) "ever" flags, and the (B, A, T) flags per simulated step start_index+1 .. end_index
            extras={"collided": collided, "offroad": offroad, "collision_steps": collision_steps,
                    "offroad_steps": offroad_steps},
        )
