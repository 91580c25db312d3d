"""ScenarioTensor: validation, views, batch operations, safetensors IO and the inverse dynamics."""

from __future__ import annotations

import math
import os
import tempfile

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from safetensors.torch import save_file

from trafficrlhf_sdk.simulation.dynamics import unicycle_rollout, wrap_angle
from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, ScenarioValidationError
from trafficrlhf_sdk.scenario import DEFAULT_LAYERS, MapRaster, ScenarioTensor
from trafficrlhf_sdk.testing.strategies import feasible_trajectories, scenario_tensors

FAST = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def make_map(b: int = 2, h: int = 4, w: int = 5, layers: tuple[str, ...] = DEFAULT_LAYERS) -> MapRaster:
    raster = (torch.arange(b * len(layers) * h * w).reshape(b, len(layers), h, w) % 2).to(torch.uint8)
    return MapRaster(raster=raster, world_to_pixel=torch.eye(3).expand(b, 3, 3).clone(), layers=layers)


def make_fields(b: int = 2, a: int = 3, t: int = 6) -> dict:
    """Keyword arguments of a small valid scenario with distinct values everywhere."""
    states = torch.arange(b * a * t * 4, dtype=torch.float32).reshape(b, a, t, 4) / 100
    valid = torch.ones(b, a, t, dtype=torch.bool)
    if b >= 2 and a >= 3 and t >= 3:
        valid[0, 1, 2] = False  # a hole
        valid[1, 2] = False  # a padding agent
    states = states * valid[..., None]
    return dict(
        states=states,
        valid=valid,
        extent=torch.full((b, a, 2), 2.0),
        agent_type=torch.ones(b, a, dtype=torch.int64),
        controlled=valid.any(-1),
        dt=0.1,
        current_index=2,
        map=make_map(b),
        origin=torch.arange(b * 2, dtype=torch.float64).reshape(b, 2) + 0.5,
        scene_ids=tuple(f"s{i}" for i in range(b)),
        agent_ids=tuple(tuple(f"s{i}a{j}" for j in range(a)) for i in range(b)),
        source="unit",
        extras={"k": 1},
    )


def make_scenario(b: int = 2, a: int = 3, t: int = 6, **changes) -> ScenarioTensor:
    fields = make_fields(b, a, t)
    fields.update(changes)
    return ScenarioTensor(**fields)


# ------------------------------------------------------------------ validation
def test_valid_scenario_sizes():
    s = make_scenario()
    assert (s.num_scenes, s.num_agents, s.num_steps, len(s)) == (2, 3, 6, 2)
    assert s.xy.shape == (2, 3, 6, 2) and s.speed.shape == (2, 3, 6) and s.yaw.shape == (2, 3, 6)


def test_nan_where_valid_names_states():
    fields = make_fields()
    fields["states"][0, 0, 1, 3] = float("nan")
    with pytest.raises(ScenarioValidationError, match="`states`") as info:
        ScenarioTensor(**fields)
    assert "yaw" in str(info.value) and "scene 0, agent 0, step 1" in str(info.value)
    assert isinstance(info.value, ValueError)


def test_nan_where_invalid_is_zeroed():
    fields = make_fields()
    fields["states"][0, 1, 2] = float("nan")  # step (0, 1, 2) is invalid
    fields["states"][1, 2, :, 0] = float("inf")  # padding agent
    s = ScenarioTensor(**fields)
    assert torch.isfinite(s.states).all()
    assert (s.states[0, 1, 2] == 0).all() and (s.states[1, 2] == 0).all()
    assert torch.equal(s.states[s.valid], make_fields()["states"][s.valid])


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"valid": torch.ones(2, 3, 5, dtype=torch.bool)}, "`valid`"),
        ({"valid": torch.ones(2, 3, 6, dtype=torch.uint8)}, "`valid`"),
        ({"states": torch.zeros(2, 3, 6, 4, dtype=torch.float64)}, "`states`"),
        ({"states": torch.zeros(2, 3, 6, 3)}, "`states`"),
        ({"extent": torch.ones(2, 3)}, "`extent`"),
        ({"agent_type": torch.ones(2, 3, dtype=torch.int32)}, "`agent_type`"),
        ({"controlled": torch.ones(2, 3, dtype=torch.bool)}, "`controlled`"),  # agent (1, 2) is never valid
        ({"current_index": 6}, "`current_index`"),
        ({"dt": 0.0}, "`dt`"),
        ({"dt": float("nan")}, "`dt`"),
        ({"origin": torch.zeros(3, 2, dtype=torch.float64)}, "`origin`"),
        ({"scene_ids": ("only-one",)}, "`scene_ids`"),
        ({"agent_ids": (("a",), ("b",))}, "`agent_ids`"),
        ({"map": make_map(b=3)}, "`map`"),
    ],
)
def test_validation_error_names_field(change, field):
    with pytest.raises(ScenarioValidationError, match=field):
        make_scenario(**change)


def test_extent_nan_for_valid_agent():
    fields = make_fields()
    fields["extent"][0, 0, 0] = float("nan")
    with pytest.raises(ScenarioValidationError, match="`extent`"):
        ScenarioTensor(**fields)


def test_map_layer_count_mismatch_names_layers():
    with pytest.raises(ScenarioValidationError, match=r"`map\.layers`"):
        MapRaster(raster=torch.zeros(2, 2, 4, 4, dtype=torch.uint8), world_to_pixel=torch.eye(3).expand(2, 3, 3))
    with pytest.raises(ScenarioValidationError, match=r"`map\.raster`"):
        MapRaster(raster=torch.zeros(2, 3, 4, 4), world_to_pixel=torch.eye(3).expand(2, 3, 3))
    with pytest.raises(ScenarioValidationError, match=r"`map\.world_to_pixel`"):
        MapRaster(raster=torch.zeros(2, 3, 4, 4, dtype=torch.uint8), world_to_pixel=torch.eye(3).expand(1, 3, 3))


def test_map_lookup_world_to_pixel():
    raster = torch.zeros(1, 3, 4, 6, dtype=torch.uint8)
    raster[0, 0, 1, 4] = 1  # drivable pixel (i=1, j=4)
    w2p = torch.tensor([[[2.0, 0.0, 1.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0]]])  # i = 2x + 1, j = 2y
    m = MapRaster(raster=raster, world_to_pixel=w2p)
    xy = torch.tensor([[[0.1, 2.2], [0.0, 2.0], [-0.01, 2.2], [0.1, 1.9], [100.0, 2.2], [-100.0, -100.0]]])
    assert m.lookup(xy).tolist() == [[True, True, False, False, False, False]]
    assert not m.lookup(xy, "lane_divider").any()
    with pytest.raises(ScenarioValidationError, match="crosswalk"):
        m.lookup(xy, "crosswalk")


# ----------------------------------------------------------------------- views
def test_history_future_shapes_and_current_index():
    s = make_scenario(t=10, current_index=3)
    hist, fut = s.history, s.future
    assert hist.num_steps == 4 and hist.current_index == 3
    assert fut.num_steps == 6 and fut.current_index == 0
    assert torch.equal(torch.cat([hist.states, fut.states], 2), s.states)
    assert torch.equal(torch.cat([hist.valid, fut.valid], 2), s.valid)
    assert hist.scene_ids == s.scene_ids and hist.agent_ids == s.agent_ids and hist.map is s.map


def test_time_slice():
    s = make_scenario(t=10, current_index=3)
    w = s.time_slice(2, 7)
    assert w.num_steps == 5 and w.current_index == 1
    assert torch.equal(w.states, s.states[:, :, 2:7])
    assert s.time_slice(5).current_index == 0  # "now" before the window is clamped to its start
    assert s.time_slice(0, 2).current_index == 1  # ... and after it to its end
    for start, stop in [(-1, 3), (3, 3), (4, 2), (0, 11)]:
        with pytest.raises(ScenarioValidationError, match="window"):
            s.time_slice(start, stop)


def test_future_without_future_steps():
    with pytest.raises(ScenarioValidationError, match="no future"):
        _ = make_scenario(t=4, current_index=3).future


def test_with_future():
    s = make_scenario(t=10, current_index=3)
    fut = torch.randn(2, 3, 7, 4)
    out = s.with_future(fut)
    assert out.num_steps == 3 + 1 + 7 and out.current_index == 3
    assert torch.equal(out.states[:, :, :4], s.states[:, :, :4])
    default_valid = s.valid[:, :, 3, None].expand(2, 3, 7)
    assert torch.equal(out.valid[:, :, 4:], default_valid)
    assert torch.equal(out.states[:, :, 4:][default_valid], fut[default_valid])
    explicit = torch.zeros(2, 3, 7, dtype=torch.bool)
    explicit[0, 0, 0] = True
    assert torch.equal(s.with_future(fut, explicit).valid[:, :, 4:], explicit)
    with pytest.raises(ScenarioValidationError, match="`future_states`"):
        s.with_future(torch.zeros(2, 3, 7))
    with pytest.raises(ScenarioValidationError, match="`future_states`"):
        s.with_future(torch.zeros(1, 3, 7, 4))


def test_actions_masked_and_wrapped():
    fields = make_fields(b=1, a=1, t=3)
    fields["states"] = torch.tensor([[[[0.0, 0.0, 1.0, 3.1], [0.1, 0.0, 2.0, -3.1], [0.2, 0.0, 2.5, -3.0]]]])
    s = ScenarioTensor(**fields)
    acc = s.actions()
    assert acc.shape == (1, 1, 2, 2)
    expected_rate = (2 * math.pi - 6.2) / 0.1  # the short way across +-pi
    assert torch.allclose(acc[0, 0, 0], torch.tensor([10.0, expected_rate]), atol=1e-3)
    valid = s.valid.clone()
    valid[0, 0, 1] = False
    masked = ScenarioTensor(**{**fields, "valid": valid})
    assert not masked.action_valid.any() and (masked.actions() == 0).all()


# -------------------------------------------------------------------- indexing
@pytest.mark.parametrize(
    ("index", "picked"),
    [
        (1, [1]),
        (-1, [2]),
        (np.int64(0), [0]),
        (torch.tensor(2), [2]),
        (slice(0, 2), [0, 1]),
        (slice(None, None, 2), [0, 2]),
        (torch.tensor([True, False, True]), [0, 2]),
        ([True, False, True], [0, 2]),
        ([2, 0], [2, 0]),
        (torch.tensor([1]), [1]),
    ],
)
def test_indexing_keeps_ids(index, picked):
    s = make_scenario(b=3)
    sub = s[index]
    assert sub.num_scenes == len(picked)
    assert sub.scene_ids == tuple(s.scene_ids[i] for i in picked)
    assert sub.agent_ids == tuple(s.agent_ids[i] for i in picked)
    assert torch.equal(sub.states, s.states[picked])
    assert torch.equal(sub.valid, s.valid[picked])
    assert torch.equal(sub.origin, s.origin[picked])
    assert torch.equal(sub.map.padded(), s.map.padded()[picked])
    assert sub.map.pixels is s.map.pixels  # the selection reads the same rows, no pixel is copied
    assert sub.source == s.source and sub.dt == s.dt and sub.current_index == s.current_index


@pytest.mark.parametrize("b", [1, 3])
def test_repeat_scenes_matches_repeat_interleave(b):
    s = make_scenario(b=b)
    out = s.repeat_scenes(4)
    picked = torch.arange(b).repeat_interleave(4)
    assert out.num_scenes == 4 * b
    for name in ("states", "valid", "extent", "agent_type", "controlled", "origin"):
        assert torch.equal(getattr(out, name), getattr(s, name)[picked]), name
    assert torch.equal(out.map.padded(), s.map.padded()[picked])
    assert torch.equal(out.map.world_to_pixel, s.map.world_to_pixel[picked])
    assert out.scene_ids == tuple(s.scene_ids[i] for i in picked.tolist())
    assert out.agent_ids == tuple(s.agent_ids[i] for i in picked.tolist())
    assert out.map.pixels is s.map.pixels and torch.equal(out.map.rows, picked)  # rows, not copied pixels


@pytest.mark.parametrize("copies", [0, -2, 2.0, True])
@pytest.mark.parametrize("b", [1, 3])
def test_repeat_scenes_rejects_a_bad_count(b, copies):
    s = make_scenario(b=b)
    with pytest.raises(ValueError, match="copies"):
        s.repeat_scenes(copies)
    with pytest.raises(ValueError, match="copies"):
        s.map.repeat_scenes(copies)


def test_indexing_an_unchecked_window_does_not_revalidate():
    s = make_scenario(b=2)
    window = s.time_slice(0, 1).replace_unchecked(controlled=torch.ones_like(s.controlled))
    assert not window.valid[1, 2].any()  # agent 2 of scene 1 is controlled and never valid in the window
    assert window[1].controlled.all()  # a checked copy would reject controlled agents invalid in the window


def test_int_index_out_of_range():
    with pytest.raises(IndexError):
        make_scenario(b=2)[2]


# ---------------------------------------------------------------------- concat
def test_concat_pads_agents_time_and_maps():
    a = make_scenario(b=1, a=2, t=4, map=make_map(1, h=3, w=7))
    b = make_scenario(b=2, a=3, t=6, map=make_map(2, h=5, w=2))
    out = ScenarioTensor.concat([a, b])
    assert out.states.shape == (3, 3, 6, 4) and out.valid.shape == (3, 3, 6)
    assert out.map.sizes.tolist() == [[3, 7], [5, 2], [5, 2]]  # each raster keeps its own size: no padding
    assert out.map.pixels.shape == (3, 3 * 7 + 2 * 5 * 2) and out.map.padded().shape == (3, 3, 5, 7)
    assert torch.equal(out.states[:1, :2, :4], a.states) and torch.equal(out.states[1:], b.states)
    assert torch.equal(out.valid[:1, :2, :4], a.valid) and torch.equal(out.valid[1:], b.valid)
    assert not out.valid[0, 2].any() and not out.valid[0, :, 4:].any()
    assert (out.states[0, 2] == 0).all() and (out.states[0, :, 4:] == 0).all()
    assert torch.equal(out.extent[0, :2], a.extent[0]) and (out.extent[0, 2] == 0).all()
    assert out.agent_type[0, 2] == 0 and not out.controlled[0, 2]
    assert torch.equal(out.map.scene_raster(0), a.map.scene_raster(0))
    assert all(torch.equal(out.map.scene_raster(k + 1), b.map.scene_raster(k)) for k in range(2))
    padded = out.map.padded()
    assert padded[0, :, 3:].sum() == 0 and padded[1:, :, :, 2:].sum() == 0
    assert torch.equal(out.origin, torch.cat([a.origin, b.origin]))
    assert out.scene_ids == a.scene_ids + b.scene_ids
    assert out.agent_ids[0] == (*a.agent_ids[0], "") and out.agent_ids[1:] == b.agent_ids
    assert out.source == "unit"


def test_concat_errors():
    with pytest.raises(ScenarioValidationError, match="empty"):
        ScenarioTensor.concat([])
    with pytest.raises(ScenarioValidationError, match="current_index"):
        ScenarioTensor.concat([make_scenario(current_index=1), make_scenario(current_index=2)])
    with pytest.raises(ScenarioValidationError, match="layers"):
        ScenarioTensor.concat([make_scenario(), make_scenario(map=make_map(2, layers=("drivable",)))])


@FAST
@given(st.lists(scenario_tensors(max_scenes=2, max_agents=3, max_steps=5), min_size=1, max_size=3))
def test_concat_preserves_values_property(parts):
    parts = [ScenarioTensor(**{**_fields(p), "current_index": 0}) for p in parts]  # concat needs a common "now"
    out = ScenarioTensor.concat(parts)
    row = 0
    for p in parts:
        sl = slice(row, row + p.num_scenes)
        assert torch.equal(out.states[sl, : p.num_agents, : p.num_steps], p.states)
        assert torch.equal(out.valid[sl, : p.num_agents, : p.num_steps], p.valid)
        assert int(out.valid[sl].sum()) == int(p.valid.sum())
        for k in range(p.num_scenes):
            assert torch.equal(out.map.scene_raster(row + k), p.map.scene_raster(k))
        assert out.scene_ids[sl] == p.scene_ids
        row += p.num_scenes
    assert row == out.num_scenes


def _fields(s: ScenarioTensor) -> dict:
    return {name: getattr(s, name) for name in s.__dataclass_fields__}


def test_to_cpu():
    s = make_scenario()
    moved = s.to("cpu")
    assert moved.device == torch.device("cpu")
    for name in ("states", "valid", "extent", "agent_type", "controlled", "origin"):
        assert torch.equal(getattr(moved, name), getattr(s, name))
        assert getattr(moved, name).dtype == getattr(s, name).dtype
    assert moved.origin.dtype == torch.float64
    assert torch.equal(moved.map.pixels, s.map.pixels) and torch.equal(moved.map.sizes, s.map.sizes)
    assert moved.scene_ids == s.scene_ids and moved.agent_ids == s.agent_ids


# --------------------------------------------------------------------------- IO
def _bitwise_equal(a: torch.Tensor | None, b: torch.Tensor | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype.is_floating_point:
        as_int = {torch.float32: torch.int32, torch.float64: torch.int64}[a.dtype]
        return torch.equal(a.contiguous().view(as_int), b.contiguous().view(as_int))
    return torch.equal(a, b)


@FAST
@given(scenario_tensors(with_map=None, dt=None))
def test_save_load_round_trip_is_bitwise_exact(scenario):
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "scene.safetensors")
        scenario.save(path)
        loaded = ScenarioTensor.load(path)
    for name in ("states", "valid", "extent", "agent_type", "controlled", "origin"):
        assert _bitwise_equal(getattr(loaded, name), getattr(scenario, name)), name
    assert (loaded.map is None) == (scenario.map is None)
    if scenario.map is not None:
        for name in ("world_to_pixel", "polylines", "polyline_valid", "polyline_type"):
            assert _bitwise_equal(getattr(loaded.map, name), getattr(scenario.map, name)), name
        assert torch.equal(loaded.map.scene_sizes(), scenario.map.scene_sizes())
        assert all(torch.equal(loaded.map.scene_raster(b), scenario.map.scene_raster(b))
                   for b in range(scenario.num_scenes))
        assert loaded.map.layers == scenario.map.layers
    for name in ("dt", "current_index", "scene_ids", "agent_ids", "source", "extras"):
        assert getattr(loaded, name) == getattr(scenario, name), name


@FAST
@given(feasible_trajectories(max_scenes=2, max_agents=4, max_steps=12, return_actions=True))
def test_actions_rollout_reproduces_feasible_trajectory(scenario_and_actions):
    """``unicycle_rollout(states[:, :, 0], scenario.actions())`` reproduces the states of a feasible trajectory.

    Tolerances (float32, x and y within +-100 m, speeds below 30 m/s, 12 steps of 0.1 s): speed and yaw
    (compared modulo 2 pi) to 1e-4, positions to 1e-3 m.
    """
    scenario, actions = scenario_and_actions
    recovered = scenario.actions()
    assert scenario.action_valid.all()
    assert torch.allclose(recovered, actions, atol=2e-3)  # finite differences of float32 states
    rolled = unicycle_rollout(scenario.states[:, :, 0], recovered, scenario.dt)
    target = scenario.states[:, :, 1:]
    assert (rolled[..., 2] - target[..., 2]).abs().max() <= 1e-4
    assert wrap_angle(rolled[..., 3] - target[..., 3]).abs().max() <= 1e-4
    assert (rolled[..., :2] - target[..., :2]).abs().max() <= 1e-3


@pytest.fixture()
def saved(tmp_path):
    path = tmp_path / "scene.safetensors"
    make_scenario().save(str(path))
    return path


def test_truncated_file_is_data_format_error(saved):
    data = saved.read_bytes()
    for cut in (4, 60, len(data) // 2, len(data) - 1):
        saved.write_bytes(data[:cut])
        with pytest.raises(DataFormatError, match="safetensors"):
            ScenarioTensor.load(str(saved))


def test_corrupt_file_is_data_format_error(tmp_path):
    path = tmp_path / "garbage.safetensors"
    path.write_bytes(b"\xff" * 8 + b"not a header at all" * 10)
    with pytest.raises(DataFormatError, match=r"garbage\.safetensors"):
        ScenarioTensor.load(str(path))
    path.write_bytes(b"")
    with pytest.raises(DataFormatError):
        ScenarioTensor.load(str(path))


def test_safetensors_file_that_is_not_a_scenario(tmp_path):
    path = tmp_path / "weights.safetensors"
    save_file({"weight": torch.zeros(3, 3)}, str(path))
    with pytest.raises(DataFormatError, match="not a TrafficRLHF scenario"):
        ScenarioTensor.load(str(path))


def test_scenario_header_with_missing_tensors(tmp_path):
    path = tmp_path / "partial.safetensors"
    meta = {"trafficrlhf_scenario": "1", "dt": "0.1", "current_index": "0", "scene_ids": "[]", "agent_ids": "[]",
            "source": '""', "extras": "{}", "map_layers": "null"}
    save_file({"valid": torch.ones(1, 1, 2, dtype=torch.bool)}, str(path), metadata=meta)
    with pytest.raises(DataFormatError, match="states"):
        ScenarioTensor.load(str(path))


def test_malformed_metadata_and_invalid_content(tmp_path, saved):
    from safetensors import safe_open
    from safetensors.torch import load_file

    tensors = load_file(str(saved))
    with safe_open(str(saved), framework="pt") as handle:
        meta = dict(handle.metadata())
    bad_json = tmp_path / "bad_json.safetensors"
    save_file(tensors, str(bad_json), metadata={**meta, "extras": "{not json"})
    with pytest.raises(DataFormatError, match="metadata"):
        ScenarioTensor.load(str(bad_json))
    nan_states = tmp_path / "nan.safetensors"
    tensors["states"][0, 0, 0, 0] = float("nan")
    save_file(tensors, str(nan_states), metadata=meta)
    with pytest.raises(DataFormatError, match="`states`"):
        ScenarioTensor.load(str(nan_states))


def test_missing_file_is_data_not_found(tmp_path):
    with pytest.raises(DataNotFoundError, match=r"nope\.safetensors"):
        ScenarioTensor.load(str(tmp_path / "nope.safetensors"))
