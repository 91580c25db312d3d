"""Scenario source ``nuscenes_pred``: nuScenes prediction scenes (2 Hz labels + 3 px/m map rasters).

Data: ``<root>/label/<split>/scene-XXXX.txt`` and ``<root>/maps/{scene-XXXX.png, meta_scene-XXXX.txt}``, as
described in shared/data/README.md. nuScenes data is licensed CC BY-NC-SA 4.0 (non-commercial).
"""

from trafficrlhf_sdk import hookimpl

from trafficrlhf_nuscenes_pred.source import NuScenesPredSource, parse_label_file

__all__ = ["NuScenesPredSource", "parse_label_file"]


@hookimpl
def register_scenario_sources(register):  # type: ignore[no-untyped-def]
    """Register ``nuscenes_pred``."""
    register("nuscenes_pred", NuScenesPredSource)
