"""``example_gru``: an example TrafficRLHF traffic model, a GRU policy with a stochastic Gaussian head.

It encodes each agent's history, its nearest neighbours and a low-resolution map crop, then a GRU decoder
emits, step by step for 2 s at 0.1 s, a diagonal Gaussian over (acceleration, yaw rate); sampled actions are
rolled through the SDK's unicycle dynamics. The adapter registers itself as the traffic model ``example_gru``
through the ``trafficrlhf_sdk`` entry point. The bundled checkpoint was trained on nuScenes (CC BY-NC-SA 4.0,
non-commercial).
"""

from trafficrlhf_sdk import hookimpl
from trafficrlhf_sdk.lazy import lazy_exports
from trafficrlhf_sdk.registry import Lazy

_EXPORTS = {
    "BUNDLED_CHECKPOINT": "adapter",
    "ExampleGRUAdapter": "adapter",
    "GRUConfig": "model",
    "GRUPolicyNet": "model",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


@hookimpl
def register_traffic_models(register):  # type: ignore[no-untyped-def]
    """Register ``example_gru`` (imported when first used)."""
    register("example_gru", Lazy("trafficrlhf_example_gru.adapter:ExampleGRUAdapter"))
