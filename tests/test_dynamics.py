"""Unicycle dynamics: the step formula, the CTG/tbsim bounds, rollouts, gradients and batching."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficrlhf_sdk.simulation.dynamics import (
    DEFAULT_BOUNDS,
    UnicycleBounds,
    action_bounds,
    unicycle_rollout,
    unicycle_step,
    wrap_angle,
)
from trafficrlhf_sdk.testing.strategies import feasible_trajectories

FAST = settings(max_examples=40, deadline=None)


def test_step_matches_hand_computation():
    dt, x, y, v, yaw, a, w = 0.1, 1.0, 2.0, 3.0, 0.5, 1.0, 0.2
    travel = dt * (v + a * dt / 2)  # 0.1 * 3.05 = 0.305; cos(0.5) = 0.8775826, sin(0.5) = 0.4794255
    expected = [x + travel * math.cos(yaw), y + travel * math.sin(yaw), v + dt * a, yaw + dt * w]
    f64 = torch.float64
    out = unicycle_step(torch.tensor([x, y, v, yaw], dtype=f64), torch.tensor([a, w], dtype=f64), dt)
    assert out.tolist() == pytest.approx(expected, abs=1e-12)
    assert out.tolist() == pytest.approx([1.2676627, 2.1462248, 3.1, 0.52], abs=1e-6)
    unbounded = unicycle_step(torch.tensor([x, y, v, yaw]), torch.tensor([a, w]), dt, bounds=None)
    assert unbounded.tolist() == pytest.approx(expected, abs=1e-6)


def test_step_wraps_yaw():
    out = unicycle_step(torch.tensor([0.0, 0.0, 5.0, 3.1]), torch.tensor([0.0, 1.0]), 0.1)
    assert out[3].item() == pytest.approx(3.2 - 2 * math.pi, abs=1e-6)


def test_acceleration_clipped_to_minus10_plus8():
    state = torch.tensor([[0.0, 0.0, 5.0, 0.0]] * 2)
    out = unicycle_step(state, torch.tensor([[100.0, 0.0], [-100.0, 0.0]]), 0.1)
    assert out[:, 2].tolist() == pytest.approx([5.8, 4.0], abs=1e-6)
    lb, ub = action_bounds(torch.tensor(5.0))
    assert (lb[0].item(), ub[0].item()) == (-10.0, 8.0)


def test_speed_bounds():
    lb, ub = action_bounds(torch.tensor([29.5, -9.5, 35.0, -15.0]))
    assert ub[:, 0].tolist() == pytest.approx([0.5, 8.0, -5.0, 8.0])  # acc_ub = min(max(v_max - v, -10), 8)
    assert lb[:, 0].tolist() == pytest.approx([-10.0, -0.5, -10.0, 5.0])  # acc_lb = max(min(v_min - v, 8), -10)
    state = torch.tensor([[0.0, 0.0, 25.0, 0.0], [0.0, 0.0, -5.0, 0.0]])
    flat_out = torch.tensor([[100.0, 0.0], [-100.0, 0.0]])
    rolled = unicycle_rollout(state, flat_out[:, None].expand(2, 200, 2), 0.1)
    assert rolled[0, :, 2].max() <= 30.0 + 1e-4 and rolled[0, -1, 2] > 29.9
    assert rolled[1, :, 2].min() >= -10.0 - 1e-4 and rolled[1, -1, 2] < -9.9


@pytest.mark.parametrize(
    ("speed", "bound"),
    [
        (0.0, 0.1),  # vclip = 0.1: min(0.05, 62.8) = 0.05, floored at 0.1
        (0.1, 0.1),
        (0.5, 0.25),  # 0.5 * 0.5
        (1.0, 0.5),
        (-1.0, 0.5),  # |v|
        (3.0, 1.5),
        (4.0, 2 * math.pi / 4.0),  # min(2.0, 1.571)
        (10.0, 2 * math.pi / 10.0),
        (-20.0, 2 * math.pi / 20.0),
        (100.0, 0.1),  # 0.0628 floored at 0.1
    ],
)
def test_yaw_rate_bound(speed, bound):
    lb, ub = action_bounds(torch.tensor(speed, dtype=torch.float64))
    assert ub[1].item() == pytest.approx(bound) and lb[1].item() == pytest.approx(-bound)
    state = torch.tensor([0.0, 0.0, speed, 0.0], dtype=torch.float64)
    for command in (50.0, -50.0):
        out = unicycle_step(state, torch.tensor([0.0, command], dtype=torch.float64), 0.1)
        assert out[3].item() == pytest.approx(math.copysign(0.1 * bound, command))


def test_custom_bounds():
    bounds = UnicycleBounds(acc_min=-6.0, acc_max=4.0, max_yaw_rate=8.0)
    lb, ub = action_bounds(torch.tensor(5.0), bounds)
    assert lb.tolist() == pytest.approx([-6.0, -1.6]) and ub.tolist() == pytest.approx([4.0, 1.6])
    with pytest.raises(ValueError):
        UnicycleBounds(acc_mx=1.0)


@FAST
@given(
    st.floats(-15, 35),
    st.floats(-math.pi, math.pi),
    st.floats(-50, 50),
    st.floats(-10, 10),
)
def test_step_respects_bounds_property(speed, yaw, acc, yaw_rate):
    state = torch.tensor([1.0, -2.0, speed, yaw], dtype=torch.float64)
    out = unicycle_step(state, torch.tensor([acc, yaw_rate], dtype=torch.float64), 0.1)
    lb, ub = action_bounds(state[2])
    eff_acc = (out[2] - speed) / 0.1
    eff_rate = wrap_angle(out[3] - yaw) / 0.1
    assert lb[0] - 1e-9 <= eff_acc <= ub[0] + 1e-9
    assert lb[1] - 1e-9 <= eff_rate <= ub[1] + 1e-9
    if lb[0] <= acc <= ub[0]:
        assert eff_acc.item() == pytest.approx(acc, abs=1e-9)


def _loop_rollout(initial, actions, dt, bounds):
    state, out = initial, []
    for t in range(actions.shape[-2]):
        state = unicycle_step(state, actions[..., t, :], dt, bounds)
        out.append(state)
    return torch.stack(out, -2)


@pytest.mark.parametrize("seed", range(3))
def test_closed_form_rollout_equals_loop_without_bounds(seed):
    gen = torch.Generator().manual_seed(seed)
    initial = torch.randn(3, 5, 4, generator=gen, dtype=torch.float64) * torch.tensor([20.0, 20.0, 5.0, 2.0],
                                                                                       dtype=torch.float64)
    actions = torch.randn(3, 5, 40, 2, generator=gen, dtype=torch.float64) * torch.tensor([3.0, 1.0],
                                                                                           dtype=torch.float64)
    closed = unicycle_rollout(initial, actions, 0.1, bounds=None)
    looped = _loop_rollout(initial, actions, 0.1, None)
    assert closed.shape == looped.shape == (3, 5, 40, 4)
    assert torch.allclose(closed[..., :3], looped[..., :3], atol=1e-9)
    assert wrap_angle(closed[..., 3] - looped[..., 3]).abs().max() < 1e-9
    assert (closed[..., 3] >= -math.pi).all() and (closed[..., 3] < math.pi).all()


def test_bounded_rollout_equals_loop_of_bounded_steps():
    gen = torch.Generator().manual_seed(0)
    initial = torch.randn(4, 4, generator=gen) * torch.tensor([10.0, 10.0, 8.0, 2.0])
    actions = torch.randn(4, 30, 2, generator=gen) * torch.tensor([20.0, 5.0])  # often out of bounds
    assert torch.equal(unicycle_rollout(initial, actions, 0.1), _loop_rollout(initial, actions, 0.1, DEFAULT_BOUNDS))
    assert not torch.allclose(unicycle_rollout(initial, actions, 0.1, bounds=None),
                              unicycle_rollout(initial, actions, 0.1))


@settings(max_examples=30, deadline=None)
@given(feasible_trajectories(max_steps=12, return_actions=True))
def test_in_bounds_actions_are_not_clipped(scenario_and_actions):
    scenario, actions = scenario_and_actions
    initial = scenario.states[:, :, 0]
    bounded = unicycle_rollout(initial, actions, scenario.dt)
    free = unicycle_rollout(initial, actions, scenario.dt, bounds=None)
    assert torch.allclose(bounded[..., :3], free[..., :3], atol=1e-3)
    assert wrap_angle(bounded[..., 3] - free[..., 3]).abs().max() < 1e-4
    assert torch.equal(bounded, scenario.states[:, :, 1:])


def test_gradcheck_rollout_and_step_without_bounds():
    gen = torch.Generator().manual_seed(1)
    initial = (torch.randn(2, 4, generator=gen, dtype=torch.float64) * 0.5).requires_grad_()
    actions = (torch.randn(2, 3, 2, generator=gen, dtype=torch.float64) * 0.5).requires_grad_()
    assert torch.autograd.gradcheck(lambda s, a: unicycle_rollout(s, a, 0.1, bounds=None), (initial, actions))
    assert torch.autograd.gradcheck(lambda s, a: unicycle_step(s, a, 0.1, bounds=None), (initial, actions[:, 0]))


def test_gradients_flow_through_bounded_rollout():
    initial = torch.tensor([[0.0, 0.0, 5.0, 0.3]], requires_grad=True)
    actions = torch.tensor([[[0.5, 0.1], [-0.5, -0.1], [1.0, 0.0]]], requires_grad=True)  # inside the bounds
    unicycle_rollout(initial, actions, 0.1)[..., -1, :2].sum().backward()
    assert torch.isfinite(actions.grad).all() and (actions.grad[..., :2, :].abs() > 0).all()
    assert torch.isfinite(initial.grad).all() and initial.grad[0, 2].abs() > 0
    clipped = torch.tensor([[[100.0, 0.0]]], requires_grad=True)  # clipped: no gradient through the action
    unicycle_rollout(initial.detach(), clipped, 0.1)[..., 2].sum().backward()
    assert clipped.grad[0, 0, 0] == 0


@pytest.mark.parametrize("bounds", [DEFAULT_BOUNDS, None])
@pytest.mark.parametrize("lead", [(), (3,), (2, 3), (2, 1, 3)])
def test_batching_over_leading_dims(lead, bounds):
    gen = torch.Generator().manual_seed(2)
    initial = torch.randn(*lead, 4, generator=gen) * 3
    actions = torch.randn(*lead, 6, 2, generator=gen) * 3
    out = unicycle_rollout(initial, actions, 0.1, bounds)
    assert out.shape == (*lead, 6, 4)
    flat_init, flat_act = initial.reshape(-1, 4), actions.reshape(-1, 6, 2)
    for k in range(flat_init.shape[0]):
        single = unicycle_rollout(flat_init[k], flat_act[k], 0.1, bounds)
        assert torch.allclose(out.reshape(-1, 6, 4)[k], single, atol=1e-5)
    step = unicycle_step(initial, actions[..., 0, :], 0.1, bounds)
    assert step.shape == (*lead, 4) and torch.allclose(step, out[..., 0, :], atol=1e-6)
    lb, ub = action_bounds(initial[..., 2])
    assert lb.shape == ub.shape == (*lead, 2)


@FAST
@given(st.floats(-1e4, 1e4))
def test_wrap_angle_range_and_equivalence(angle):
    for dtype in (torch.float32, torch.float64):
        x = torch.tensor(angle, dtype=dtype)
        w = wrap_angle(x)
        assert -math.pi <= w.item() < math.pi or (dtype == torch.float32 and w == -torch.tensor(math.pi))
        k = (x.double() - w.double()) / (2 * math.pi)
        assert abs(k.item() - round(k.item())) < (1e-3 if dtype == torch.float32 else 1e-9)
