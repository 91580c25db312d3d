"""TrafficRLHF plugin: the compact BITS (spatial goal network + frozen goal-conditioned policy) as traffic model
``bits``, with its bundled checkpoints ``bits`` and ``bits-baseline``. The weights are trained on nuScenes
(CC BY-NC-SA 4.0, non-commercial)."""

from __future__ import annotations

from trafficrlhf_sdk import hookimpl
from trafficrlhf_sdk.lazy import lazy_exports
from trafficrlhf_sdk.registry import Lazy, register_folders

_EXPORTS = {
    "BITSAdapter": "adapter",
    "BITSOptions": "adapter",
    "default_checkpoint": "adapter",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


@hookimpl
def register_traffic_models(register):  # type: ignore[no-untyped-def]
    """Register ``bits`` (factory: :class:`BITSAdapter`; imported when first used)."""
    register("bits", Lazy("trafficrlhf_bits.adapter:BITSAdapter"))


@hookimpl
def register_pretrained(register):  # type: ignore[no-untyped-def]
    """Register the bundled checkpoints (folders beside the reference package, found without importing it)."""
    register_folders(register, "bits_reference", {
        "bits": "checkpoints/bits_small",
        "bits-baseline": "../baselines/bits",
    })
