"""Scenario source ``nuscenes_pred``: nuScenes prediction scenes (2 Hz labels + 3 px/m map rasters).

Data: ``<root>/label/<split>/scene-XXXX.txt`` and ``<root>/maps/{scene-XXXX.png, meta_scene-XXXX.txt}``, as
described in shared/data/README.md. nuScenes data is licensed CC BY-NC-SA 4.0 (non-commercial).
"""

from trafficrlhf_sdk import hookimpl
from trafficrlhf_sdk.lazy import lazy_exports
from trafficrlhf_sdk.registry import Lazy

_EXPORTS = {
    "NuScenesPredSource": "source",
    "parse_label_file": "source",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


@hookimpl
def register_scenario_sources(register):  # type: ignore[no-untyped-def]
    """Register ``nuscenes_pred``."""
    register("nuscenes_pred", Lazy("trafficrlhf_nuscenes_pred.source:NuScenesPredSource"))
