"""Scenario source ``scenarionet``: ScenarioNet scenario pickles (one ``*.pkl`` per scenario).

Reads the scenario description that ScenarioNet/MetaDrive use for Waymo, nuPlan, nuScenes and Argoverse 2
exports; the default root is ``<data root>/nuscenes_mini_scenarionet`` (the ten nuScenes v1.0-mini scenes, see
shared/data/README.md). Pickles are only read through the restricted unpickler of
:mod:`trafficrlhf_scenarionet.unpickler`. nuScenes data is licensed CC BY-NC-SA 4.0 (non-commercial); other
datasets keep their own terms.
"""

from trafficrlhf_sdk import hookimpl
from trafficrlhf_sdk.lazy import lazy_exports
from trafficrlhf_sdk.registry import Lazy

_EXPORTS = {
    "RestrictedUnpickler": "unpickler",
    "ScenarioNetConfig": "source",
    "ScenarioNetSource": "source",
    "read_scenario": "source",
    "restricted_load": "unpickler",
    "restricted_loads": "unpickler",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


@hookimpl
def register_scenario_sources(register):  # type: ignore[no-untyped-def]
    """Register ``scenarionet``."""
    register("scenarionet", Lazy("trafficrlhf_scenarionet.source:ScenarioNetSource"))
