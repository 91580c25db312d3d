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

from trafficrlhf_sdk.lazy import lazy_exports
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.plugins import (
    build_policy,
    get_metric,
    get_scenario_source,
    get_traffic_model,
    list_plugins,
)
from trafficrlhf_sdk.plugins import registry as registry  # the registries, for plugins and their tests
from trafficrlhf_sdk.version import __version__

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


def from_pretrained(checkpoint: str, **options: Any) -> Any:
    """The traffic model saved in ``checkpoint``: a folder, or a bundled checkpoint's name such as
    ``"ctg-aligned"`` (``trafficrlhf plugins`` lists them); its ``config.json`` names the adapter. ``options``
    (e.g. ``guidance="no_collision"``, ``seed=0``) go to the adapter."""
    return build_policy(None, {**options, "checkpoint": checkpoint})
