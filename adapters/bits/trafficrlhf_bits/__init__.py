"""TrafficRLHF plugin: the compact BITS (spatial goal network + frozen goal-conditioned policy) as traffic model
``bits``. The bundled weights are trained on nuScenes (CC BY-NC-SA 4.0, non-commercial)."""

from trafficrlhf_sdk import hookimpl

from trafficrlhf_bits.adapter import BITSAdapter, BITSOptions, default_checkpoint

__all__ = ["BITSAdapter", "BITSOptions", "default_checkpoint"]


@hookimpl
def register_traffic_models(register):  # type: ignore[no-untyped-def]
    """Register ``bits`` (factory: :class:`BITSAdapter`, accepts guidance / plan_samples / checkpoint / seed)."""
    register("bits", BITSAdapter)
