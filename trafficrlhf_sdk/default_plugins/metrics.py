"""Built-in metrics, registered like any plugin's."""

from __future__ import annotations

from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.metrics import FailureMetric, GuidanceObjectivesMetric, RealismMetric, SpeedMetric
from trafficrlhf_sdk.registry import Register


@hookimpl
def register_metrics(register: Register) -> None:
    """failure, failure_corners, realism_ctg, realism_body, guidance_objectives, speed."""
    register("failure", FailureMetric("center"))
    register("failure_corners", FailureMetric("corners"))
    register("realism_ctg", RealismMetric("ctg"))
    register("realism_body", RealismMetric("body"))
    register("guidance_objectives", GuidanceObjectivesMetric())
    register("speed", SpeedMetric())
