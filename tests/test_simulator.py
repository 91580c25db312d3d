"""Closed-loop simulator: log replay is exact, replanning protocol (2 Hz, no peeking), controlled-agent selection,
policy errors, built-in policies and config validation."""

from __future__ import annotations

import dataclasses
import os

import pydantic
import pytest
import torch

from trafficrlhf_sdk.errors import ScenarioValidationError
from trafficrlhf_sdk.metrics import FailureMetric, RealismMetric
from trafficrlhf_sdk.metrics.failure import collisions_per_step
from trafficrlhf_sdk.scenario import AgentType, MapRaster, ScenarioTensor, default_data_root
from trafficrlhf_sdk.simulation import (
    ConstantVelocityPolicy,
    LogReplayPolicy,
    NoisyLogPolicy,
    Plan,
    Rollout,
    SimulationConfig,
    log_rollout,
    simulate,
)

NUM_REAL_SCENES = 30


# ----------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def real_scenes() -> ScenarioTensor:
    """The first 30 long-enough nuscenes_pred val scenes (skips without the data or the plugin)."""
    if not os.path.isdir(os.path.join(default_data_root(), "nuscenes_pred", "label")):
        pytest.skip(f"nuscenes_pred not found under {default_data_root()!r}")
    from trafficrlhf_sdk import get_scenario_source
    from trafficrlhf_sdk.errors import UnknownComponentError

    try:
        source = get_scenario_source("nuscenes_pred")
    except UnknownComponentError:
        pytest.skip("the nuscenes_pred source plugin is not installed")
    return source.load_batch("val", NUM_REAL_SCENES)


@pytest.fixture(scope="module")
def replay(real_scenes) -> Rollout:  # type: ignore[no-untyped-def]
    return simulate(LogReplayPolicy(), real_scenes)


def synthetic(num_agents: int = 3, num_steps: int = 131, scene_map: MapRaster | None = None,
              y: list[float] | None = None) -> ScenarioTensor:
    """One scene of agents driving along +x at 5 m/s in parallel lanes (y = 0, 5, 10, ...), 3 s of history."""
    time_s = torch.arange(num_steps, dtype=torch.float32) * 0.1
    lanes = y if y is not None else [5.0 * a for a in range(num_agents)]
    states = torch.stack([torch.stack([5.0 * time_s, torch.full_like(time_s, lane), torch.full_like(time_s, 5.0),
                                       torch.zeros_like(time_s)], -1) for lane in lanes])[None]
    return ScenarioTensor(
        states=states, valid=torch.ones(1, len(lanes), num_steps, dtype=torch.bool),
        extent=torch.tensor([[[4.0, 2.0]] * len(lanes)]),
        agent_type=torch.full((1, len(lanes)), int(AgentType.VEHICLE)),
        controlled=torch.ones(1, len(lanes), dtype=torch.bool), current_index=30, map=scene_map,
    )


class CountingPolicy:
    """Constant velocity that records every call and what it was shown."""

    def __init__(self) -> None:
        self.inner = ConstantVelocityPolicy()
        self.calls: list[tuple[int, int, int]] = []  # (current_index, context.num_steps, horizon)
        self.contexts: list[ScenarioTensor] = []
        self.reset_with: ScenarioTensor | None = None

    def reset(self, scenario: ScenarioTensor) -> None:
        self.reset_with = scenario
        self.inner.reset(scenario)

    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        self.calls.append((context.current_index, context.num_steps, horizon))
        self.contexts.append(context)
        return self.inner.plan(context, horizon)


# --------------------------------------------------------------------------------------- log replay
def test_log_replay_reproduces_the_log_exactly(real_scenes, replay) -> None:  # type: ignore[no-untyped-def]
    end = replay.end_index
    assert (replay.start_index, end) == (30, 130)
    assert torch.equal(replay.simulated.states, real_scenes.states[:, :, : end + 1])
    # by default (late_agents="drop", upstream) the tracks that appear after the start are left out
    expected = real_scenes.valid[:, :, : end + 1].clone()
    expected[:, :, 31:] &= real_scenes.valid[:, :, 30, None]
    assert torch.equal(replay.simulated.valid, expected)
    assert not torch.equal(expected, real_scenes.valid[:, :, : end + 1]), "the val scenes have late tracks"
    kept = log_rollout(real_scenes, SimulationConfig(late_agents="replay"))
    assert torch.equal(kept.simulated.valid, real_scenes.valid[:, :, : end + 1])
    assert torch.equal(replay.simulated.states, replay.logged.states)
    assert torch.equal(replay.simulated.valid, replay.logged.valid)
    assert replay.controlled.any()
    assert not (replay.controlled & ~real_scenes.controlled).any()


def test_log_replay_failure_rate_equals_the_logged_data(replay) -> None:  # type: ignore[no-untyped-def]
    """FailureMetric of the replayed rollout = FailureMetric of the logged scene itself (and of log_rollout)."""
    logged_only = Rollout(replay.logged, replay.logged, replay.controlled, replay.start_index, replay.end_index)
    replayed = FailureMetric().compute(replay).values
    assert replayed == FailureMetric().compute(logged_only).values
    assert replayed == FailureMetric().compute(log_rollout(replay.logged)).values
    assert 0 <= replayed["failure_rate"] < 0.1  # the log has a few annotation overlaps, not many failures


@pytest.mark.parametrize("preset", ["ctg", "body"])
def test_log_replay_has_zero_realism_deviation(replay, preset) -> None:  # type: ignore[no-untyped-def]
    values = RealismMetric(preset).compute(replay).values
    assert values and all(v == 0.0 for v in values.values()), values


def test_constant_velocity_is_worse_than_log_replay(real_scenes, replay) -> None:  # type: ignore[no-untyped-def]
    rollout = simulate(ConstantVelocityPolicy(), real_scenes)
    assert torch.equal(rollout.controlled, replay.controlled)
    cv, log = FailureMetric().compute(rollout).values, FailureMetric().compute(replay).values
    assert cv["failure_rate"] > log["failure_rate"]
    for preset in ("ctg", "body"):
        name = f"realism_{preset}"
        assert RealismMetric(preset).compute(rollout).values[name] > RealismMetric(preset).compute(replay).values[name]


def test_uncontrolled_agents_replay_the_log(real_scenes) -> None:  # type: ignore[no-untyped-def]
    """Release every other controlled agent: under constant velocity they still follow the log exactly."""
    ids = real_scenes.controlled.nonzero()
    released = ids[::2]
    controlled = real_scenes.controlled.clone()
    controlled[released[:, 0], released[:, 1]] = False
    scenario = dataclasses.replace(real_scenes, controlled=controlled)
    rollout = simulate(ConstantVelocityPolicy(), scenario, SimulationConfig(late_agents="replay"))
    end = rollout.end_index
    free = ~rollout.controlled
    assert free[released[:, 0], released[:, 1]].all()
    assert torch.equal(rollout.simulated.states[free], real_scenes.states[:, :, : end + 1][free])
    assert torch.equal(rollout.simulated.valid[free], real_scenes.valid[:, :, : end + 1][free])
    driven = rollout.simulated.states[rollout.controlled][:, rollout.start_index + 1 :]
    logged = real_scenes.states[:, :, : end + 1][rollout.controlled][:, rollout.start_index + 1 :]
    assert not torch.equal(driven, logged)  # the policy did drive the others


# ----------------------------------------------------------------------------------- replanning
def test_replanning_protocol_and_no_peeking() -> None:
    """10 s at 2 Hz = 20 plan calls at steps 30, 35, ..., 125; each sees exactly steps 0..now of the simulated
    scene (never the future), and reset receives the log with current_index = start."""
    policy = CountingPolicy()
    rollout = simulate(policy, synthetic())
    assert [c[0] for c in policy.calls] == list(range(30, 130, 5))
    assert all(num_steps == now + 1 for now, num_steps, _ in policy.calls)
    assert all(horizon == 5 for *_, horizon in policy.calls)
    assert policy.reset_with is not None and policy.reset_with.current_index == 30
    for context in policy.contexts:
        t = context.current_index
        assert context.states.shape[2] == context.valid.shape[2] == t + 1
        assert torch.equal(context.states, rollout.simulated.states[:, :, : t + 1])  # the simulated past


def test_replanning_with_longer_plans_and_other_rates() -> None:
    policy = CountingPolicy()
    simulate(policy, synthetic(), SimulationConfig(replan_every=10, plan_horizon=52, duration_s=5.0))
    assert [c[0] for c in policy.calls] == [30, 40, 50, 60, 70]
    assert {c[2] for c in policy.calls} == {52}


def test_rollout_past_the_end_of_the_log_is_padded() -> None:
    """A log shorter than start + 10 s: the window is padded, uncontrolled steps past the log are invalid."""
    scenario = synthetic(num_steps=100)
    rollout = simulate(ConstantVelocityPolicy(), scenario, SimulationConfig(after_log_end="continue"))
    assert rollout.simulated.num_steps == 131
    assert rollout.simulated.valid[:, :, 100:].all()  # controlled agents keep driving (upstream)
    assert not rollout.logged.valid[:, :, 100:].any()
    ended = simulate(ConstantVelocityPolicy(), scenario)  # default: a driven agent ends with its logged track
    assert ended.simulated.valid[:, :, 31:100].all() and not ended.simulated.valid[:, :, 100:].any()
    assert torch.equal(ended.simulated.states[:, :, :100], rollout.simulated.states[:, :, :100])


def test_failures_after_a_logged_track_ends_are_not_counted_by_default() -> None:
    """An agent driven at constant velocity off the end of its logged track into another agent: a collision with
    after_log_end="continue", none by default, where the agent leaves the scene when its log ends."""
    scenario = synthetic(y=[0.0, 0.0, 50.0])
    valid = scenario.valid.clone()
    valid[0, 0, 60:] = False  # agent 0's log ends 3 s into the rollout, 2 m/s behind the parked agent 1
    states = scenario.states.clone()
    states[0, 1, :, 0] = 50.0  # agent 1 stands on agent 0's path, reached after its log has ended
    states[0, 1, :, 2] = 0.0
    scenario = dataclasses.replace(scenario, valid=valid, states=states * valid[..., None])
    kept = simulate(ConstantVelocityPolicy(), scenario, SimulationConfig(after_log_end="continue"))
    ended = simulate(ConstantVelocityPolicy(), scenario)
    assert collisions_per_step(kept.simulated)[0, 0, 31:].any()
    assert not collisions_per_step(ended.simulated)[0, 0, 31:].any()


# ------------------------------------------------------------------------------ controlled agents
def tiny_map() -> MapRaster:
    """A 4 m x 40 m map at 1 px/m: x in [0, 40) along rows, y in [0, 4) along columns; drivable only for y < 2."""
    drivable = torch.zeros(40, 4, dtype=torch.uint8)
    drivable[:, :2] = 1
    raster = torch.stack([drivable, torch.zeros_like(drivable), torch.zeros_like(drivable)])[None]
    return MapRaster(raster=raster, world_to_pixel=torch.eye(3)[None])


def test_agents_starting_off_road_are_not_controlled() -> None:
    # agent 0 on the drivable strip, agent 1 off it (y = 3), agent 2 outside the raster (y = 10)
    scenario = synthetic(scene_map=tiny_map(), y=[0.5, 3.0, 10.0])
    scenario = dataclasses.replace(scenario, states=scenario.states.clone())
    scenario.states[..., 0] -= 12.0  # at the start step (t = 3 s) every agent is at x = 3 m, inside the map rows
    rollout = simulate(ConstantVelocityPolicy(), scenario)
    assert rollout.controlled.tolist() == [[True, False, False]]
    assert torch.equal(rollout.simulated.states[0, 1:], scenario.states[0, 1:, :131])  # the others replay the log
    kept = simulate(ConstantVelocityPolicy(), scenario, SimulationConfig(remove_offroad_at_start=False))
    assert kept.controlled.tolist() == [[True, True, True]]


def test_a_scene_without_controlled_agents_replays_the_log() -> None:
    scenario = synthetic(scene_map=tiny_map(), y=[3.0, 10.0])  # both off the drivable strip (and x = 15 m)
    policy = CountingPolicy()
    rollout = simulate(policy, scenario)
    assert not rollout.controlled.any() and len(policy.calls) == 20
    assert torch.equal(rollout.simulated.states, rollout.logged.states)
    assert all(v != v for v in FailureMetric().compute(rollout).values.values())  # NaN: no agent to rate


def test_agents_invalid_at_the_start_are_not_controlled() -> None:
    scenario = synthetic()
    valid = scenario.valid.clone()
    valid[0, 1, :31] = False  # appears after the start
    scenario = dataclasses.replace(scenario, valid=valid, states=scenario.states * valid[..., None])
    rollout = simulate(ConstantVelocityPolicy(), scenario, SimulationConfig(late_agents="replay"))
    assert rollout.controlled.tolist() == [[True, False, True]]
    assert torch.equal(rollout.simulated.valid[0, 1], valid[0, 1, :131])  # replayed from the step it appears
    dropped = simulate(ConstantVelocityPolicy(), scenario)  # default, upstream: left out of the rollout
    assert dropped.controlled.tolist() == [[True, False, True]]
    assert not dropped.simulated.valid[0, 1].any() and not dropped.logged.valid[0, 1].any()


# ------------------------------------------------------------------------------------- bad policies
class FixedPolicy:
    """Returns whatever ``make(context, horizon)`` builds."""

    def __init__(self, make) -> None:  # type: ignore[no-untyped-def]
        self.make = make

    def reset(self, scenario: ScenarioTensor) -> None:
        pass

    def plan(self, context: ScenarioTensor, horizon: int):  # type: ignore[no-untyped-def]
        return self.make(context, horizon)


def _good(context: ScenarioTensor, horizon: int) -> torch.Tensor:
    return ConstantVelocityPolicy().plan(context, horizon).states


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda c, h: Plan(_good(c, h)[:, :1]), "shape"),  # one agent missing
        (lambda c, h: Plan(_good(c, h)[:, :, :2]), "shape"),  # plan shorter than the executed steps
        (lambda c, h: Plan(_good(c, h)[..., :3]), "shape"),  # no yaw
        (lambda c, h: Plan(_good(c, h)[0]), "shape"),  # batch axis dropped
        (lambda c, h: Plan(_good(c, h), torch.ones(1, 3, h, 2, dtype=torch.bool)), "valid"),
        (lambda c, h: Plan(_good(c, h), torch.ones(1, 3, h)), "valid"),  # float mask
        (lambda c, h: _good(c, h), "Plan"),  # a bare tensor
        (lambda c, h: Plan(torch.full_like(_good(c, h), float("nan"))), "NaN"),
        (lambda c, h: Plan(_good(c, h) * (float("inf") if c.current_index == 60 else 1.0)), "NaN or inf"),
    ],
)
def test_bad_plans_raise_clear_errors(make, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ScenarioValidationError, match=match) as info:
        simulate(FixedPolicy(make), synthetic())
    assert "FixedPolicy" in str(info.value)


def test_nan_in_steps_the_plan_marks_invalid_is_fine() -> None:
    """A policy may leave NaN where it marks its plan invalid; those slots end up zero and invalid."""

    def make(context: ScenarioTensor, horizon: int) -> Plan:
        states = _good(context, horizon).clone()
        valid = torch.ones(states.shape[:3], dtype=torch.bool)
        states[:, 2], valid[:, 2] = float("nan"), False  # agent 2 vanishes
        return Plan(states, valid)

    rollout = simulate(FixedPolicy(make), synthetic())
    assert not rollout.simulated.valid[0, 2, 31:].any()
    assert torch.equal(rollout.simulated.states[0, 2, 31:], torch.zeros(100, 4))


# --------------------------------------------------------------------------------- built-in policies
def test_noisy_log_policy_is_deterministic_under_a_seed() -> None:
    scenario = synthetic()
    first = simulate(NoisyLogPolicy(position_noise_m=1.0, seed=3), scenario)
    second = simulate(NoisyLogPolicy(position_noise_m=1.0, seed=3), scenario)
    other = simulate(NoisyLogPolicy(position_noise_m=1.0, seed=4), scenario)
    assert torch.equal(first.simulated.states, second.simulated.states)
    assert not torch.equal(first.simulated.states, other.simulated.states)
    assert not torch.equal(first.simulated.states, first.logged.states)
    silent = simulate(NoisyLogPolicy(position_noise_m=0.0, seed=3), scenario)
    assert torch.equal(silent.simulated.states, silent.logged.states)


def test_noisy_log_policy_rejects_bad_options() -> None:
    with pytest.raises(ValueError, match="position_noise_m"):
        NoisyLogPolicy(position_noise_m=-1.0)
    with pytest.raises(ValueError, match="ramp_s"):
        NoisyLogPolicy(ramp_s=0.0)


def test_constant_velocity_keeps_speed_and_heading() -> None:
    scenario = synthetic()
    rollout = simulate(ConstantVelocityPolicy(), scenario)
    # the synthetic log is itself constant velocity, so the rollout reproduces it up to float32 rounding
    torch.testing.assert_close(rollout.simulated.states, rollout.logged.states, atol=1e-4, rtol=0)


# ------------------------------------------------------------------------------------------- config
def test_config_rejects_unknown_keys() -> None:
    with pytest.raises(pydantic.ValidationError, match="replan_evry"):
        SimulationConfig(replan_evry=5)  # type: ignore[call-arg]


def test_config_rejects_plan_horizon_shorter_than_replan_interval() -> None:
    with pytest.raises(pydantic.ValidationError, match="plan_horizon"):
        SimulationConfig(replan_every=10, plan_horizon=5)
    assert SimulationConfig(replan_every=10, plan_horizon=10).plan_horizon == 10


@pytest.mark.parametrize("options", [{"duration_s": 0.0}, {"replan_every": 0}, {"start_index": 0}])
def test_config_rejects_out_of_range_values(options) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(pydantic.ValidationError):
        SimulationConfig(**options)


def test_start_index_outside_the_scene_is_refused() -> None:
    with pytest.raises(ScenarioValidationError, match="start_index"):
        simulate(ConstantVelocityPolicy(), synthetic(), SimulationConfig(start_index=500))
