"""TrafficRLHF plugin: the compact TrafficGen (initializer + multi-modal forecaster) as traffic model
``trafficgen``, with its bundled checkpoints ``trafficgen`` (2 s), ``trafficgen-4s`` and ``trafficgen-baseline``
(the 4 s model aligned with PPO). The weights are trained on nuScenes (CC BY-NC-SA 4.0, non-commercial)."""

from __future__ import annotations

from trafficrlhf_sdk import hookimpl
from trafficrlhf_sdk.lazy import lazy_exports
from trafficrlhf_sdk.registry import Lazy, register_folders

_EXPORTS = {
    "TrafficGenAdapter": "adapter",
    "TrafficGenOptions": "adapter",
    "default_checkpoint": "adapter",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


@hookimpl
def register_traffic_models(register):  # type: ignore[no-untyped-def]
    """Register ``trafficgen`` (factory: :class:`TrafficGenAdapter`; imported when first used)."""
    register("trafficgen", Lazy("trafficrlhf_trafficgen.adapter:TrafficGenAdapter"))


@hookimpl
def register_pretrained(register):  # type: ignore[no-untyped-def]
    """Register the bundled checkpoints (folders beside the reference package, found without importing it)."""
    register_folders(register, "trafficgen_reference", {
        "trafficgen": "checkpoints/trafficgen_small",
        "trafficgen-4s": "checkpoints/trafficgen_small_4s",
        "trafficgen-baseline": "../baselines/trafficgen",
    })
