"""Hand-written rewards, registered like any plugin's and used as ``builtin:NAME``: baselines and ablations for
the learned reward models (the product's aligned models come from learned ones)."""

from __future__ import annotations

from typing import Any

from trafficrlhf_sdk.hookspecs import hookimpl
from trafficrlhf_sdk.registry import Register


def _factory(class_name: str, **defaults: Any) -> Any:
    """A factory of ``trafficrlhf_sdk.reward.builtin.<class_name>`` with ``defaults`` (torch loads on first use)."""

    def build(**options: Any) -> Any:
        from trafficrlhf_sdk.reward import builtin

        return getattr(builtin, class_name)(**{**defaults, **options})

    build.__name__ = build.__qualname__ = class_name
    build.__doc__ = f"``{class_name}({', '.join(f'{k}={v!r}' for k, v in defaults.items())})``"
    return build


@hookimpl
def register_rewards(register: Register) -> None:
    """failure, collision, failure-margins, realism, realism-margins, realism-speed, realism-kinematics, random,
    judgment."""
    register("failure", _factory("FailureReward"))
    register("collision", _factory("FailureReward", offroad=False))
    register("failure-margins", _factory("FailureReward", margins=True))
    register("realism", _factory("RealismReward"))
    register("realism-margins", _factory("RealismReward", margins=True))
    register("realism-speed", _factory("RealismReward", margins=True, speed_weight=1.0))
    register("realism-kinematics", _factory("RealismReward", margins=True, kinematics_weight=0.5))
    register("random", _factory("RandomReward"))
    register("judgment", _judgment)


def _judgment(**options: Any) -> Any:
    """``JudgmentReward(profile='attentive')``: the stand-in annotator's judgment used directly as the reward."""
    from trafficrlhf_sdk.reward.oracle import JudgmentReward

    return JudgmentReward(**options)
