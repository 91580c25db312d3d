"""The heading-mismatch term of ``RealismReward``: the logged turn asked for, against a hand count."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficrlhf_sdk.reward.builtin import RealismReward
from trafficrlhf_sdk.reward.loading import load_reward
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario import ScenarioTensor

NOW = 10  # current_index: 1 s of history at 0.1 s
STEPS = 41


def _turning(yaw_rates: list[float], speed: float = 8.0, offset: float = 0.0) -> ScenarioTensor:
    """One scene of agents on lanes 50 m apart, 4 s at 0.1 s, all at ``speed`` m/s; after now agent ``a`` turns
    at ``yaw_rates[a]`` rad/s. ``offset`` (rad) is added to every future heading (a constant steering error)."""
    rates = torch.tensor(yaw_rates, dtype=torch.float64)[:, None]
    time_s = torch.arange(STEPS, dtype=torch.float64) * 0.1
    after = (time_s - NOW * 0.1).clamp_min(0)
    yaw = rates * after + offset * (after > 0)
    # positions integrated from the headings, so the scene is self-consistent
    dx = speed * torch.cos(yaw) * 0.1
    dy = speed * torch.sin(yaw) * 0.1
    x = torch.cumsum(dx, -1) - dx[:, :1]
    y = torch.cumsum(dy, -1) - dy[:, :1] + 50.0 * torch.arange(len(yaw_rates), dtype=torch.float64)[:, None]
    speed_t = torch.full_like(x, speed)
    wrapped = torch.atan2(torch.sin(yaw), torch.cos(yaw))
    states = torch.stack([x, y, speed_t, wrapped], -1)[None].float()
    a = len(yaw_rates)
    return ScenarioTensor(states=states, valid=torch.ones(1, a, STEPS, dtype=torch.bool),
                          extent=torch.tensor([[[4.5, 1.9]] * a]), agent_type=torch.ones(1, a, dtype=torch.long),
                          controlled=torch.ones(1, a, dtype=torch.bool), current_index=NOW)


def _expected(sample_rate: float, log_rate: float, offset: float, tolerance: float, scale: float) -> float:
    """Hand count of the mean clipped heading mismatch over the 30 future steps."""
    total = 0.0
    for k in range(1, STEPS - NOW):
        t = k * 0.1
        error = (sample_rate - log_rate) * t + offset
        error = abs(math.atan2(math.sin(error), math.cos(error)))
        total += min(1.0, max(0.0, error - tolerance) / scale)
    return total / (STEPS - NOW - 1)


def test_following_the_logged_turn_costs_nothing_and_under_steering_costs_the_hand_count() -> None:
    log = _turning([0.3, 0.3, 0.0])
    sampled = _turning([0.3, 0.24, 0.0])  # the second agent under-steers by a fifth
    plain = RealismReward().agent_scores(sampled, logged=log)
    with_term = RealismReward(heading_weight=2.0).agent_scores(sampled, logged=log)
    extra = (plain - with_term)[0].double()
    assert extra[0].abs() < 1e-6 and extra[2].abs() < 1e-6
    assert extra[1].item() == pytest.approx(2.0 * _expected(0.24, 0.3, 0.0, 0.05, 0.5), abs=1e-5)
    assert extra[1] > 0


@settings(max_examples=25, deadline=None)
@given(rate=st.floats(-0.6, 0.6), offset=st.floats(-3.0, 3.0), tolerance=st.floats(0.0, 0.3),
       scale=st.floats(0.1, 1.0))
def test_the_term_matches_the_hand_count_and_stays_in_its_bounds(rate: float, offset: float, tolerance: float,
                                                                  scale: float) -> None:
    log = _turning([0.2])
    sampled = _turning([rate], offset=offset)
    reward = RealismReward(heading_weight=1.0, heading_tolerance=tolerance, heading_scale=scale)
    extra = (RealismReward().agent_scores(sampled, logged=log) - reward.agent_scores(sampled, logged=log))
    value = extra[0, 0].item()
    assert 0.0 <= value <= 1.0 + 1e-6
    assert value == pytest.approx(_expected(rate, 0.2, offset, tolerance, scale), abs=2e-4)


def test_slow_logged_agents_are_not_asked_to_turn() -> None:
    """Below ``stall_log_speed`` a logged heading is mostly noise: the term leaves such agents alone."""
    log = _turning([0.5], speed=1.0)
    sampled = _turning([-0.5], speed=1.0)
    plain = RealismReward().agent_scores(sampled, logged=log)
    with_term = RealismReward(heading_weight=1.0).agent_scores(sampled, logged=log)
    torch.testing.assert_close(with_term, plain)


def test_builtin_and_bad_values() -> None:
    reward = load_reward("builtin:realism-heading")
    assert isinstance(reward, RealismReward) and reward.margins and reward.heading_weight == 1.0
    assert load_reward("builtin:realism-heading", {"heading_scale": 0.25}).heading_scale == 0.25
    with pytest.raises(TrafficRLHFError, match="heading_scale"):
        RealismReward(heading_scale=0.0)
    with pytest.raises(TrafficRLHFError, match="heading_weight"):
        RealismReward(heading_weight=-1.0)
