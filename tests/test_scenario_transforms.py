"""Scene transforms: mirrored scenes (``mirror_scenario``) keep the geometry the metrics see and flip turns;
perturbed histories (``perturb_history``) move each agent's past rigidly and leave the future alone."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings

from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_per_step
from trafficrlhf_sdk.scenario import MIRROR_SUFFIX, ScenarioTensor, mirror_scenario, perturb_history
from trafficrlhf_sdk.testing.strategies import feasible_trajectories, scenario_tensors


@settings(deadline=None)
@given(scenario_tensors(max_agents=4, with_map=None))
def test_mirroring_twice_gives_the_scenario_back(scenario: ScenarioTensor) -> None:
    mirrored = mirror_scenario(scenario)
    back = mirror_scenario(mirrored)
    assert torch.equal(back.states, scenario.states) and torch.equal(back.valid, scenario.valid)
    assert back.scene_ids == scenario.scene_ids
    assert all(s.endswith(MIRROR_SUFFIX) for s in mirrored.scene_ids)
    valid = scenario.valid
    assert torch.equal(mirrored.states[..., 1][valid], -scenario.states[..., 1][valid])
    assert torch.equal(mirrored.states[..., [0, 2]], scenario.states[..., [0, 2]])
    yaw = mirrored.states[..., 3]
    assert bool(((yaw >= -torch.pi) & (yaw < torch.pi)).all())  # still wrapped, validated on construction
    if scenario.map is not None:
        assert torch.equal(back.map.world_to_pixel, scenario.map.world_to_pixel)
        assert mirrored.map.pixels is scenario.map.pixels  # the raster is shared, only the transform changes


@settings(deadline=None)
@given(scenario_tensors(max_agents=4, with_map=True))
def test_a_mirrored_point_reads_the_pixel_its_original_reads(scenario: ScenarioTensor) -> None:
    assert torch.equal(offroad_per_step(mirror_scenario(scenario)), offroad_per_step(scenario))
    assert torch.equal(mirror_scenario(scenario).map.to_pixel(scenario.xy * torch.tensor([1.0, -1.0])),
                       scenario.map.to_pixel(scenario.xy))


@settings(max_examples=50, deadline=None)
@given(feasible_trajectories(max_agents=4, return_actions=True))
def test_mirrored_turns_change_sign_and_speeds_do_not(drawn: tuple[ScenarioTensor, torch.Tensor]) -> None:
    scenario, _ = drawn
    original, mirrored = scenario.actions(), mirror_scenario(scenario).actions()
    torch.testing.assert_close(mirrored[..., 0], original[..., 0])
    torch.testing.assert_close(mirrored[..., 1], -original[..., 1], atol=1e-4, rtol=0)


def test_recorded_scenes_keep_their_collisions_and_off_road_steps_when_mirrored(val_scenes: ScenarioTensor) -> None:
    # the logged agents rarely fail, so push them around by a few metres to get failures of both kinds
    noise = torch.randn(val_scenes.xy.shape, generator=torch.Generator().manual_seed(0)) * 3.0
    states = val_scenes.states.clone()
    states[..., :2] += noise * val_scenes.valid[..., None]
    shaken = val_scenes.replace_unchecked(states=states)
    mirrored = mirror_scenario(shaken)
    collisions, offroad = collisions_per_step(shaken), offroad_per_step(shaken)
    assert collisions.sum() > 10 and offroad.sum() > 10  # not vacuous
    assert torch.equal(collisions_per_step(mirrored), collisions)
    assert torch.equal(offroad_per_step(mirrored), offroad)
    # reflection flips the sign of the signed area swept by each agent's path (its turning direction)
    xy, m_xy = shaken.xy, mirrored.xy
    cross = xy[..., :-1, 0] * xy[..., 1:, 1] - xy[..., :-1, 1] * xy[..., 1:, 0]
    m_cross = m_xy[..., :-1, 0] * m_xy[..., 1:, 1] - m_xy[..., :-1, 1] * m_xy[..., 1:, 0]
    torch.testing.assert_close(m_cross, -cross)


def _random_moves(scenario: ScenarioTensor, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    shape = scenario.controlled.shape
    return (2 * torch.rand(shape, generator=gen) - 1) * 2.0, (2 * torch.rand(shape, generator=gen) - 1) * 0.5


@settings(max_examples=60, deadline=None)
@given(scenario_tensors(max_agents=4, with_map=None))
def test_a_perturbed_history_is_a_rigid_move_that_ends_beside_the_logged_pose(scenario: ScenarioTensor) -> None:
    lateral, turn = _random_moves(scenario, 0)
    moved = perturb_history(scenario, lateral, turn)
    now, valid = scenario.current_index, scenario.valid
    past = valid[:, :, : now + 1]
    # the future, speeds, validity and agents not valid now are untouched
    assert torch.equal(moved.states[:, :, now + 1 :], scenario.states[:, :, now + 1 :])
    assert torch.equal(moved.states[..., 2], scenario.states[..., 2]) and torch.equal(moved.valid, valid)
    still = ~valid[:, :, now]
    assert torch.equal(moved.states[still], scenario.states[still])
    # pairwise distances within each agent's history are kept (a rigid move)
    d_before = torch.cdist(scenario.xy[:, :, : now + 1].double(), scenario.xy[:, :, : now + 1].double())
    d_after = torch.cdist(moved.xy[:, :, : now + 1].double(), moved.xy[:, :, : now + 1].double())
    pair = past[..., :, None] & past[..., None, :]
    torch.testing.assert_close(d_after[pair], d_before[pair], atol=2e-3, rtol=1e-5)
    # the pose now moved by `lateral` across the heading now, and turned by `turn`
    on = valid[:, :, now]
    yaw_now = scenario.yaw[:, :, now]
    shift = moved.xy[:, :, now] - scenario.xy[:, :, now]
    left = torch.stack([-torch.sin(yaw_now), torch.cos(yaw_now)], -1)
    torch.testing.assert_close((shift * left).sum(-1)[on], lateral[on], atol=2e-3, rtol=0)
    torch.testing.assert_close(torch.linalg.vector_norm(shift, dim=-1)[on], lateral.abs()[on], atol=2e-3, rtol=0)
    dyaw = torch.remainder(moved.yaw[:, :, : now + 1] - scenario.yaw[:, :, : now + 1] - turn[..., None] + torch.pi,
                           2 * torch.pi) - torch.pi
    assert not bool((dyaw[past & on[..., None]].abs() > 1e-4).any())


@settings(max_examples=30, deadline=None)
@given(scenario_tensors(max_agents=4, with_map=None))
def test_a_zero_perturbation_leaves_the_scenario_as_logged(scenario: ScenarioTensor) -> None:
    zeros = torch.zeros(scenario.controlled.shape)
    moved = perturb_history(scenario, zeros, zeros)
    assert torch.equal(moved.states[..., :3], scenario.states[..., :3])  # positions exact, even far out
    torch.testing.assert_close(moved.states[..., 3], scenario.states[..., 3], atol=1e-6, rtol=0)


def test_a_perturbation_of_the_wrong_shape_is_refused(val_scenes: ScenarioTensor) -> None:
    with pytest.raises(ValueError, match="`turn` has shape"):
        perturb_history(val_scenes, torch.zeros(val_scenes.controlled.shape), torch.zeros(3))
