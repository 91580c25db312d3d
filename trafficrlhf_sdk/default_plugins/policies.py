"""Built-in closed-loop policies, registered as traffic models so `--model` can name them."""

from __future__ import annotations

from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.registry import Register
from trafficrlhf_sdk.simulation.policies import ConstantVelocityPolicy, LogReplayPolicy, NoisyLogPolicy


@hookimpl
def register_traffic_models(register: Register) -> None:
    """log_replay, constant_velocity, noisy_log."""
    register("log_replay", LogReplayPolicy)
    register("constant_velocity", ConstantVelocityPolicy)
    register("noisy_log", NoisyLogPolicy)
