"""``StationaryHold``: which agents CTG/BITS-style planners hold still, decided at the rollout start or every replan."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.models.stationary import StationaryHold
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor


def scene_with_speeds(speeds: list[float], now: int = 5) -> ScenarioTensor:
    """One scene, one agent per entry of ``speeds`` (signed, m/s, constant over 10 steps)."""
    a, t = len(speeds), 10
    states = torch.zeros(1, a, t, 4)
    states[..., 2] = torch.tensor(speeds)[None, :, None]
    return ScenarioTensor(states=states, valid=torch.ones(1, a, t, dtype=torch.bool), extent=torch.ones(1, a, 2),
                          agent_type=torch.full((1, a), int(AgentType.VEHICLE)),
                          controlled=torch.ones(1, a, dtype=torch.bool), current_index=now)


def test_outside_a_rollout_the_current_speed_decides() -> None:
    hold = StationaryHold(0.5)
    assert hold.mask(scene_with_speeds([0.0, -0.4, 0.5, 0.6, -3.0])).tolist() == [[True, True, True, False, False]]


def test_rollout_start_keeps_the_decision_made_at_reset() -> None:
    hold = StationaryHold(0.5, "rollout_start")
    hold.start(scene_with_speeds([0.0, 8.0]))
    later = scene_with_speeds([6.0, 0.1])  # the stopped one drives off, the moving one stops
    with hold.planning():
        assert hold.mask(later).tolist() == [[True, False]]
    assert hold.mask(later).tolist() == [[False, True]]  # a direct sample: its context is the start


def test_every_replan_reads_the_current_speed_even_while_planning() -> None:
    hold = StationaryHold(0.5, "every_replan")
    hold.start(scene_with_speeds([0.0, 8.0]))
    with hold.planning():
        assert hold.mask(scene_with_speeds([6.0, 0.1])).tolist() == [[False, True]]


def test_bad_rule_and_a_context_of_another_rollout_are_named() -> None:
    with pytest.raises(ValueError, match="stationary_rule='sometimes'"):
        StationaryHold(0.5, "sometimes")  # type: ignore[arg-type]
    hold = StationaryHold(0.5)
    hold.start(scene_with_speeds([0.0, 8.0]))
    with hold.planning(), pytest.raises(ValueError, match=r"reset\(\) recorded \(1, 2\)"):
        hold.mask(scene_with_speeds([0.0, 8.0, 3.0]))
