"""TrafficRLHF plugin: the compact CTG diffusion model as traffic model ``ctg``."""

from trafficrlhf_sdk import hookimpl

from trafficrlhf_ctg.adapter import CTGAdapter, CTGOptions, default_checkpoint

__all__ = ["CTGAdapter", "CTGOptions", "default_checkpoint"]


@hookimpl
def register_traffic_models(register):  # type: ignore[no-untyped-def]
    """Register ``ctg`` (factory: :class:`CTGAdapter`, accepts guidance / checkpoint / seed)."""
    register("ctg", CTGAdapter)
