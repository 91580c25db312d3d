"""Traffic-model adapter contract and shared agent-centric features."""

from trafficrlhf_sdk.models.adapter import (
    AdapterOptions,
    PolicyTrace,
    SampleOutput,
    TrafficModelAdapter,
    extend_constant_velocity,
)

__all__ = ["AdapterOptions", "PolicyTrace", "SampleOutput", "TrafficModelAdapter", "extend_constant_velocity"]
