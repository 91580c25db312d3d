"""``scripts/realism_by_failure.py``: realism deviation over agent groups split by failure."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, run_batched
from trafficrlhf_sdk.metrics.realism import RealismMetric
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import ConstantVelocityPolicy


def test_groups_partition_the_agents_and_the_whole_group_is_the_reported_metric(
        val_scenes: ScenarioTensor, load_script) -> None:  # type: ignore[no-untyped-def]
    script = load_script("realism_by_failure")
    config = EvaluationConfig(batch_size=50, seed=0)
    rollout = run_batched(ConstantVelocityPolicy(), val_scenes, config)[0]
    failing = script.failing_agents(rollout)
    assert failing.any(), "constant velocity should leave the road somewhere in these scenes"
    assert not (failing & ~rollout.controlled).any()
    other = rollout  # a second run (here the same): the groups are unions over runs
    groups = script.agent_groups([rollout, other])
    everyone = groups["all"]
    assert torch.equal(groups["scenes where no run fails"] | groups["other scenes"], everyone)
    assert not (groups["scenes where no run fails"] & groups["other scenes"]).any()
    assert torch.equal(groups["agents failing in some run"], failing)
    assert torch.equal(groups["agents failing in no run"] | failing, everyone)
    assert not groups["scenes where no run fails"][failing.any(-1)].any()
    reported = RealismMetric("ctg").compute(rollout).values
    mine = script.realism_over(rollout, everyone, "ctg")
    assert mine["mean"] == pytest.approx(reported["realism_ctg"])
    assert mine["lon_acc"] == pytest.approx(reported["realism_ctg_lon_acc"])
