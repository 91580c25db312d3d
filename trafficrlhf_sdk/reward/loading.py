"""One entry point for every reward the fine-tuner and the evaluation accept: a saved reward model, or a
registered hand-written reward (``builtin:NAME``)."""

from __future__ import annotations

from typing import Any

from trafficrlhf_sdk.errors import TrafficRLHFError

__all__ = ["BUILTIN_PREFIX", "load_reward"]

BUILTIN_PREFIX = "builtin:"


def load_reward(spec: str, options: dict[str, Any] | None = None) -> Any:
    """The reward named by ``spec``: a folder written by ``trafficrlhf rm train`` (loaded in eval mode), or
    ``builtin:NAME`` for a hand-written reward registered through the ``register_rewards`` hook (``trafficrlhf
    plugins`` lists them). ``options`` are keyword arguments of a built-in reward's factory."""
    options = dict(options or {})
    if spec.startswith(BUILTIN_PREFIX):
        from trafficrlhf_sdk.plugins import registry

        rewards = registry("rewards")
        name = spec[len(BUILTIN_PREFIX):]
        if name not in rewards.names():
            raise TrafficRLHFError(f"unknown built-in reward {spec!r}; use one of "
                                   f"{', '.join(BUILTIN_PREFIX + n for n in rewards.names())}.")
        try:
            reward = rewards.get(name)(**options)
        except TypeError as error:
            raise TrafficRLHFError(f"reward options {sorted(options)} do not fit {spec!r} ({error}); use keyword "
                                   "arguments of its class in trafficrlhf_sdk.reward.builtin.") from None
        reward.name_or_path = spec  # recorded by the fine-tuner's history
        return reward
    if options:
        raise TrafficRLHFError(f"reward options {sorted(options)} apply to built-in rewards only; {spec!r} is a "
                               "saved reward model.")
    from trafficrlhf_sdk.reward.model import RewardModel

    model = RewardModel.from_pretrained(spec).eval()
    model.name_or_path = spec
    return model
