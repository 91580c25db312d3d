"""TrafficRLHF plugin: the compact CTG diffusion model as traffic model ``ctg``, with its bundled checkpoints
``ctg`` (2 s plan), ``ctg-4s`` (4 s plan), ``ctg-aligned`` (the 4 s model aligned against a learned reward
model) and ``ctg-baseline`` (aligned against hand-written rewards, a baseline). The weights are
trained on nuScenes (CC BY-NC-SA 4.0, non-commercial)."""

from __future__ import annotations

from trafficrlhf_sdk import hookimpl
from trafficrlhf_sdk.lazy import lazy_exports
from trafficrlhf_sdk.registry import Lazy, register_folders

_EXPORTS = {
    "CTGAdapter": "adapter",
    "CTGOptions": "adapter",
    "default_checkpoint": "adapter",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


@hookimpl
def register_traffic_models(register):  # type: ignore[no-untyped-def]
    """Register ``ctg`` (factory: :class:`CTGAdapter`; imported when first used)."""
    register("ctg", Lazy("trafficrlhf_ctg.adapter:CTGAdapter"))


@hookimpl
def register_pretrained(register):  # type: ignore[no-untyped-def]
    """Register the bundled checkpoints (folders beside the reference package, found without importing it)."""
    register_folders(register, "ctg_reference", {
        "ctg": "checkpoints/ctg_small",
        "ctg-4s": "checkpoints/ctg_small_4s",
        "ctg-baseline": "../baselines/ctg",
        "ctg-aligned": "../aligned/ctg",
    })
