"""TrafficRLHF SDK: align traffic-simulation models with human preferences.

The loop, stage by stage (each a subpackage):

1. ``feedback``: campaigns of N candidate futures per context, labelled in the browser or by stand-in annotators,
   exported as preference pairs;
2. ``reward``: reward models r_HF trained with the Bradley-Terry loss, saved as safetensors with a model card;
3. ``alignment``: :func:`align`, PPO fine-tuning of any registered traffic model on r + alpha * r_HF;
4. ``evaluation``: the closed-loop protocol (10 s, replanning at 2 Hz) and its metrics;

and :func:`rlhf` (``loop``), which runs stages 1-3 round after round on the policy it produces.

Underneath: ``scenario`` (:class:`ScenarioTensor`, sources), ``simulation`` (dynamics, guidance, simulator),
``metrics``, ``models`` (the adapter contract) and the plugin registries. Names are imported on first use, so
``import trafficrlhf_sdk`` stays fast.
"""

from __future__ import annotations

from typing import Any

from trafficrlhf_sdk._lazy import lazy_exports
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.plugins import list_plugins, registry

__version__ = "0.1.0"

_EXPORTS = {
    "AgentType": "scenario",
    "MapRaster": "scenario",
    "ScenarioSource": "scenario",
    "ScenarioTensor": "scenario",
    "SourceConfig": "scenario",
    "align": "alignment",
    "rlhf": "loop",
    "RLHFConfig": "loop",
    "AlignConfig": "alignment",
    "TrafficModelAdapter": "models",
    "RewardModel": "reward",
    "evaluate_policy": "evaluation",
}

__all__ = [
    "AgentType",
    "AlignConfig",
    "MapRaster",
    "RLHFConfig",
    "RewardModel",
    "ScenarioSource",
    "ScenarioTensor",
    "SourceConfig",
    "TrafficModelAdapter",
    "TrafficRLHFError",
    "__version__",
    "align",
    "evaluate_policy",
    "from_pretrained",
    "get_metric",
    "get_scenario_source",
    "get_traffic_model",
    "hookimpl",
    "list_plugins",
    "rlhf",
]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


def get_scenario_source(name: str, **options: Any) -> Any:
    """Instantiate the registered scenario source ``name`` with its config ``options`` (e.g. ``root=...``)."""
    source_cls = registry("scenario_sources").get(name)
    return source_cls(**options)


def get_traffic_model(name: str, **options: Any) -> Any:
    """Instantiate the registered traffic model (or built-in policy) ``name``."""
    factory = registry("traffic_models").get(name)
    return factory(**options)


def from_pretrained(checkpoint: str, **options: Any) -> Any:
    """The traffic model saved in ``checkpoint``: a folder, or a bundled checkpoint's name such as
    ``"ctg-aligned"`` (``trafficrlhf plugins`` lists them); its ``config.json`` names the adapter. ``options``
    (e.g. ``guidance="no_collision"``, ``seed=0``) go to the adapter."""
    from trafficrlhf_sdk.plugins import build_policy

    return build_policy(None, {**options, "checkpoint": checkpoint})


def get_metric(name: str) -> Any:
    """The registered metric ``name``."""
    return registry("metrics").get(name)
