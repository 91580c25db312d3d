"""Closed-loop simulation: replan at 2 Hz, execute the first steps of each plan, replay the rest from the log."""

from trafficrlhf_sdk.simulation.policies import (
    ClosedLoopPolicy,
    ConstantVelocityPolicy,
    LogReplayPolicy,
    NoisyLogPolicy,
    Plan,
)
from trafficrlhf_sdk.simulation.simulator import Rollout, SimulationConfig, log_rollout, simulate

__all__ = [
    "ClosedLoopPolicy",
    "ConstantVelocityPolicy",
    "LogReplayPolicy",
    "NoisyLogPolicy",
    "Plan",
    "Rollout",
    "SimulationConfig",
    "log_rollout",
    "simulate",
]
