"""Agent type codes shared by every scenario source."""

from __future__ import annotations

from enum import IntEnum

__all__ = ["AgentType"]


class AgentType(IntEnum):
    """Agent categories stored in ``ScenarioTensor.agent_type``.

    ``UNSET`` marks padding slots; ``OTHER`` covers static objects (cones, barriers) and unknown classes.
    """

    UNSET = 0
    VEHICLE = 1
    PEDESTRIAN = 2
    CYCLIST = 3
    OTHER = 4

    @classmethod
    def from_name(cls, name: str) -> AgentType:
        """Map a dataset class name (nuScenes, ScenarioNet, ...) to an :class:`AgentType`."""
        key = name.strip().upper()
        if key in _VEHICLE_NAMES:
            return cls.VEHICLE
        if key in ("PEDESTRIAN", "PED", "HUMAN"):
            return cls.PEDESTRIAN
        if key in ("CYCLIST", "BICYCLE", "MOTORCYCLE", "BIKE"):
            return cls.CYCLIST
        return cls.OTHER


_VEHICLE_NAMES = frozenset({"VEHICLE", "CAR", "TRUCK", "BUS", "EMERGENCY", "CONSTRUCTION", "TRAILER", "EGO"})
