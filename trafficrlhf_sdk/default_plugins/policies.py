"""Built-in closed-loop policies, registered as traffic models so `--model` can name them."""

from __future__ import annotations

from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.registry import Lazy, Register


@hookimpl
def register_traffic_models(register: Register) -> None:
    """log_replay, constant_velocity, noisy_log."""
    register("log_replay", Lazy("trafficrlhf_sdk.simulation.policies:LogReplayPolicy"))
    register("constant_velocity", Lazy("trafficrlhf_sdk.simulation.policies:ConstantVelocityPolicy"))
    register("noisy_log", Lazy("trafficrlhf_sdk.simulation.policies:NoisyLogPolicy"))
