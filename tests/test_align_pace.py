"""The fine-tuner's pace constraint (``pace_tolerance``, trafficrlhf_sdk.alignment.pace)."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
from trafficrlhf_sdk.alignment.pace import PaceConstraint, sample_speeds
from trafficrlhf_sdk.metrics.speed import pooled_speed_ratio
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

gru = pytest.importorskip("trafficrlhf_example_gru")

FAST = dict(contexts_per_epoch=4, samples_per_context=4, minibatch_contexts=2, ppo_epochs=1, progress_bar=False)


def _model():  # type: ignore[no-untyped-def]
    torch.manual_seed(0)
    return gru.ExampleGRUAdapter()


class SlowerIsBetter:
    """A reward that pays for braking: each agent's reward is minus its mean speed over the sampled future."""

    def agent_scores(self, scenario: ScenarioTensor) -> torch.Tensor:
        return -sample_speeds(scenario, scenario.num_steps - 1 - scenario.current_index) / 10.0

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        speed = scenario.states[..., 2].abs() * scenario.valid
        return -(speed.sum(1) / scenario.valid.sum(1).clamp_min(1)) / 10.0


def test_sample_speeds_is_the_mean_absolute_speed_over_the_valid_future_steps(
        train_scene_list: list[ScenarioTensor]) -> None:
    scene = train_scene_list[0].replace_unchecked(current_index=10)
    speeds = sample_speeds(scene, 20)
    for a in range(scene.num_agents):
        valid = scene.valid[0, a, 11:31]
        values = scene.states[0, a, 11:31, 2].abs()[valid]
        expected = values.mean() if valid.any() else torch.tensor(0.0)
        assert torch.isclose(speeds[0, a], expected, atol=1e-5)


def test_the_multipliers_move_only_outside_the_band_and_each_on_its_own_side() -> None:
    pace = PaceConstraint(0.03, 10.0, lambda: [], 4, None)
    pace.base = {"": 1.0}
    stats = pace.step(None, {"pooled_speed_ratio": 0.99, "failure_rate": 0.1})  # 1 % slower: inside the band
    assert (stats["pace_multiplier_slow"], stats["pace_multiplier_fast"]) == (0.0, 0.0)
    stats = pace.step(None, {"pooled_speed_ratio": 0.95, "failure_rate": 0.1})  # 5 % slower: 2 points outside
    assert stats["pace_change"] == pytest.approx(-0.05)
    assert stats["pace_multiplier_slow"] == pytest.approx(0.2) and stats["pace_multiplier_fast"] == 0.0
    pace.step(None, {"pooled_speed_ratio": 0.99, "failure_rate": 0.1})  # back inside: the multiplier decays
    assert pace.bands[""].slow == pytest.approx(0.0)
    pace.step(None, {"pooled_speed_ratio": 1.06, "failure_rate": 0.1})
    assert pace.bands[""].slow == 0.0 and pace.bands[""].fast == pytest.approx(0.3)
    pace.restore([{"pace_multiplier_slow": 0.5, "pace_multiplier_fast": 0.0}])
    assert (pace.bands[""].slow, pace.bands[""].fast) == (0.5, 0.0)


def test_the_proportional_term_adds_the_current_violation_to_the_accumulated_multiplier() -> None:
    pace = PaceConstraint(0.03, 10.0, lambda: [], 4, None, kp=20.0)
    pace.base = {"": 1.0}
    stats = pace.step(None, {"pooled_speed_ratio": 0.95, "failure_rate": 0.1})  # e_slow = 0.02, e_fast = -0.08
    assert stats["pace_integral_slow"] == pytest.approx(0.2) and stats["pace_integral_fast"] == 0.0
    assert stats["pace_multiplier_slow"] == pytest.approx(0.2 + 20 * 0.02) and stats["pace_multiplier_fast"] == 0.0
    pace.step(None, {"pooled_speed_ratio": 1.0, "failure_rate": 0.1})  # inside: e_slow = -0.03
    band = pace.bands[""]
    assert band.slow_sum == 0.0 and band.slow == 0.0  # 0.2 - 10 x 0.03 and 0.2 - 20 x 0.03: never below 0
    pace.restore([{"pace_multiplier_slow": 0.9, "pace_multiplier_fast": 0.0, "pace_integral_slow": 0.4,
                   "pace_integral_fast": 0.0}])
    assert (pace.bands[""].slow, pace.bands[""].slow_sum) == (0.9, 0.4)


def test_turning_and_straight_agents_have_bands_of_their_own() -> None:
    """With ``by_turning`` a slowdown of only the turning agents raises only the turning band's slow multiplier;
    the straight band's agents keep their plain advantages, the turning ones get the speed term."""
    pace = PaceConstraint(0.03, 10.0, lambda: [], 4, None, by_turning=True)
    start = {"pooled_speed_ratio": 1.0, "pooled_speed_ratio_turning": 0.9, "pooled_speed_ratio_straight": 1.05,
             "failure_rate": 0.1}
    stats = pace.step(None, start)
    assert stats["pace_change_turning"] == stats["pace_change_straight"] == stats["pace_change"] == 0.0
    stats = pace.step(None, {"pooled_speed_ratio": 1.0, "pooled_speed_ratio_turning": 0.9 * 0.95,
                             "pooled_speed_ratio_straight": 1.05 * 1.02, "failure_rate": 0.1})
    assert stats["pace_change_turning"] == pytest.approx(-0.05) and stats["pace_change"] == 0.0
    assert stats["pace_multiplier_slow_turning"] == pytest.approx(0.2)
    assert stats["pace_multiplier_slow_straight"] == stats["pace_multiplier_fast_straight"] == 0.0
    adv = torch.tensor([[[0.0, 1.0]], [[0.0, -1.0]], [[0.0, 0.0]]]).transpose(0, 1)  # (B=1, S=3, A=2)
    speeds = torch.tensor([[[4.0, 4.0]], [[6.0, 6.0]], [[8.0, 8.0]]]).transpose(0, 1)
    turning = torch.tensor([[[True, False]]])  # agent 0 turns in the log
    mixed = pace.mix(adv, speeds, 1, torch.ones_like(adv, dtype=torch.bool), turning)
    assert mixed[0, 2, 0] > mixed[0, 1, 0] > mixed[0, 0, 0]  # the faster sample of the turning agent is preferred
    assert torch.equal(mixed[0, :, 1], adv[0, :, 1])  # the straight agent's band is idle
    with pytest.raises(ValueError, match="turning"):
        pace.mix(adv, speeds, 1, torch.ones_like(adv, dtype=torch.bool))
    pace.restore([{**stats, "pace_multiplier_fast_straight": 0.4}])
    assert (pace.bands["straight"].fast, pace.bands["turning"].slow) == (0.4, pytest.approx(0.2))
    pace.step(None, {"pooled_speed_ratio": 1.0, "pooled_speed_ratio_turning": float("nan"),
                     "pooled_speed_ratio_straight": 1.05, "failure_rate": 0.1})  # no turning agent was driven
    assert pace.bands["turning"].slow == pytest.approx(0.2)  # held, not moved by a NaN


def test_a_context_agent_turns_when_its_logged_window_turns_by_more_than_turn_rad(
        train_scene_list: list[ScenarioTensor]) -> None:
    from trafficrlhf_sdk.alignment.pace import logged_turning
    from trafficrlhf_sdk.metrics.speed import TURN_RAD

    scene = max(train_scene_list, key=lambda s: s.num_agents).time_slice(0, 71).replace_unchecked(current_index=30)
    assert scene.num_agents >= 5
    states = scene.states.clone()
    states[0, :, 31:, 3] = 0.0
    states[0, 0, 31:, 3] = torch.linspace(0.0, TURN_RAD + 0.1, 40)
    states[0, 1, 31:, 3] = torch.linspace(0.0, -(TURN_RAD + 0.1), 40)
    states[0, 2, 31:, 3] = torch.linspace(0.0, TURN_RAD - 0.1, 40)
    states[0, 3, :31, 3] = torch.linspace(0.0, 3.0, 31)  # turned in its history only
    valid = torch.ones_like(scene.valid)
    turning = logged_turning(scene.replace_unchecked(states=states, valid=valid))
    assert turning[0, :4].tolist() == [True, True, False, False]
    assert not turning[0, 4:].any()


def _plant_swings(kp: float, epochs: int = 70) -> list[float]:
    """A toy policy whose pace, pulled 1 % slower per epoch by its reward, moves by 0.0165 x the net multiplier
    (slow - fast) of two epochs before (the response measured on a model that answers within a few epochs);
    returns the pace change per epoch."""
    pace = PaceConstraint(0.03, 5.0, lambda: [], 4, None, kp=kp)
    pace.base = {"": 1.0}
    change, changes, pushes = 0.0, [], [0.0, 0.0]
    for _ in range(epochs):
        pace.step(None, {"pooled_speed_ratio": 1.0 + change, "failure_rate": 0.0})
        changes.append(change)
        pushes.append(pace.bands[""].slow - pace.bands[""].fast)
        change += -0.01 + 0.0165 * pushes[-3]
    return changes


def test_the_proportional_term_damps_the_swings_of_a_fast_answering_pace() -> None:
    """With the plain Lagrangian (an integral controller) the delayed toy pace swings ever wider around the band;
    with a proportional gain it stays near it."""
    plain, damped = _plant_swings(0.0), _plant_swings(20.0)
    assert max(abs(c) for c in plain[-20:]) > 0.2
    assert max(abs(c) for c in damped[-20:]) < 0.06


def test_the_speed_term_ranks_samples_by_speed_and_leaves_advantages_alone_at_zero_multipliers() -> None:
    pace = PaceConstraint(0.03, 1.0, lambda: [], 4, None)
    adv = torch.tensor([[[0.0, 1.0]], [[0.0, -1.0]], [[0.0, 0.0]]]).transpose(0, 1)  # (B=1, S=3, A=2)
    speeds = torch.tensor([[[4.0, 5.0]], [[6.0, 5.0]], [[8.0, 5.0]]]).transpose(0, 1)
    mask = torch.ones_like(adv, dtype=torch.bool)
    assert torch.equal(pace.mix(adv, speeds, 1, mask), adv)
    pace.bands[""].slow = 1.0
    mixed = pace.mix(adv, speeds, 1, mask)
    # agent 0 had no reward advantage (a passing agent): the faster sample now has the higher advantage
    assert mixed[0, 2, 0] > mixed[0, 1, 0] > mixed[0, 0, 0]
    # agent 1's samples all have the same speed: only the reward term, scaled by 1 / (1 + slow)
    assert torch.allclose(mixed[0, :, 1], adv[0, :, 1] / 2)
    pace.bands[""].slow, pace.bands[""].fast = 0.0, 1.0  # too fast: the slower sample is preferred
    mixed = pace.mix(adv, speeds, 1, mask)
    assert mixed[0, 0, 0] > mixed[0, 2, 0]


def test_the_pace_drive_is_the_pooled_speed_ratio_of_the_evaluations_rollout_and_repeats_exactly(
        train_scene_list: list[ScenarioTensor]) -> None:
    model = _model()
    pace = PaceConstraint(0.03, 5.0, lambda: train_scene_list, 3, None)
    state = torch.get_rng_state()
    first = pace.drive(model)
    assert torch.equal(torch.get_rng_state(), state)  # the training's random numbers are not consumed
    assert pace.drive(model) == first  # same weights, same scenes, same seed: the same figures
    torch.manual_seed(0)
    model.options = model.options.model_copy(update={"seed": 0})
    rollout = simulate(model, pace.batch(), SimulationConfig(duration_s=10.0))
    assert first["pooled_speed_ratio"] == pytest.approx(pooled_speed_ratio(rollout))
    assert pace.batch().num_scenes == 3 and pace.batch().current_index == 30


def test_the_constraint_holds_the_pace_against_a_reward_that_pays_for_braking(
        train_scene_list: list[ScenarioTensor]) -> None:
    """Trained against a reward that only pays for slowing down, the unconstrained policy loses pace on the
    held-out drive; with the constraint the multiplier rises and the pace stays closer to the start."""
    common = dict(alpha=1.0, imitation_coef=0.0, credit="agent", learning_rate=3e-3, epochs=6, **FAST)

    def run(**extra):  # type: ignore[no-untyped-def]
        trainer = AlignTrainer(_model(), SlowerIsBetter(), AlignConfig(**common, **extra), scenes=train_scene_list)
        trainer.pace = trainer.pace or PaceConstraint(1.0 - 1e-9, 0.0, lambda: train_scene_list, 4, None)
        return trainer.train()

    free = run()
    held = run(pace_tolerance=0.02, pace_multiplier_lr=20.0)
    assert free[0]["pace_change"] == held[0]["pace_change"] == 0.0  # epoch 1 drives the starting weights
    assert free[-1]["pace_change"] < -0.04, "the braking reward must slow the free policy"
    assert max(row["pace_multiplier_slow"] for row in held) > 0
    assert held[-1]["pace_change"] > free[-1]["pace_change"] + 0.02
    assert all("heldout_failure" in row for row in held)


def test_the_two_bands_run_in_the_trainer_and_need_agent_credit(train_scene_list: list[ScenarioTensor]) -> None:
    with pytest.raises(ValueError, match="pace_by_turning"):
        AlignConfig(pace_by_turning=True, credit="agent")
    with pytest.raises(ValueError, match="credit='agent'"):
        AlignConfig(pace_by_turning=True, pace_tolerance=0.03, credit="scene")
    config = AlignConfig(alpha=1.0, credit="agent", epochs=2, pace_tolerance=0.001, pace_multiplier_lr=50.0,
                         pace_by_turning=True, **FAST)
    history = AlignTrainer(_model(), SlowerIsBetter(), config, scenes=train_scene_list).train()
    for row in history:
        assert {"pace_change_turning", "pace_change_straight", "pace_multiplier_slow_turning",
                "pace_multiplier_fast_straight"} <= set(row)
    assert history[0]["pace_change_turning"] == history[0]["pace_change_straight"] == 0.0
