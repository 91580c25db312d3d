"""What a person watching a scenario sees around each agent, per step: near misses, tailgating, the agent it
follows, the speed it drove at before ``current_index`` and the neighbours that make its flow.

The stand-in annotators' judgment (:mod:`~trafficrlhf_sdk.feedback.judgment`) and the reward model's scene-context
inputs (:mod:`~trafficrlhf_sdk.reward.scene_context`) both read these, so a reward model sees each cue exactly as
the judgment measures it. Shapes follow :class:`~trafficrlhf_sdk.scenario.tensor.ScenarioTensor`: ``(B, A, T)``
per step, ``(B, A)`` per agent.
"""

from __future__ import annotations

import math

import torch

from trafficrlhf_sdk.metrics.failure import collisions_per_step
from trafficrlhf_sdk.metrics.geometry import colliding_pairs, pair_step_flags, path_gaps
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["PathCues", "flow_neighbours", "near_misses_per_step", "path_cues", "recent_speed"]


def near_misses_per_step(scenario: ScenarioTensor, margin_m: float,
                         collided: torch.Tensor | None = None) -> torch.Tensor:
    """bool ``(B, A, T)``: the agent's box comes within ``margin_m`` of another's (both grown by it) without
    touching it (``collided``: :func:`~trafficrlhf_sdk.metrics.failure.collisions_per_step`, computed if None)."""
    if margin_m <= 0:
        return torch.zeros_like(scenario.valid)
    grown = scenario.extent + 2 * margin_m
    close = pair_step_flags(scenario.valid, *colliding_pairs(scenario.xy, scenario.yaw, grown, scenario.valid))
    return close & ~(collisions_per_step(scenario) if collided is None else collided)


class PathCues:
    """The agents in each agent's path ahead, per step (:func:`path_cues`).

    Fields (each ``(B, A, T)``): ``tailgating`` (bool: a time to collision below ``ttc_s`` with an agent in the
    path, or a time headway below ``headway_s`` while driving above ``driving_speed``), ``lead_gap`` (m, bumper to
    bumper to the nearest agent in the path; ``inf`` when none), ``lead_closing`` (m/s, positive when closing in)
    and ``lead_index`` (that agent's index; meaningful where ``lead_gap`` is finite).
    """

    def __init__(self, tailgating: torch.Tensor, lead_gap: torch.Tensor, lead_closing: torch.Tensor,
                 lead_index: torch.Tensor) -> None:
        self.tailgating, self.lead_gap, self.lead_closing, self.lead_index = (tailgating, lead_gap, lead_closing,
                                                                              lead_index)


def path_cues(scenario: ScenarioTensor, ttc_s: float, headway_s: float, driving_speed: float) -> PathCues:
    """Tailgating flags and the lead of every agent at every step (see :class:`PathCues`)."""
    speed = scenario.states[..., 2]
    gap, closing, in_path = path_gaps(scenario.xy, scenario.yaw, speed, scenario.extent, scenario.valid)
    inf = torch.full_like(gap, math.inf)
    ttc = torch.where(in_path & (closing > 0), gap / closing.clamp_min(1e-6), inf).amin(2)
    headway = torch.where(in_path, gap / speed[:, :, None].clamp_min(1e-6), inf).amin(2)
    tailgating = (ttc < ttc_s) | ((headway < headway_s) & (speed > driving_speed))
    lead = torch.where(in_path, gap, inf).min(2)
    lead_closing = closing.gather(2, lead.indices[:, :, None]).squeeze(2)
    return PathCues(tailgating, lead.values, lead_closing, lead.indices)


def recent_speed(scenario: ScenarioTensor, seconds: float = 1.0) -> torch.Tensor:
    """``(B, A)`` m/s: the distance each agent covered over the last ``seconds`` up to ``current_index`` divided by
    that time, as the history shows it; where either end is not valid, the mean of its speed channel over those
    steps (0 for an agent not seen)."""
    now, dt = scenario.current_index, scenario.dt
    states, valid = scenario.states.double(), scenario.valid
    back = max(0, now - round(seconds / dt))
    covered = torch.linalg.vector_norm(states[:, :, now, :2] - states[:, :, back, :2], dim=-1)
    recent = valid.clone()
    recent[:, :, now + 1:] = False
    recent[:, :, :back] = False
    channel = (states[..., 2] * recent).sum(-1) / recent.sum(-1).clamp_min(1)
    seen = valid[:, :, now] & valid[:, :, back] & (now > back)
    return torch.where(seen, covered / max((now - back) * dt, 1e-9), channel)


def flow_neighbours(scenario: ScenarioTensor, radius_m: float) -> torch.Tensor:
    """bool ``(B, A, A)``: agent ``j`` is in agent ``i``'s flow, near it (within ``radius_m``) at
    ``current_index`` and heading within 45 degrees of its heading, both valid then, never itself."""
    now = scenario.current_index
    valid = scenario.valid[:, :, now]
    xy0, yaw0 = scenario.states[:, :, now, :2].double(), scenario.states[:, :, now, 3].double()
    same_way = torch.cos(yaw0[:, :, None] - yaw0[:, None, :]) > math.cos(math.pi / 4)
    eye = torch.eye(scenario.num_agents, dtype=torch.bool, device=valid.device)[None]
    return (torch.cdist(xy0, xy0) <= radius_m) & same_way & valid[:, :, None] & valid[:, None, :] & ~eye
