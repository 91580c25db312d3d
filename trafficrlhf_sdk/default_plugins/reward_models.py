"""Built-in reward-model architectures, registered like any plugin's."""

from __future__ import annotations

from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.registry import Lazy, Register


@hookimpl
def register_reward_model_architectures(register: Register) -> None:
    """ctg_mlp (the paper's), trafficgen_mcg (a TrafficGen-style encoder with the paper's head), ensemble (a
    bootstrap ensemble of any registered architecture)."""
    register("ctg_mlp", Lazy("trafficrlhf_sdk.reward.ctg_mlp:CTGMLPRewardModel"))
    register("trafficgen_mcg", Lazy("trafficrlhf_sdk.reward.trafficgen_mcg:TrafficGenMCGRewardModel"))
    register("ensemble", Lazy("trafficrlhf_sdk.reward.model:RewardEnsemble"))
