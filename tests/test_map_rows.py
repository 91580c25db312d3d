"""Map rasters at their own sizes, and scenes that share raster rows (``MapRaster.rows``): each reads exactly
what its own image (or its dense copy) holds."""

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
    assert shared.map.pixels is scenario.map.pixels and dense.map.rows is None
    xy = shared.xy.double()
    assert torch.equal(shared.map.lookup(xy), dense.map.lookup(xy))
    assert torch.equal(shared.map.layer("lane_divider"), dense.map.layer("lane_divider"))
    scene = torch.arange(shared.num_scenes).repeat_interleave(3)
    points = xy[:, 0, :3].reshape(-1, 2)
    if points.shape[0] == scene.shape[0]:
        assert torch.equal(shared.map.lookup_points(scene, points), dense.map.lookup_points(scene, points))
    assert torch.equal(map_crops(shared, size_px=6), map_crops(dense, size_px=6))
    for b in range(shared.num_scenes):
        assert torch.equal(shared.map.scene_raster(b), dense.map.scene_raster(b))


@SETTINGS
@given(data=st.data(), scenario=scenario_tensors(max_scenes=3, max_agents=4, max_steps=6))
def test_repeat_index_and_concat_compose(data, scenario):
    copies = data.draw(st.integers(1, 4), label="copies")
    repeated = scenario.repeat_scenes(copies)
    picks = data.draw(_picks(repeated.num_scenes), label="picks")
    twice = repeated[picks]
    source = torch.arange(scenario.num_scenes).repeat_interleave(copies)[picks]
    for b, original in enumerate(source.tolist()):
        assert torch.equal(twice.map.scene_raster(b), scenario.map.scene_raster(original))
    joined = ScenarioTensor.concat([twice, scenario, repeated])
    reference = ScenarioTensor.concat([_dense(twice), scenario, _dense(repeated)])
    assert torch.equal(joined.map.padded(), reference.map.padded())
    assert torch.equal(joined.map.scene_sizes(), reference.map.scene_sizes())
    assert torch.equal(joined.map.world_to_pixel, reference.map.world_to_pixel)
    # concat keeps each shared row once: at most the distinct rows of each part, never one per scene
    assert joined.map.num_rows <= len(set(picks)) + 2 * scenario.num_scenes


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
    assert loaded.map.rows is None and torch.equal(loaded.map.padded(), dense.map.padded())
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


@SETTINGS
@given(data=st.data(), scenario=scenario_tensors(max_scenes=3, max_agents=4, max_steps=6))
def test_every_pixel_read_is_its_own_scenes_image(data, scenario):
    """``read`` and ``lookup`` against plain indexing of each scene's own image (0 outside it), scene by scene."""
    scene_map = scenario.map
    picks = data.draw(_picks(scenario.num_scenes), label="picks")
    shared = ScenarioTensor.concat([scenario[picks], scenario]).map
    for m in (scene_map, shared):
        n = 20
        scene = torch.tensor(data.draw(st.lists(st.integers(0, m.num_scenes - 1), min_size=n, max_size=n)))
        i = torch.tensor(data.draw(st.lists(st.integers(-2, 10), min_size=n, max_size=n)))
        j = torch.tensor(data.draw(st.lists(st.integers(-2, 10), min_size=n, max_size=n)))
        values = m.read(scene, i, j)  # (C, n)
        for k in range(n):
            image = m.scene_raster(int(scene[k]))
            inside = 0 <= int(i[k]) < image.shape[1] and 0 <= int(j[k]) < image.shape[2]
            expected = image[:, int(i[k]), int(j[k])] if inside else torch.zeros(len(m.layers), dtype=torch.uint8)
            assert torch.equal(values[:, k], expected)
            assert bool(m.inside(scene[k], i[k], j[k])) == inside
        assert torch.equal(m.read(scene, i, j, [2, 0]), values[[2, 0]])
        assert torch.equal(m.read(scene, i, j, [1]), values[[1]])
    # a concatenation holds each scene's pixels once, at its own size: no padding
    assert shared.pixels.shape[1] <= int((scene_map.sizes[:, 0] * scene_map.sizes[:, 1]).sum()) * 2


def test_rasters_of_different_sizes_are_packed_without_padding():
    small = MapRaster(raster=torch.ones(1, 3, 2, 3, dtype=torch.uint8), world_to_pixel=torch.eye(3)[None])
    large = MapRaster(raster=torch.zeros(1, 3, 40, 50, dtype=torch.uint8), world_to_pixel=torch.eye(3)[None])
    both = MapRaster.concat([small, large])
    assert both.pixels.shape == (3, 2 * 3 + 40 * 50) and both.sizes.tolist() == [[2, 3], [40, 50]]
    # a point beyond the small map's own 2 x 3 pixels is off its layers, as one outside any raster
    xy = torch.tensor([[[1.5, 2.5], [1.5, 3.5]], [[1.5, 2.5], [39.5, 49.5]]], dtype=torch.float64)
    assert both.lookup(xy).tolist() == [[True, False], [False, False]]
    assert both.padded().shape == (2, 3, 40, 50) and int(both.padded()[0].sum()) == 3 * 2 * 3
    # a zero-padded batch with each row's size gives the same packed map
    again = MapRaster(raster=both.padded(), sizes=both.sizes, world_to_pixel=both.world_to_pixel)
    assert torch.equal(again.pixels, both.pixels)
    with pytest.raises(ScenarioValidationError, match=r"`map\.sizes` must lie between 1 and the raster's \(40, 50\)"):
        MapRaster(raster=both.padded(), sizes=torch.tensor([[2, 3], [41, 50]]), world_to_pixel=both.world_to_pixel)
    with pytest.raises(ScenarioValidationError, match=r"`map\.pixels` holds 2006 pixels per layer"):
        MapRaster(pixels=both.pixels, sizes=torch.tensor([[2, 3], [40, 49]]), world_to_pixel=both.world_to_pixel)


def test_an_empty_selection_concatenates_and_copies_to_nothing():
    scene_map = MapRaster(raster=torch.ones(2, 3, 4, 5, dtype=torch.uint8), world_to_pixel=torch.eye(3).expand(2, 3, 3))
    empty = scene_map.index(torch.zeros(2, dtype=torch.bool))
    assert empty.num_scenes == 0 and empty.dense().pixels.shape == (3, 0)
    both = MapRaster.concat([empty, scene_map])
    assert both.num_scenes == 2 and torch.equal(both.padded(), scene_map.padded())
