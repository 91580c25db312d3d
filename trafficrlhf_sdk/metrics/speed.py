"""Speed against the log: catches models that avoid failures by slowing down or stopping.

Failure rates reward a model that stops: a parked agent neither collides (often) nor leaves the road, and its
acceleration histograms stay narrow, so the realism deviations barely notice either. Compare ``stopped_share``
with ``stopped_share_logged`` and ``speed_ratio`` with 1 beside any drop in the failure rate.
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.metrics.base import Metric, MetricResult
from trafficrlhf_sdk.metrics.failure import nanmean, scene_mean
from trafficrlhf_sdk.metrics.turns import TURN_RAD, turning_agents
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.simulator import Rollout

__all__ = ["STOPPED_BELOW_MPS", "TURN_RAD", "SpeedMetric", "pooled_speed_ratio", "turning_agents"]

STOPPED_BELOW_MPS = 0.5  # an agent slower than this at the last step counts as stopped


class SpeedMetric(Metric):
    """``speed_ratio``: per scene, the controlled agents' summed simulated speed over the summed logged speed at
    the steps the log has (1 = the log's pace, < 1 slower), averaged over scenes. ``stopped_share``: per scene,
    the share of controlled agents with a logged last step whose simulated speed there is below 0.5 m/s; and
    ``stopped_share_logged``: the same agents' share in the log (the reference for ``stopped_share``).
    ``speed_ratio_turning`` / ``speed_ratio_straight``: ``speed_ratio`` over only the agents whose logged heading
    changes by more than / at most :data:`TURN_RAD` between their first and last logged step of the rollout (means
    over the scenes that have such agents): where a model's pace changed, in turns or on the straight."""

    name = "speed"
    # neither direction is better: the closer speed_ratio is to 1 and stopped_share to stopped_share_logged, the
    # closer the pace is to the log's

    def compute(self, rollout: Rollout) -> MetricResult:
        """speed_ratio, speed_ratio_turning and speed_ratio_straight (dimensionless), stopped_share and
        stopped_share_logged (fractions of agents); means over scenes with at least one such controlled agent (with
        logged speed, for the ratios)."""
        simulated, logged, steps, sim_speed, log_speed = _speeds(rollout)
        turning = turning_agents(logged, steps)
        ratio, ratio_turning, ratio_straight = (_ratio(sim_speed, log_speed, agents)
                                                for agents in (None, turning, ~turning))
        at_end = rollout.controlled & logged.valid[..., -1] & simulated.valid[..., -1]
        per_scene = {
            "speed_ratio": ratio,
            "speed_ratio_turning": ratio_turning,
            "speed_ratio_straight": ratio_straight,
            "stopped_share": scene_mean(simulated.states[..., -1, 2].abs() < STOPPED_BELOW_MPS, at_end),
            "stopped_share_logged": scene_mean(logged.states[..., -1, 2].abs() < STOPPED_BELOW_MPS, at_end),
        }
        return MetricResult(values={k: nanmean(v) for k, v in per_scene.items()}, per_scene=per_scene)


def pooled_speed_ratio(rollout: Rollout, turning: bool | None = None) -> float:
    """The summed simulated speed of every controlled agent of every scene over their summed logged speed, at the
    steps the log has (NaN without any). Unlike ``speed_ratio`` (a mean of per-scene ratios) a scene whose logged
    agents barely move does not swing it, so it is the quieter statistic for one fixed set of scenes. ``turning``:
    only the agents that turn in the log (True) or the others (False), as ``speed_ratio_turning`` splits them."""
    _, logged, steps, sim_speed, log_speed = _speeds(rollout)
    if turning is not None:
        agents = turning_agents(logged, steps) == turning
        sim_speed, log_speed = sim_speed * agents[..., None], log_speed * agents[..., None]
    log_total = float(log_speed.sum())
    return float(sim_speed.sum()) / log_total if log_total > 0 else float("nan")


def _speeds(rollout: Rollout) -> tuple[ScenarioTensor, ScenarioTensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The rollout's simulated and logged steps after the start, the steps both have for controlled agents
    ``(B, A, T)``, and the simulated and logged absolute speeds there (0 elsewhere; double)."""
    first, last = rollout.start_index + 1, rollout.end_index + 1
    simulated = rollout.simulated.time_slice(first, last)
    logged = rollout.logged.time_slice(first, last)
    steps = logged.valid & simulated.valid & rollout.controlled[..., None]
    sim_speed = simulated.states[..., 2].double().abs() * steps
    log_speed = logged.states[..., 2].double().abs() * steps
    return simulated, logged, steps, sim_speed, log_speed


def _ratio(sim_speed: torch.Tensor, log_speed: torch.Tensor, agents: torch.Tensor | None) -> torch.Tensor:
    """``(B,)``: summed simulated over summed logged speed ``(B, A, T)`` of ``agents (B, A)`` (all: None); NaN where
    they have no logged speed."""
    if agents is not None:
        sim_speed, log_speed = sim_speed * agents[..., None], log_speed * agents[..., None]
    log_total = log_speed.sum((1, 2))
    return torch.where(log_total > 0, sim_speed.sum((1, 2)) / log_total.clamp_min(1e-9),
                       torch.full_like(log_total, float("nan")))
