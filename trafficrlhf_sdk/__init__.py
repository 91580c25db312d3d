"""TrafficRLHF SDK: align traffic-simulation models with human preferences.

Public API (see docs/): scenario data (:class:`ScenarioTensor`, sources), dynamics, the closed-loop
simulator and its metrics, the plugin registries, and :func:`align` (stage III: PPO fine-tuning of a traffic
model against a reward model; the classes live in :mod:`trafficrlhf_sdk.align`).
"""

from __future__ import annotations

from typing import Any

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.plugins import list_plugins, registry
from trafficrlhf_sdk.scenario import AgentType, MapRaster, ScenarioSource, ScenarioTensor, SourceConfig

__version__ = "0.1.0"

__all__ = [
    "AgentType",
    "MapRaster",
    "ScenarioSource",
    "ScenarioTensor",
    "SourceConfig",
    "TrafficRLHFError",
    "__version__",
    "align",
    "get_metric",
    "get_scenario_source",
    "get_traffic_model",
    "hookimpl",
    "list_plugins",
]


def get_scenario_source(name: str, **options: Any) -> ScenarioSource:
    """Instantiate the registered scenario source ``name`` with its config ``options`` (e.g. ``root=...``)."""
    source_cls = registry("scenario_sources").get(name)
    return source_cls(**options)


def get_traffic_model(name: str, **options: Any) -> Any:
    """Instantiate the registered traffic model (or built-in policy) ``name``."""
    factory = registry("traffic_models").get(name)
    return factory(**options)


def get_metric(name: str) -> Any:
    """The registered metric ``name``."""
    return registry("metrics").get(name)


# Last, so that the name `trafficrlhf_sdk.align` is the function (the subpackage stays importable by its full
# path: `from trafficrlhf_sdk.align import AlignConfig`).
from trafficrlhf_sdk.align import align  # noqa: E402
