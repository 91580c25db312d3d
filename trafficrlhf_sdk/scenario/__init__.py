"""Scenario data structures, IO and the source interface."""

from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.map import DEFAULT_LAYERS, MapRaster, PolylineType
from trafficrlhf_sdk.scenario.source import ScenarioSource, SourceConfig, default_data_root
from trafficrlhf_sdk.scenario.statistics import inspect_source, scene_statistics
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.scenario.transforms import MIRROR_SUFFIX, mirror_scenario, perturb_history

__all__ = [
    "DEFAULT_LAYERS",
    "MIRROR_SUFFIX",
    "AgentType",
    "MapRaster",
    "PolylineType",
    "ScenarioSource",
    "ScenarioTensor",
    "SourceConfig",
    "default_data_root",
    "inspect_source",
    "mirror_scenario",
    "perturb_history",
    "scene_statistics",
]
