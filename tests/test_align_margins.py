"""The near-failure costs of ``FailureReward(margins=True)`` against shapely and a per-point pixel lookup."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from trafficrlhf_sdk.reward.builtin import FailureReward, RealismReward, time_to_collision
from trafficrlhf_sdk.reward.loading import load_reward
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario import ScenarioTensor

pytest.importorskip("shapely.geometry")
from trafficrlhf_sdk.testing.reference_metrics import reference_collisions, reference_offroad


@pytest.fixture(scope="module")
def jittered(nuscenes_source) -> ScenarioTensor:  # type: ignore[no-untyped-def]
    """Six real train scenes, 3 s, every position moved by up to ~1.5 m: plenty of grazed road edges, near
    misses and a few outright failures."""
    batch = nuscenes_source.load_batch("train", 6).time_slice(0, 31).replace_unchecked(current_index=10)
    gen = torch.Generator().manual_seed(3)
    states = batch.states.clone()
    states[..., :2] += 1.5 * torch.randn(states[..., :2].shape, generator=gen)
    return batch.replace_unchecked(states=states * batch.valid[..., None])


def _reference_costs(scene: ScenarioTensor, corner_weight: float, near_weight: float,
                     buffer_m: tuple[float, float]) -> np.ndarray:
    """Per agent-step cost with shapely boxes and one pixel lookup per corner (numpy, written out)."""
    xy, yaw = scene.xy.double().numpy(), scene.yaw.double().numpy()
    extent, valid = scene.extent.double().numpy(), scene.valid.numpy()
    failed = reference_collisions(xy, yaw, extent, valid) | reference_offroad(scene.map, xy, valid)
    grown = extent + 2 * np.asarray(buffer_m)
    near = reference_collisions(xy, yaw, grown, valid)
    corners_off = np.zeros(valid.shape)
    for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        dx, dy = sx * extent[:, :, None, 0] / 2, sy * extent[:, :, None, 1] / 2
        corner = np.stack([xy[..., 0] + dx * np.cos(yaw) - dy * np.sin(yaw),
                           xy[..., 1] + dx * np.sin(yaw) + dy * np.cos(yaw)], -1)
        corners_off += reference_offroad(scene.map, corner, valid) / 4
    soft = np.minimum(1.0, near_weight * near + corner_weight * corners_off)
    return np.where(failed, 1.0, soft) * valid


def test_margin_costs_match_shapely_and_pixel_lookup(jittered: ScenarioTensor) -> None:
    reward = FailureReward(margins=True, corner_weight=0.4, near_weight=0.3, near_buffer_m=(0.6, 0.3))
    cost, mask = reward._failures(jittered)
    expected = _reference_costs(jittered, 0.4, 0.3, (0.6, 0.3)) * mask.numpy()
    assert ((expected > 0) & (expected < 1)).sum() > 20, "the fixture should contain near failures"
    np.testing.assert_allclose(cost.numpy(), expected, atol=1e-6)


def test_margins_only_lower_rewards_and_keep_failures_at_minus_one(jittered: ScenarioTensor) -> None:
    plain, soft = FailureReward(), FailureReward(margins=True)
    plain_scores, soft_scores = plain.agent_scores(jittered), soft.agent_scores(jittered)
    assert (soft_scores <= plain_scores + 1e-7).all()
    assert (soft_scores < plain_scores - 1e-3).any()
    assert (soft.step_rewards(jittered) <= plain.step_rewards(jittered) + 1e-7).all()
    # an agent failing at every future step scores exactly -1 with or without margins
    plain_cost, mask = plain._failures(jittered)
    soft_cost, _ = soft._failures(jittered)
    assert torch.equal(soft_cost[plain_cost == 1], torch.ones(int((plain_cost == 1).sum())))
    assert set(plain_cost[mask].unique().tolist()) <= {0.0, 1.0}


def test_the_log_rarely_pays_a_margin_cost(nuscenes_source) -> None:  # type: ignore[no-untyped-def]
    log = nuscenes_source.load_batch("train", 6)
    cost, mask = FailureReward(margins=True)._failures(log)
    mean_cost = float(cost[mask].mean())
    assert 0 < mean_cost < 0.05, f"logged driving costs {mean_cost:.4f} per agent-step"


def test_realism_reward_with_margins_adds_the_same_costs(jittered: ScenarioTensor) -> None:
    plain, soft = RealismReward(), RealismReward(margins=True)
    extra = plain.agent_scores(jittered, logged=jittered) - soft.agent_scores(jittered, logged=jittered)
    expected = FailureReward().agent_scores(jittered) - FailureReward(margins=True).agent_scores(jittered)
    torch.testing.assert_close(extra, expected)


def _with_future_speed(scene: ScenarioTensor, factor: float) -> ScenarioTensor:
    states = scene.states.clone()
    states[:, :, scene.current_index + 1:, 2] *= factor
    return scene.replace_unchecked(states=states)


def _reference_speed_term(scene: ScenarioTensor, logged: ScenarioTensor, mask: torch.Tensor, tolerance: float,
                          floor: float) -> np.ndarray:
    """Per agent mean of min(1, relu(|v - v_log| / max(v_log, floor) - tolerance)), numpy, written out."""
    now = scene.current_index
    v = np.abs(scene.states[:, :, now + 1:, 2].double().numpy())
    v_log = np.abs(logged.states[:, :, now + 1:, 2].double().numpy())
    both = mask[:, :, now + 1:].numpy() & logged.valid[:, :, now + 1:].numpy()
    err = np.clip(np.abs(v - v_log) / np.maximum(v_log, floor) - tolerance, 0, 1) * both
    return err.sum(-1) / np.maximum(both.sum(-1), 1)


@pytest.mark.parametrize("factor", [0.5, 1.5, 0.9])
def test_speed_mismatch_term_matches_a_written_out_reference(jittered: ScenarioTensor, factor: float) -> None:
    scene = _with_future_speed(jittered, factor)
    without, with_speed = RealismReward(), RealismReward(speed_weight=2.0, speed_tolerance=0.2, speed_floor=2.5)
    added = without.agent_scores(scene, logged=jittered) - with_speed.agent_scores(scene, logged=jittered)
    _, mask = without._failures(scene)
    expected = 2.0 * _reference_speed_term(scene, jittered, mask, 0.2, 2.5)
    np.testing.assert_allclose(added.double().numpy(), expected, atol=1e-5)
    assert (added > 0).any() == (abs(factor - 1) > 0.2)


def test_speed_mismatch_is_symmetric_and_free_for_the_log(jittered: ScenarioTensor) -> None:
    reward = RealismReward(speed_weight=1.0, speed_floor=1e-3)
    base = RealismReward()
    assert torch.equal(reward.agent_scores(jittered, logged=jittered), base.agent_scores(jittered, logged=jittered))
    slow, fast = _with_future_speed(jittered, 0.5), _with_future_speed(jittered, 1.5)
    slow_cost = base.agent_scores(slow, logged=jittered) - reward.agent_scores(slow, logged=jittered)
    fast_cost = base.agent_scores(fast, logged=jittered) - reward.agent_scores(fast, logged=jittered)
    torch.testing.assert_close(slow_cost, fast_cost)  # 50 % too slow costs what 50 % too fast costs
    assert float(slow_cost.max()) > 0.2


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"speed_weight": -1.0}, "speed_weight"),
    ({"speed_tolerance": -0.1}, "speed_tolerance"),
    ({"speed_floor": 0.0}, "speed_floor"),
])
def test_bad_speed_settings_name_the_argument(kwargs: dict, match: str) -> None:
    with pytest.raises(TrafficRLHFError, match=match):
        RealismReward(**kwargs)


def test_realism_reward_takes_the_margin_settings(jittered: ScenarioTensor) -> None:
    settings = {"corner_weight": 0.4, "near_weight": 0.3, "near_buffer_m": [0.6, 0.3]}  # a list, as JSON gives it
    realism = load_reward("builtin:realism-margins", settings)
    cost, _ = realism._failures(jittered)
    expected, _ = FailureReward(margins=True, corner_weight=0.4, near_weight=0.3, near_buffer_m=(0.6, 0.3))._failures(
        jittered)
    assert torch.equal(cost, expected) and realism.near_buffer_m == (0.6, 0.3)
    assert not torch.equal(cost, RealismReward(margins=True)._failures(jittered)[0])
    with pytest.raises(TrafficRLHFError, match="near_weight"):
        RealismReward(margins=True, near_weight=2.0)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"corner_weight": 1.5}, "corner_weight"),
    ({"near_weight": -0.1}, "near_weight"),
    ({"near_buffer_m": (0.5, -1.0)}, "near_buffer_m"),
    ({"ttc_weight": 1.5}, "ttc_weight"),
    ({"ttc_threshold_s": 0.0}, "ttc_threshold_s"),
])
def test_bad_margin_settings_name_the_argument(kwargs: dict, match: str) -> None:
    with pytest.raises(TrafficRLHFError, match=match):
        FailureReward(margins=True, **kwargs)
    with pytest.raises(TrafficRLHFError, match="ttc_weight"):
        FailureReward(ttc_weight=0.5)  # a margin term without margins


def test_time_to_collision_matches_a_pairwise_loop(jittered: ScenarioTensor) -> None:
    """Against a plain loop over scenes, agents, others and steps (in the path: ahead along the heading and within
    half of both widths plus 0.5 m to the side; bumper-to-bumper gap over the closing speed), on jittered real
    scenes with random speeds, and one follower by hand: 10 m/s, 5 m behind a 5 m/s car -> 1 s."""
    gen = torch.Generator().manual_seed(5)
    states = jittered.states.clone()
    states[..., 2] = torch.rand(states[..., 2].shape, generator=gen) * 15
    scene = jittered.replace_unchecked(states=states).time_slice(0, 6)
    got = time_to_collision(scene)
    xy, yaw, v, ext, ok = scene.xy, scene.yaw, scene.states[..., 2], scene.extent, scene.valid
    expected = torch.full(got.shape, math.inf)
    for b, i, j, t in np.ndindex(*xy.shape[:2], xy.shape[1], xy.shape[2]):
        if i == j or not (ok[b, i, t] and ok[b, j, t]):
            continue
        c, s_ = math.cos(yaw[b, i, t]), math.sin(yaw[b, i, t])
        dx, dy = (xy[b, j, t] - xy[b, i, t]).tolist()
        along, across = dx * c + dy * s_, abs(-dx * s_ + dy * c)
        closing = float(v[b, i, t]) - float(v[b, j, t]) * math.cos(yaw[b, j, t] - yaw[b, i, t])
        if along <= 0 or across > (ext[b, i, 1] + ext[b, j, 1]) / 2 + 0.5 or closing <= 0:
            continue
        gap = max(along - float(ext[b, i, 0] + ext[b, j, 0]) / 2, 0.0)
        expected[b, i, t] = min(expected[b, i, t].item(), gap / closing)
    finite = torch.isfinite(expected)
    assert finite.sum() > 5 and torch.equal(finite, torch.isfinite(got))
    torch.testing.assert_close(got[finite], expected[finite], atol=1e-4, rtol=1e-4)

    lane = torch.tensor([[[[0.0, 0.0, 10.0, 0.0]], [[9.5, 0.0, 5.0, 0.0]], [[9.5, 3.5, 0.0, 0.0]]]])
    pair = ScenarioTensor(states=lane, valid=torch.ones(1, 3, 1, dtype=torch.bool),
                          extent=torch.tensor([[[4.5, 1.9], [4.5, 1.9], [4.5, 1.9]]]),
                          agent_type=torch.ones(1, 3, dtype=torch.long), controlled=torch.ones(1, 3, dtype=torch.bool))
    ttc = time_to_collision(pair)[0, :, 0]
    assert math.isclose(float(ttc[0]), 1.0, rel_tol=1e-5) and torch.isinf(ttc[1:]).all()
    cost, _ = FailureReward(margins=True, collision=True, offroad=False, near_weight=0.0, corner_weight=0.0,
                            ttc_weight=0.6, ttc_threshold_s=1.5)._failures(pair)
    assert math.isclose(float(cost[0, 0, 0]), 0.6 / 3, rel_tol=1e-5) and float(cost[0, 1:].sum()) == 0


def test_builtin_reward_names() -> None:
    assert load_reward("builtin:failure-margins").margins
    realism = load_reward("builtin:realism-margins")
    assert isinstance(realism, RealismReward) and realism.margins and realism.speed_weight == 0
    speed = load_reward("builtin:realism-speed")
    assert isinstance(speed, RealismReward) and speed.margins and speed.speed_weight == 1.0
    assert not load_reward("builtin:failure").margins
    with pytest.raises(TrafficRLHFError, match="builtin:realism-margins"):
        load_reward("builtin:nope")
    assert math.isclose(load_reward("builtin:failure-margins").corner_weight, 0.5)
