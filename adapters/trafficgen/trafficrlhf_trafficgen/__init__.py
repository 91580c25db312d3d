"""TrafficRLHF plugin: the compact TrafficGen (initializer + multi-modal forecaster) as traffic model ``trafficgen``.

The bundled checkpoint was trained on nuScenes (CC BY-NC-SA 4.0, non-commercial).
"""

from trafficrlhf_sdk import hookimpl

from trafficrlhf_trafficgen.adapter import TrafficGenAdapter, TrafficGenOptions, default_checkpoint

__all__ = ["TrafficGenAdapter", "TrafficGenOptions", "default_checkpoint"]


@hookimpl
def register_traffic_models(register):  # type: ignore[no-untyped-def]
    """Register ``trafficgen`` (factory: :class:`TrafficGenAdapter`, accepts guidance / checkpoint / seed)."""
    register("trafficgen", TrafficGenAdapter)
