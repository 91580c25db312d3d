"""The metric interface: anything that turns a :class:`Rollout` into named numbers."""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import ClassVar

import torch

from trafficrlhf_sdk.simulation.simulator import Rollout

__all__ = ["Metric", "MetricResult"]


@dataclass(frozen=True)
class MetricResult:
    """Scalars (means over scenes) plus optional per-scene tensors ``(B,)`` and plot-ready extras."""

    values: dict[str, float]
    per_scene: dict[str, torch.Tensor] = field(default_factory=dict)
    extras: dict[str, object] = field(default_factory=dict)


class Metric(abc.ABC):
    """A closed-loop metric, registered with the ``register_metrics`` hook under :attr:`name`."""

    name: ClassVar[str] = ""
    lower_is_better: ClassVar[bool] = True

    @abc.abstractmethod
    def compute(self, rollout: Rollout) -> MetricResult:
        """Evaluate ``rollout``; scalars are means over scenes that have at least one controlled agent."""
