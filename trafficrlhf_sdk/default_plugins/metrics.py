"""Built-in metrics, registered like any plugin's."""

from __future__ import annotations

from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.registry import Lazy, Register


@hookimpl
def register_metrics(register: Register) -> None:
    """failure, failure_corners, realism_ctg, realism_body, guidance_objectives, speed."""
    register("failure", Lazy("trafficrlhf_sdk.metrics.failure:FailureMetric", "center"))
    register("failure_corners", Lazy("trafficrlhf_sdk.metrics.failure:FailureMetric", "corners"))
    register("realism_ctg", Lazy("trafficrlhf_sdk.metrics.realism:RealismMetric", "ctg"))
    register("realism_body", Lazy("trafficrlhf_sdk.metrics.realism:RealismMetric", "body"))
    register("guidance_objectives",
             Lazy("trafficrlhf_sdk.metrics.guidance_objectives:GuidanceObjectivesMetric", call=True))
    register("speed", Lazy("trafficrlhf_sdk.metrics.speed:SpeedMetric", call=True))
