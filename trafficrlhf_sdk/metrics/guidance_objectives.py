"""How well a rollout meets each guidance objective, whether or not guidance was used (for comparisons)."""

from __future__ import annotations

from trafficrlhf_sdk.metrics.base import Metric, MetricResult
from trafficrlhf_sdk.simulation.simulator import Rollout

__all__ = ["GuidanceObjectivesMetric"]


class GuidanceObjectivesMetric(Metric):
    """``guidance_speed_limit`` (mean excess speed over the scene's heuristic limit, m/s),
    ``guidance_target_speed`` (mean |v - logged v|, m/s), ``guidance_goal_waypoint`` (closest approach to the
    logged position 7.5 s after the start, m). Collision and off-road objectives are the failure metrics."""

    name = "guidance_objectives"

    def compute(self, rollout: Rollout) -> MetricResult:
        """The three objectives, means over controlled agents of all scenes."""
        from trafficrlhf_sdk.simulation.guidance import guidance_objectives

        return MetricResult(values=guidance_objectives(rollout.simulated, rollout.logged, rollout.controlled,
                                                       rollout.start_index, rollout.end_index))
