"""Closed-loop simulation: unicycle dynamics, guidance, and the simulator that replans at 2 Hz, executes the first
steps of each plan and replays the other agents from the log.

Names are imported on first use, so ``trafficrlhf_sdk.simulation.dynamics`` can be read by the scenario package
without loading the simulator.
"""

from trafficrlhf_sdk.lazy import lazy_exports

_EXPORTS = {
    "ClosedLoopPolicy": "policies",
    "ConstantVelocityPolicy": "policies",
    "LogReplayPolicy": "policies",
    "NoisyLogPolicy": "policies",
    "Plan": "policies",
    "policy_seed": "policies",
    "seed_policy": "policies",
    "Rollout": "simulator",
    "SimulationConfig": "simulator",
    "log_rollout": "simulator",
    "simulate": "simulator",
    "GuidanceSet": "guidance",
    "unicycle_step": "dynamics",
    "unicycle_rollout": "dynamics",
    "wrap_angle": "dynamics",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
