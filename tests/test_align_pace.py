"""The fine-tuner's pace constraint (``pace_tolerance``, trafficrlhf_sdk.alignment.pace)."""

from __future__ import annotations

import math

import pytest
import torch

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
from trafficrlhf_sdk.alignment.pace import PaceConstraint, sample_speeds
from trafficrlhf_sdk.metrics.speed import SpeedMetric
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
    pace.base_ratio = 1.0
    stats = pace.step(None, {"speed_ratio": 0.99, "failure_rate": 0.1})  # 1 % slower: inside the band
    assert (stats["pace_multiplier_slow"], stats["pace_multiplier_fast"]) == (0.0, 0.0)
    stats = pace.step(None, {"speed_ratio": 0.95, "failure_rate": 0.1})  # 5 % slower: 2 points outside
    assert stats["pace_change"] == pytest.approx(-0.05)
    assert stats["pace_multiplier_slow"] == pytest.approx(0.2) and stats["pace_multiplier_fast"] == 0.0
    pace.step(None, {"speed_ratio": 0.99, "failure_rate": 0.1})  # back inside: the multiplier decays
    assert pace.slow == pytest.approx(0.0)
    pace.step(None, {"speed_ratio": 1.06, "failure_rate": 0.1})
    assert pace.slow == 0.0 and pace.fast == pytest.approx(0.3)
    pace.restore([{"pace_multiplier_slow": 0.5, "pace_multiplier_fast": 0.0}])
    assert (pace.slow, pace.fast) == (0.5, 0.0)


def test_the_proportional_term_adds_the_current_violation_to_the_accumulated_multiplier() -> None:
    pace = PaceConstraint(0.03, 10.0, lambda: [], 4, None, kp=20.0)
    pace.base_ratio = 1.0
    stats = pace.step(None, {"speed_ratio": 0.95, "failure_rate": 0.1})  # e_slow = 0.02, e_fast = -0.08
    assert stats["pace_integral_slow"] == pytest.approx(0.2) and stats["pace_integral_fast"] == 0.0
    assert stats["pace_multiplier_slow"] == pytest.approx(0.2 + 20 * 0.02) and stats["pace_multiplier_fast"] == 0.0
    pace.step(None, {"speed_ratio": 1.0, "failure_rate": 0.1})  # inside: e_slow = -0.03
    assert pace.slow_sum == 0.0 and pace.slow == 0.0  # 0.2 - 10 x 0.03 and 0.2 - 20 x 0.03: never below 0
    pace.restore([{"pace_multiplier_slow": 0.9, "pace_multiplier_fast": 0.0, "pace_integral_slow": 0.4,
                   "pace_integral_fast": 0.0}])
    assert (pace.slow, pace.slow_sum) == (0.9, 0.4)


def _plant_swings(kp: float, epochs: int = 70) -> list[float]:
    """A toy policy whose pace, pulled 1 % slower per epoch by its reward, moves by 0.0165 x the net multiplier
    (slow - fast) of two epochs before (the response measured on a model that answers within a few epochs);
    returns the pace change per epoch."""
    pace = PaceConstraint(0.03, 5.0, lambda: [], 4, None, kp=kp)
    pace.base_ratio = 1.0
    change, changes, pushes = 0.0, [], [0.0, 0.0]
    for _ in range(epochs):
        pace.step(None, {"speed_ratio": 1.0 + change, "failure_rate": 0.0})
        changes.append(change)
        pushes.append(pace.slow - pace.fast)
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
    pace.slow = 1.0
    mixed = pace.mix(adv, speeds, 1, mask)
    # agent 0 had no reward advantage (a passing agent): the faster sample now has the higher advantage
    assert mixed[0, 2, 0] > mixed[0, 1, 0] > mixed[0, 0, 0]
    # agent 1's samples all have the same speed: only the reward term, scaled by 1 / (1 + slow)
    assert torch.allclose(mixed[0, :, 1], adv[0, :, 1] / 2)
    pace.slow, pace.fast = 0.0, 1.0  # too fast: the slower sample is preferred
    mixed = pace.mix(adv, speeds, 1, mask)
    assert mixed[0, 0, 0] > mixed[0, 2, 0]


def test_the_pace_drive_is_the_evaluations_speed_ratio_and_repeats_exactly(
        train_scene_list: list[ScenarioTensor]) -> None:
    model = _model()
    pace = PaceConstraint(0.03, 5.0, lambda: train_scene_list, 3, None)
    state = torch.get_rng_state()
    first = pace.drive(model)
    assert torch.equal(torch.get_rng_state(), state)  # the training's random numbers are not consumed
    again = pace.drive(model)  # same weights, same scenes, same seed: the same figures
    assert {k: again[k] for k in ("speed_ratio", "failure_rate")} == {k: first[k] for k in ("speed_ratio",
                                                                                           "failure_rate")}
    assert torch.equal(again["agent_speeds"].isnan(), first["agent_speeds"].isnan())
    assert torch.equal(again["agent_speeds"].nan_to_num(), first["agent_speeds"].nan_to_num())
    torch.manual_seed(0)
    model.options = model.options.model_copy(update={"seed": 0})
    rollout = simulate(model, pace.batch(), SimulationConfig(duration_s=10.0))
    assert first["speed_ratio"] == pytest.approx(SpeedMetric().compute(rollout).values["speed_ratio"])
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
    each = run(pace_tolerance=0.02, pace_multiplier_lr=20.0, pace_per_agent=True)
    assert each[0]["pace_agent_slowdown"] == each[0]["pace_agent_speedup"] == 0.0
    assert max(row["pace_multiplier_slow"] for row in each) > 0
    assert each[-1]["pace_change"] > free[-1]["pace_change"] + 0.02


def test_per_agent_deviations_count_each_agents_slowdown_and_speedup_apart() -> None:
    """One agent 20 % slower and one 20 % faster leave the mean pace where it was but show on both sides; agents
    missing from either drive are left out, and speeds below the floor count as the floor."""
    pace = PaceConstraint(0.03, 10.0, lambda: [], 4, None, per_agent=True)
    nan = float("nan")
    pace.start({"speed_ratio": 1.0, "agent_speeds": torch.tensor([[10.0, 10.0, nan, 0.2]])})
    slowdown, speedup = pace.agent_deviations(torch.tensor([[8.0, 12.0, 5.0, 0.5]]))
    assert slowdown == pytest.approx(-math.log(0.8) / 3) and speedup == pytest.approx(math.log(1.2) / 3)
    stats = pace.step(None, {"speed_ratio": 1.0, "failure_rate": 0.0,
                             "agent_speeds": torch.tensor([[8.0, 12.0, 5.0, 0.5]])})
    assert stats["pace_change"] == 0.0  # the mean pace did not move ...
    assert stats["pace_multiplier_slow"] == pytest.approx(10 * (-math.log(0.8) / 3 - 0.03))  # ... each agent did
    assert stats["pace_multiplier_fast"] == pytest.approx(10 * (math.log(1.2) / 3 - 0.03))


def test_the_per_agent_band_is_counted_above_the_starting_models_own_seed_to_seed_floor() -> None:
    """A drive that differs from the start only as much as the starting model's drive with another seed does
    moves no multiplier; the same deviations without that floor do."""
    nan = float("nan")
    start = {"speed_ratio": 1.0, "agent_speeds": torch.tensor([[10.0, 10.0, 8.0, nan]])}
    again = {"speed_ratio": 1.0, "agent_speeds": torch.tensor([[9.0, 11.0, 8.0, nan]])}
    with_floor = PaceConstraint(0.01, 10.0, lambda: [], 4, None, per_agent=True)
    with_floor.start(start, again)
    assert with_floor.floor == pytest.approx((-math.log(0.9) / 3, math.log(1.1) / 3))
    stats = with_floor.step(None, {**again, "failure_rate": 0.0})
    assert stats["pace_multiplier_slow"] == stats["pace_multiplier_fast"] == 0.0
    without = PaceConstraint(0.01, 10.0, lambda: [], 4, None, per_agent=True)
    without.start(start)
    stats = without.step(None, {**again, "failure_rate": 0.0})
    assert stats["pace_multiplier_slow"] > 0 and stats["pace_multiplier_fast"] > 0


def test_the_per_agent_speed_terms_rank_samples_against_the_starting_models_speed_for_that_agent() -> None:
    pace = PaceConstraint(0.03, 1.0, lambda: [], 4, None, per_agent=True)
    adv = torch.zeros(1, 4, 2)
    speeds = torch.tensor([[4.0, 6.0], [5.0, 6.0], [6.0, 6.0], [7.0, 6.0]])[None]  # (B=1, S=4, A=2)
    reference = torch.tensor([[[6.0, 6.0]]])
    mask = torch.ones_like(adv, dtype=torch.bool)
    assert torch.equal(pace.mix_per_agent(adv, speeds, reference, 1, mask), adv)
    pace.slow = 1.0  # too slow: samples below the reference lose, the more the further below; above it is no gain
    mixed = pace.mix_per_agent(adv, speeds, reference, 1, mask)
    assert mixed[0, 0, 0] < mixed[0, 1, 0] < mixed[0, 2, 0] == mixed[0, 3, 0]
    assert torch.all(mixed[0, :, 1] == 0)  # every sample at the reference: nothing to rank
    pace.slow, pace.fast = 0.0, 1.0  # too fast: samples above the reference lose
    mixed = pace.mix_per_agent(adv, speeds, reference, 1, mask)
    assert mixed[0, 3, 0] < mixed[0, 2, 0] == mixed[0, 1, 0] == mixed[0, 0, 0]


def test_per_agent_pace_needs_the_pace_band_and_per_agent_credit() -> None:
    with pytest.raises(ValueError, match="pace_per_agent"):
        AlignConfig(pace_per_agent=True)
    with pytest.raises(ValueError, match="pace_per_agent"):
        AlignConfig(pace_per_agent=True, pace_tolerance=0.03, credit="scene")
