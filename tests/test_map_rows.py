"""Scenes that share raster rows (``MapRaster.rows``) read exactly what their dense copies read."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficrlhf_sdk.errors import ScenarioValidationError
from trafficrlhf_sdk.models.features import map_crops
from trafficrlhf_sdk.reward.features import FeatureSpec, compute_step_inputs
from trafficrlhf_sdk.scenario.map import MapRaster, crop_map
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor, scenario_from_bytes, scenario_to_bytes
from trafficrlhf_sdk.testing.strategies import scenario_tensors

SETTINGS = settings(max_examples=40, deadline=None)


def _picks(b: int) -> st.SearchStrategy[list[int]]:
    return st.lists(st.integers(0, b - 1), min_size=1, max_size=6)


def _dense(scenario: ScenarioTensor) -> ScenarioTensor:
    assert scenario.map is not None
    return scenario.replace_unchecked(map=scenario.map.dense())


@SETTINGS
@given(data=st.data(), scenario=scenario_tensors(max_scenes=3, max_agents=4, max_steps=6))
def test_selected_scenes_read_what_their_dense_copies_read(data, scenario):
    picks = data.draw(_picks(scenario.num_scenes), label="picks")
    shared = scenario[picks]
    dense = _dense(shared)
    assert shared.map.raster is scenario.map.raster and dense.map.rows is None
    xy = shared.xy.double()
    assert torch.equal(shared.map.lookup(xy), dense.map.lookup(xy))
    assert torch.equal(shared.map.layer("lane_divider"), dense.map.layer("lane_divider"))
    scene = torch.arange(shared.num_scenes).repeat_interleave(3)
    points = xy[:, 0, :3].reshape(-1, 2)
    if points.shape[0] == scene.shape[0]:
        assert torch.equal(shared.map.lookup_points(scene, points), dense.map.lookup_points(scene, points))
    assert torch.equal(map_crops(shared, size_px=6), map_crops(dense, size_px=6))
    for b in range(shared.num_scenes):
        assert torch.equal(shared.map.scene_raster(b), dense.map.raster[b])


@SETTINGS
@given(data=st.data(), scenario=scenario_tensors(max_scenes=3, max_agents=4, max_steps=6))
def test_repeat_index_and_concat_compose(data, scenario):
    copies = data.draw(st.integers(1, 4), label="copies")
    repeated = scenario.repeat_scenes(copies)
    picks = data.draw(_picks(repeated.num_scenes), label="picks")
    twice = repeated[picks]
    expected = scenario.map.raster[torch.arange(scenario.num_scenes).repeat_interleave(copies)[picks]]
    assert torch.equal(twice.map.dense().raster, expected)
    joined = ScenarioTensor.concat([twice, scenario, repeated])
    reference = ScenarioTensor.concat([_dense(twice), scenario, _dense(repeated)])
    assert torch.equal(joined.map.dense().raster, reference.map.raster)
    assert torch.equal(joined.map.world_to_pixel, reference.map.world_to_pixel)
    # concat keeps each shared row once: at most the distinct rows of each part, never one per scene
    assert joined.map.raster.shape[0] <= len(set(picks)) + 2 * scenario.num_scenes


@settings(max_examples=15, deadline=None)
@given(scenario=scenario_tensors(max_scenes=2, max_agents=3, max_steps=8, min_steps=8))
def test_reward_features_and_files_see_the_same_map(scenario):
    shared = scenario.repeat_scenes(3)
    dense = _dense(shared)
    spec = FeatureSpec()
    a, b = compute_step_inputs(shared, spec), compute_step_inputs(dense, spec)
    for name in a.__dataclass_fields__:
        left, right = getattr(a, name), getattr(b, name)
        if isinstance(left, torch.Tensor):
            assert torch.equal(left, right), name
    loaded = scenario_from_bytes(scenario_to_bytes(shared))
    assert loaded.map.rows is None and torch.equal(loaded.map.raster, dense.map.raster)
    one = shared[-1]
    cropped = crop_map(one.map, one.xy[0, :, 0].double(), 2.0)
    assert cropped.rows is None and cropped.num_scenes == 1


def test_bad_rows_are_refused_with_the_argument_named():
    raster = torch.zeros(2, 3, 4, 4, dtype=torch.uint8)
    w2p = torch.eye(3).expand(3, 3, 3).clone()
    with pytest.raises(ScenarioValidationError, match=r"`map\.rows` must index the 2 raster rows"):
        MapRaster(raster=raster, world_to_pixel=w2p, rows=torch.tensor([0, 2, 1]))
    with pytest.raises(ScenarioValidationError, match=r"`map\.rows` must be an int64"):
        MapRaster(raster=raster, world_to_pixel=w2p, rows=torch.tensor([0.0, 1.0, 1.0]))
    with pytest.raises(ScenarioValidationError, match=r"world_to_pixel` must have shape \(3, 3, 3\)"):
        MapRaster(raster=raster, world_to_pixel=w2p[:2], rows=torch.tensor([0, 1, 1]))


@SETTINGS
@given(data=st.data(), scenario=scenario_tensors(max_scenes=3, max_agents=4, max_steps=6))
def test_crops_of_selected_agents_equal_those_of_every_slot(data, scenario):
    picks = data.draw(_picks(scenario.num_scenes), label="picks")
    shared = scenario[picks]  # shared raster rows as well as dense ones
    for view in (shared, _dense(shared)):
        mask = torch.tensor(data.draw(st.lists(st.booleans(), min_size=view.num_scenes * view.num_agents,
                                               max_size=view.num_scenes * view.num_agents), label="mask"))
        mask = mask.reshape(view.num_scenes, view.num_agents)
        full = map_crops(view, size_px=6, resolution_m=0.7)
        part = map_crops(view, size_px=6, resolution_m=0.7, agents=mask)
        assert torch.equal(part[mask], full[mask])
        assert not part[~mask].any()
