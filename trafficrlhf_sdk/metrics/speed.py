"""Speed against the log: catches models that avoid failures by slowing down or stopping.

Failure rates reward a model that stops: a parked agent neither collides (often) nor leaves the road, and its
acceleration histograms stay narrow, so the realism deviations barely notice either. Compare ``stopped_share``
with ``stopped_share_logged`` and ``speed_ratio`` with 1 beside any drop in the failure rate.
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.metrics.base import Metric, MetricResult
from trafficrlhf_sdk.metrics.failure import nanmean, scene_mean
from trafficrlhf_sdk.simulation.simulator import Rollout

__all__ = ["STOPPED_BELOW_MPS", "SpeedMetric"]

STOPPED_BELOW_MPS = 0.5  # an agent slower than this at the last step counts as stopped


class SpeedMetric(Metric):
    """``speed_ratio``: per scene, the controlled agents' summed simulated speed over the summed logged speed at
    the steps the log has (1 = the log's pace, < 1 slower), averaged over scenes. ``stopped_share``: per scene,
    the share of controlled agents with a logged last step whose simulated speed there is below 0.5 m/s; and
    ``stopped_share_logged``: the same agents' share in the log (the reference for ``stopped_share``)."""

    name = "speed"
    # neither direction is better: the closer speed_ratio is to 1 and stopped_share to stopped_share_logged, the
    # closer the pace is to the log's

    def compute(self, rollout: Rollout) -> MetricResult:
        """speed_ratio (dimensionless), stopped_share and stopped_share_logged (fractions of agents); means
        over scenes with at least one controlled agent (with logged speed, for the ratio)."""
        first, last = rollout.start_index + 1, rollout.end_index + 1
        simulated = rollout.simulated.time_slice(first, last)
        logged = rollout.logged.time_slice(first, last)
        steps = logged.valid & simulated.valid & rollout.controlled[..., None]  # (B, A, T)
        sim_speed = simulated.states[..., 2].double().abs() * steps
        log_speed = logged.states[..., 2].double().abs() * steps
        log_total = log_speed.sum((1, 2))
        ratio = torch.where(log_total > 0, sim_speed.sum((1, 2)) / log_total.clamp_min(1e-9),
                            torch.full_like(log_total, float("nan")))
        at_end = rollout.controlled & logged.valid[..., -1] & simulated.valid[..., -1]
        per_scene = {
            "speed_ratio": ratio,
            "stopped_share": scene_mean(simulated.states[..., -1, 2].abs() < STOPPED_BELOW_MPS, at_end),
            "stopped_share_logged": scene_mean(logged.states[..., -1, 2].abs() < STOPPED_BELOW_MPS, at_end),
        }
        return MetricResult(values={k: nanmean(v) for k, v in per_scene.items()}, per_scene=per_scene)
