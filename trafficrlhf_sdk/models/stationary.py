"""Which agents a planner holds still: upstream CTG and BITS disable the control of stationary agents
(tbsim ``disable_control_on_stationary='current_speed'``, |v| <= 0.5 m/s), deciding once, at the rollout start.

:class:`StationaryHold` keeps that decision for an adapter: :meth:`~StationaryHold.start` records the speeds at
the rollout start (call it from ``reset``), and inside :meth:`~StationaryHold.planning` (wrap ``plan`` with it)
:meth:`~StationaryHold.mask` answers from those speeds. Outside a rollout (a direct ``sample`` call, as PPO makes
on cut contexts) the context's current step is the start, so the current speed decides.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Literal

import torch

from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["StationaryHold", "StationaryRule"]

StationaryRule = Literal["rollout_start", "every_replan"]


class StationaryHold:
    """Holds agents at or below ``speed`` m/s still. ``rule``: ``"rollout_start"`` (upstream: decided once from
    the speeds at the rollout start, so an agent that later stops may drive off again) or ``"every_replan"``
    (decided from the current speed at every replan, so an agent that stops is held for the rest of the
    rollout)."""

    def __init__(self, speed: float, rule: StationaryRule = "rollout_start") -> None:
        if rule not in ("rollout_start", "every_replan"):
            raise ValueError(f"stationary_rule={rule!r}; use 'rollout_start' or 'every_replan'.")
        self.speed, self.rule = speed, rule
        self._start_speed: torch.Tensor | None = None  # (B, A) |speed| at the rollout start
        self._planning = False

    def start(self, scenario: ScenarioTensor) -> None:
        """Record the speeds ``(B, A)`` at ``scenario.current_index`` (the rollout start)."""
        self._start_speed = scenario.states[:, :, scenario.current_index, 2].abs().clone()

    @contextmanager
    def planning(self) -> Iterator[None]:
        """Inside this block :meth:`mask` uses the recorded rollout-start speeds (for ``"rollout_start"``)."""
        previous, self._planning = self._planning, True
        try:
            yield
        finally:
            self._planning = previous

    @property
    def in_plan(self) -> bool:
        """Whether a :meth:`planning` block is open (the caller executes the samples and keeps no trace)."""
        return self._planning

    def mask(self, context: ScenarioTensor) -> torch.Tensor:
        """bool ``(B, A)``: the agents of ``context`` to hold still now."""
        speed = context.states[:, :, context.current_index, 2].abs()
        if self.rule == "rollout_start" and self._planning and self._start_speed is not None:
            if tuple(self._start_speed.shape) != tuple(speed.shape):
                raise ValueError(
                    f"plan() got a context with (scenes, agents) {tuple(speed.shape)}, but reset() recorded "
                    f"{tuple(self._start_speed.shape)}; call reset() with the scenario the rollout runs on."
                )
            speed = self._start_speed.to(speed.device)
        return speed <= self.speed
