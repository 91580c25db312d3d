"""The kinematic-histogram term of ``RealismReward`` (a counted density-ratio discriminator) against a closed form,
and the ``--reward-option`` plumbing of ``load_reward``."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficrlhf_sdk.reward.builtin import KINEMATIC_BINS, RealismReward, kinematic_log_ratio
from trafficrlhf_sdk.reward.loading import load_reward
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario import ScenarioTensor

NOW = 10  # current_index: 1 s of history at 0.1 s


def _scenes(accelerations: list[list[float]], speed: float = 8.0) -> ScenarioTensor:
    """``B`` scenes of ``A`` agents on parallel lanes 20 m apart, 5 s at 0.1 s: each drives at ``speed`` m/s
    until now and then accelerates at its ``accelerations[b][a]`` (m/s^2, negative = braking, speeds kept >= 0
    by the caller's choice)."""
    acc = torch.tensor(accelerations, dtype=torch.float64)  # (B, A)
    b, a = acc.shape
    time_s = torch.arange(51, dtype=torch.float64) * 0.1
    after = (time_s - NOW * 0.1).clamp_min(0)
    x = speed * time_s + 0.5 * acc[..., None] * after**2
    v = speed + acc[..., None] * after
    y = 20.0 * torch.arange(a, dtype=torch.float64)[None, :, None].expand(b, a, 51)
    states = torch.stack([x, y, v, torch.zeros_like(x)], -1).float()
    return ScenarioTensor(states=states, valid=torch.ones(b, a, 51, dtype=torch.bool),
                          extent=torch.full((b, a, 2), 2.0), agent_type=torch.ones(b, a, dtype=torch.long),
                          controlled=torch.ones(b, a, dtype=torch.bool), current_index=NOW)


def test_the_log_against_itself_scores_zero() -> None:
    log = _scenes([[0.0, 1.0, -2.0], [0.5, 0.0, 0.0]])
    scores = kinematic_log_ratio(log, log, log.controlled)
    assert torch.equal(scores, torch.zeros_like(scores))


def test_over_produced_accelerations_lose_and_rare_ones_gain_by_the_closed_form() -> None:
    """The log: half the agents cruise, half accelerate at 1.5 m/s^2. The samples: three quarters cruise. Per
    agent the score is a third of log p_log(bin) - log p_sampled(bin) of its longitudinal acceleration (lateral
    acceleration and jerk fall in the same bins for every agent after the first future sample, so their ratios
    cancel except at the onset of the acceleration, which the written-out count below includes)."""
    log = _scenes([[0.0, 1.5, 0.0, 1.5]] * 2)
    sampled = _scenes([[0.0, 0.0, 0.0, 1.5]] * 2)
    scores = kinematic_log_ratio(sampled, log, sampled.controlled).double()
    cruise, accelerating = scores[0, 0].item(), scores[0, 3].item()
    assert cruise < 0 < accelerating
    torch.testing.assert_close(scores[:, :3], torch.full((2, 3), cruise, dtype=torch.float64))

    from trafficrlhf_sdk.metrics.realism import kinematics

    # independent count over the same samples with numpy-free python: bins of every quantity per agent
    def bins_of(scene: ScenarioTensor) -> dict[str, list[list[int]]]:
        q, ok, _ = kinematics(scene, "body")
        future = [k * 5 > NOW for k in range(ok.shape[-1])]
        out: dict[str, list[list[int]]] = {}
        for name, spec in KINEMATIC_BINS.items():
            width = (spec.high - spec.low) / spec.num_bins
            out[name] = [[min(spec.num_bins - 1, max(0, math.floor((float(v) - spec.low) / width)))
                          for k, v in enumerate(q[name][b, a]) if ok[b, a, k] and future[k]]
                         for b in range(scene.num_scenes) for a in range(scene.num_agents)]
        return out

    sim_bins, log_bins = bins_of(sampled), bins_of(log)
    expected = [0.0] * 8
    for name, spec in KINEMATIC_BINS.items():
        def density(per_agent: list[list[int]], n: int = spec.num_bins) -> list[float]:
            counts = [1.0] * n
            for agent in per_agent:
                for index in agent:
                    counts[index] += 1
            return [c / sum(counts) for c in counts]

        p_sim, p_log = density(sim_bins[name]), density(log_bins[name])
        for i, agent in enumerate(sim_bins[name]):
            expected[i] += sum(max(-3.0, min(3.0, math.log(p_log[j]) - math.log(p_sim[j]))) for j in agent)
    counts = [3 * len(agent) for agent in sim_bins["lon_acc"]]
    expected_t = torch.tensor([e / c for e, c in zip(expected, counts)], dtype=torch.float64).reshape(2, 4)
    torch.testing.assert_close(scores, expected_t, atol=1e-6, rtol=0)


def test_agents_outside_the_mask_score_zero_and_do_not_count() -> None:
    log = _scenes([[0.0, 1.5, 0.0, 1.5]])
    sampled = _scenes([[0.0, 0.0, 0.0, 1.5]])
    keep = torch.tensor([[True, False, True, True]])
    scores = kinematic_log_ratio(sampled, log, keep)
    assert scores[0, 1] == 0
    # the excluded cruising agent no longer counts: fewer over-produced cruise samples, a milder penalty
    assert scores[0, 0] > kinematic_log_ratio(sampled, log, sampled.controlled)[0, 0]


@settings(max_examples=25, deadline=None)
@given(weight=st.floats(0.05, 3.0), acc=st.lists(st.floats(-1.5, 2.0), min_size=3, max_size=3))
def test_realism_reward_adds_weight_times_the_ratio(weight: float, acc: list[float]) -> None:
    log = _scenes([[0.0, 1.0, -1.0]])
    sampled = _scenes([acc])
    plain = RealismReward().agent_scores(sampled, logged=log)
    with_term = RealismReward(kinematics_weight=weight).agent_scores(sampled, logged=log)
    ratio = kinematic_log_ratio(sampled, log, sampled.controlled)
    torch.testing.assert_close(with_term - plain, weight * ratio, atol=1e-5, rtol=0)
    assert ratio.abs().max() <= 3.0


def test_builtin_and_reward_options() -> None:
    reward = load_reward("builtin:realism-kinematics")
    assert isinstance(reward, RealismReward) and reward.margins and reward.kinematics_weight == 0.5
    tuned = load_reward("builtin:realism-kinematics", {"kinematics_weight": 1.25, "stall_ratio": 0.4})
    assert tuned.kinematics_weight == 1.25 and tuned.stall_ratio == 0.4 and tuned.margins
    assert load_reward("builtin:failure", {"margins": True}).margins
    with pytest.raises(TrafficRLHFError, match="kinematics_wieght"):
        load_reward("builtin:realism-kinematics", {"kinematics_wieght": 1.0})
    with pytest.raises(TrafficRLHFError, match="kinematics_weight"):
        RealismReward(kinematics_weight=-0.1)
    with pytest.raises(TrafficRLHFError, match="built-in rewards only"):
        load_reward("some/reward_model_folder", {"beta": 1.0})


def test_num_samples_keeps_the_first_future_samples_only() -> None:
    """With one sample scored, only the first 0.5 s after now counts: agents that differ from the log only later
    (a braking that starts 1 s after now) score like the log."""
    log = _scenes([[0.0, 1.5, 0.0, 1.5]])
    late = log.states.clone()
    time_s = torch.arange(51, dtype=torch.float64) * 0.1
    shift = (time_s - 2.0).clamp_min(0)  # agent 0 starts braking at 2 s, 1 s after now
    late[0, 0, :, 0] -= (0.5 * 2.0 * shift**2).float()
    sampled = log.replace_unchecked(states=late)
    first_only = kinematic_log_ratio(sampled, log, log.controlled, num_samples=1)
    every = kinematic_log_ratio(sampled, log, log.controlled)
    assert torch.equal(first_only, torch.zeros_like(first_only))
    assert every[0, 0] != 0
    with pytest.raises(TrafficRLHFError, match="kinematics_samples"):
        RealismReward(kinematics_weight=0.5, kinematics_samples=0)


def test_every_builtin_reward_builds_and_is_listed_by_the_plugins_command() -> None:
    from click.testing import CliRunner

    from trafficrlhf_sdk.cli import get_cli
    from trafficrlhf_sdk.plugins import registry
    from trafficrlhf_sdk.reward import builtin
    from trafficrlhf_sdk.reward.oracle import JudgmentReward

    names = registry("rewards").names()
    assert {"failure", "failure-margins", "realism-margins", "random", "judgment"} <= set(names)
    for name in names:
        reward = load_reward(f"builtin:{name}")
        assert isinstance(reward, (builtin.FailureReward, builtin.RandomReward, JudgmentReward))
        assert callable(reward.step_rewards)
    assert load_reward("builtin:collision").offroad is False
    assert load_reward("builtin:realism-kinematics").kinematics_weight == 0.5
    listing = CliRunner().invoke(get_cli(), ["plugins", "--json"]).output
    assert all(name in listing for name in names)
    with pytest.raises(TrafficRLHFError, match="builtin:realism-margins"):
        load_reward("builtin:no-such-reward")
