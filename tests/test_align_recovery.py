"""Recovery targets (trafficrlhf_sdk.alignment.recovery): the imitation loss's future from a simulated state."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import LineString, Point

from trafficrlhf_sdk.alignment import AlignConfig
from trafficrlhf_sdk.alignment.contexts import ContextSampler
from trafficrlhf_sdk.alignment.recovery import EXTENSION_M, _project, recovery_targets
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import ConstantVelocityPolicy

NOW, H, DT = 10, 30, 0.1


def _scene(states: torch.Tensor, controlled: list[bool] | None = None) -> ScenarioTensor:
    """One scene from ``states (A, T, 4)``, every agent valid, "now" at NOW."""
    a, t = states.shape[:2]
    return ScenarioTensor(states=states[None].float(), valid=torch.ones(1, a, t, dtype=torch.bool),
                          extent=torch.tensor([[[4.5, 1.9]] * a]), agent_type=torch.ones(1, a, dtype=torch.long),
                          controlled=torch.tensor([controlled or [True] * a]), dt=DT, current_index=NOW)


def _straight(speed: float, y: float = 0.0, x0: float = 0.0, yaw: float = 0.0) -> torch.Tensor:
    """``(T, 4)``: constant speed along x at lateral position y, heading yaw, at x0 when "now"."""
    time = (torch.arange(NOW + H + 1) - NOW) * DT
    return torch.stack([x0 + speed * time, torch.full_like(time, y), torch.full_like(time, speed),
                        torch.full_like(time, yaw)], -1)


def _arc(speed: float, radius: float, phase: float = 0.0) -> torch.Tensor:
    """``(T, 4)``: a left turn at constant speed on a circle of ``radius`` round the origin."""
    angle = phase + (torch.arange(NOW + H + 1) - NOW) * DT * speed / radius
    return torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), torch.full_like(angle, speed),
                        angle + math.pi / 2], -1)


def _recover(sim: torch.Tensor, log: torch.Tensor) -> torch.Tensor:
    """The recovery target's states ``(T, 4)`` of one agent simulated as ``sim`` and logged as ``log``."""
    return recovery_targets(_scene(sim[None]), _scene(log[None])).states[0, 0]


def test_an_agent_on_its_logged_path_at_the_logs_speed_gets_the_log_back() -> None:
    for log in (_straight(10.0), _arc(8.0, 25.0)):
        target = _recover(log, log)
        assert torch.allclose(target[:, :2], log[:, :2], atol=0.05)
        assert torch.allclose(target[:, 2], log[:, 2], atol=1e-4)
        assert torch.allclose(target[:, 3], log[:, 3], atol=0.01)


def test_a_lateral_offset_closes_over_the_horizon_with_continuous_heading_and_speed() -> None:
    log = _straight(10.0)
    sim = _straight(10.0, y=2.0)
    target = _recover(sim, log)
    future = target[NOW:]
    assert torch.equal(target[: NOW + 1], sim[: NOW + 1])  # the simulated history is kept
    assert (future[1:, 1] <= future[:-1, 1] + 1e-5).all()  # lateral offset shrinks monotonically
    assert abs(float(future[-1, 1])) < 1e-3 and abs(float(future[-1, 3])) < 1e-3  # on the path, parallel to it
    assert torch.allclose(future[:, 0], log[NOW:, 0], atol=1e-3)  # the log's progress
    assert abs(float(future[1, 3])) < 0.02  # it starts parallel, as the agent drives
    assert (future[:, 3] <= 1e-6).all()  # it steers towards the path, never away
    actions = recovery_targets(_scene(sim[None]), _scene(log[None])).actions()[0, 0, NOW:]
    assert actions[:, 1].abs().max() < 1.0  # a lane change, not a jump


def test_an_agent_heading_away_from_the_path_first_continues_then_returns() -> None:
    log = _straight(10.0)
    sim = _straight(10.0, y=1.0, yaw=0.3)
    target = _recover(sim, log)[NOW:]
    assert float(target[1, 3]) == pytest.approx(0.3, abs=0.05)  # heading continues the agent's
    assert float(target[3, 1]) > 1.0  # still moving away just after "now"
    assert abs(float(target[-1, 1])) < 1e-3


def test_speed_blends_from_the_agents_own_to_the_logs() -> None:
    log = _straight(8.0)
    sim = _straight(12.0, x0=5.0)  # ahead of the log and faster
    target = _recover(sim, log)[NOW:]
    assert float(target[1, 2]) == pytest.approx(12 - 4 / H, abs=1e-4)
    assert float(target[-1, 2]) == pytest.approx(8.0, abs=1e-4)
    assert (target[1:, 2] <= target[:-1, 2] + 1e-5).all()
    travelled = float((target[1:, 2] * DT).sum())
    assert float(target[-1, 0]) == pytest.approx(5.0 + travelled, abs=1e-3)  # along the path from where it is
    assert target[:, 1].abs().max() < 1e-4


def test_an_agent_that_stands_keeps_its_offset() -> None:
    log = _straight(0.0)
    sim = _straight(0.0, y=1.5)
    target = _recover(sim, log)[NOW:]
    assert torch.allclose(target[:, 1], torch.full_like(target[:, 1], 1.5))
    assert torch.allclose(target[:, 0], torch.zeros_like(target[:, 0]))
    assert torch.allclose(target[:, 3], torch.zeros_like(target[:, 3]))


def test_agents_not_controlled_or_without_a_whole_logged_future_keep_the_log() -> None:
    log = torch.stack([_straight(10.0), _straight(10.0, y=4.0), _straight(10.0, y=8.0)])
    sim = torch.stack([_straight(11.0, y=1.0), _straight(11.0, y=5.0), _straight(11.0, y=9.0)])
    context = _scene(sim, controlled=[True, False, True])
    logged = _scene(log)
    valid = logged.valid.clone()
    valid[0, 2, NOW + 5] = False
    logged = logged.replace_unchecked(valid=valid, states=logged.states * valid[..., None])
    target = recovery_targets(context, logged)
    assert torch.equal(target.states[0, 1], logged.states[0, 1])  # not controlled
    assert torch.equal(target.states[0, 2], logged.states[0, 2])  # its log has a gap in the future
    assert torch.equal(target.valid, logged.valid)
    assert not torch.equal(target.states[0, 0, NOW + 1:], logged.states[0, 0, NOW + 1:])


def test_the_projection_matches_shapely_on_a_curved_path() -> None:
    log = _arc(8.0, 20.0)
    path = torch.cat([log[:1, :2] - EXTENSION_M * torch.tensor([[math.cos(log[0, 3]), math.sin(log[0, 3])]]),
                      log[:, :2]])[None]
    arc = torch.cat([torch.zeros(1, 1), torch.linalg.vector_norm(path[:, 1:] - path[:, :-1], dim=-1).cumsum(-1)], 1)
    line = LineString(path[0].tolist())
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(50, 2, generator=generator) * 50 - 25
    sigma, _ = _project(points, path.expand(50, -1, -1), arc.expand(50, -1))
    expected = torch.tensor([line.project(Point(p)) for p in points.tolist()])
    assert torch.allclose(sigma, expected.float(), atol=1e-3)


@settings(max_examples=40, deadline=None)
@given(offset=st.floats(-4.0, 4.0), heading=st.floats(-0.5, 0.5), pace=st.floats(0.5, 1.0),
       log_speed=st.floats(2.0, 15.0), radius=st.floats(15.0, 80.0))
def test_any_start_near_a_turn_ends_on_the_logged_path_parallel_to_it(offset: float, heading: float, pace: float,
                                                                        log_speed: float, radius: float) -> None:
    # no faster than the log, so that the target stays on the logged turn (beyond it the path runs straight on)
    speed = pace * log_speed
    log = _arc(log_speed, radius)
    start = log[NOW].clone()
    normal = torch.tensor([-math.sin(start[3]), math.cos(start[3])])
    start[:2] += offset * normal
    start[2], start[3] = speed, start[3] + heading
    sim = log.clone()
    sim[NOW] = start
    end = _recover(sim, log)[-1]
    distance_to_circle = abs(float(end[:2].norm()) - radius)
    assert distance_to_circle < 0.05
    tangent = math.atan2(float(end[1]), float(end[0])) + math.pi / 2
    assert abs(math.remainder(float(end[3]) - tangent, 2 * math.pi)) < 0.02


def test_failure_contexts_with_recovery_imitate_from_the_simulated_history(
        train_scene_list: list[ScenarioTensor]) -> None:
    draws = {}
    for recovery in (False, True):
        config = AlignConfig(failure_fraction=1.0, failure_scenes=8, contexts_per_epoch=6,
                             imitation_recovery=recovery)
        sampler = ContextSampler(ConstantVelocityPolicy(), config, lambda: train_scene_list, None, future_steps=20)
        draws[recovery] = sampler.failure_contexts(6, torch.Generator().manual_seed(0))
    (contexts, log_windows), (same_contexts, targets) = draws[False], draws[True]
    assert torch.equal(contexts.states, same_contexts.states)  # the option changes only the imitation windows
    now = contexts.current_index
    driven = contexts.controlled & contexts.valid[:, :, now] & log_windows.valid[:, :, now:].all(-1)
    assert driven.any()
    assert torch.equal(targets.states[:, :, : now + 1][driven], contexts.states[:, :, : now + 1][driven])
    assert torch.equal(targets.states[~driven], log_windows.states[~driven])
    assert torch.equal(targets.valid[~driven], log_windows.valid[~driven])
