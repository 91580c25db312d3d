"""``scripts/failure_timing.py``: the failure rate split by each agent's first failure."""

from __future__ import annotations

import dataclasses
import math

import pytest

from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, run_batched
from trafficrlhf_sdk.metrics.failure import FailureMetric
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import ConstantVelocityPolicy, LogReplayPolicy


def test_the_parts_add_up_to_the_reported_failure_rate(val_scenes: ScenarioTensor, load_script) -> None:  # type: ignore[no-untyped-def]
    script = load_script("failure_timing")
    rollout = run_batched(ConstantVelocityPolicy(), val_scenes, EvaluationConfig(batch_size=50, seed=0))[0]
    parts = script.failure_parts(rollout)
    reported = FailureMetric().compute(rollout).values["failure_rate"]
    assert parts["failure_rate"] == pytest.approx(reported)
    assert reported > 0, "constant velocity should leave the road somewhere in these scenes"
    assert math.fsum(v for k, v in parts.items() if k != "failure_rate") == pytest.approx(reported)
    assert all(v >= 0 for v in parts.values())


def test_a_logged_overlap_at_the_start_is_its_own_part(val_scenes: ScenarioTensor, load_script) -> None:  # type: ignore[no-untyped-def]
    """Two controlled agents stacked on each other in the log collide at the first step when the log is
    replayed; that collision is counted in the unavoidable part, not in "collision within 1 s"."""
    script = load_script("failure_timing")
    config = EvaluationConfig(batch_size=50, seed=0)
    clean = script.failure_parts(run_batched(LogReplayPolicy(), val_scenes, config)[0])
    scene = int(val_scenes.controlled.sum(-1).argmax())
    first, second = val_scenes.controlled[scene].nonzero()[:2, 0].tolist()
    states, valid = val_scenes.states.clone(), val_scenes.valid.clone()
    states[scene, second], valid[scene, second] = states[scene, first], valid[scene, first]
    stacked = dataclasses.replace(val_scenes, states=states, valid=valid)
    parts = script.failure_parts(run_batched(LogReplayPolicy(), stacked, config)[0])
    scenes_with_agents = int(val_scenes.controlled.any(-1).sum())
    share = 2 / int(val_scenes.controlled[scene].sum()) / scenes_with_agents  # both agents of that scene
    unavoidable = "collision, boxes overlap in the log at the start"
    assert parts[unavoidable] >= clean[unavoidable] + share - 1e-9
    assert parts["collision within 1 s"] == pytest.approx(clean["collision within 1 s"])
