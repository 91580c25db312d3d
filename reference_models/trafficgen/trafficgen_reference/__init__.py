"""A compact TrafficGen (initializer + multi-modal motion forecaster) in plain PyTorch, with its training script."""

from trafficgen_reference.model import Forecaster, Initializer, TrafficGenConfig, TrafficGenModel

__all__ = ["Forecaster", "Initializer", "TrafficGenConfig", "TrafficGenModel"]
