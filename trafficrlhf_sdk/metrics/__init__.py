"""Closed-loop metrics: failure rate, realism deviation (CTG and body-frame presets), the realism meta-metric of K
rollouts (WOSAC style), speed against the log, reward cost."""

from trafficrlhf_sdk.metrics.base import Metric, MetricResult
from trafficrlhf_sdk.metrics.failure import FailureMetric, collisions_per_step, offroad_corner_share, offroad_per_step
from trafficrlhf_sdk.metrics.guidance_objectives import GuidanceObjectivesMetric
from trafficrlhf_sdk.metrics.geometry import (
    box_corners,
    boxes_overlap,
    colliding_pairs,
    following_gaps,
    pairwise_collisions,
    path_gaps,
)
from trafficrlhf_sdk.metrics.realism import (
    HistogramSpec,
    RealismMetric,
    histogram_distance,
    kinematics,
    scene_histogram,
)
from trafficrlhf_sdk.metrics.realism_meta import META_FEATURES, MetaFeature, RealismMetaConfig, RealismMetaMetric
from trafficrlhf_sdk.metrics.reward_cost import RewardCostMetric, RewardFn
from trafficrlhf_sdk.metrics.speed import SpeedMetric

__all__ = [
    "META_FEATURES",
    "FailureMetric",
    "GuidanceObjectivesMetric",
    "HistogramSpec",
    "MetaFeature",
    "Metric",
    "MetricResult",
    "RealismMetaConfig",
    "RealismMetaMetric",
    "RealismMetric",
    "RewardCostMetric",
    "RewardFn",
    "SpeedMetric",
    "box_corners",
    "boxes_overlap",
    "colliding_pairs",
    "collisions_per_step",
    "following_gaps",
    "histogram_distance",
    "kinematics",
    "offroad_corner_share",
    "offroad_per_step",
    "pairwise_collisions",
    "path_gaps",
    "scene_histogram",
]
