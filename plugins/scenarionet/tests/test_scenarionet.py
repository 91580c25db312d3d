"""The ``scenarionet`` source and its restricted unpickler.

Synthetic scenarios (written to ``tmp_path``) run everywhere; the tests on the ten nuScenes-mini scenes read
``<default_data_root()>/nuscenes_mini_scenarionet`` in place and are skipped when it is absent. nuScenes data:
CC BY-NC-SA 4.0 (non-commercial); it is never copied into the repository.
"""

from __future__ import annotations

import math
import os
import pickle

import numpy as np
import pytest
import torch

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, UnsafePickleError
from trafficrlhf_sdk.scenario import AgentType, PolylineType, ScenarioTensor, default_data_root
from trafficrlhf_scenarionet import ScenarioNetSource, restricted_load, restricted_loads

MINI_ROOT = os.path.join(default_data_root(), "nuscenes_mini_scenarionet")
needs_data = pytest.mark.skipif(
    not os.path.isdir(MINI_ROOT),
    reason=f"nuScenes-mini ScenarioNet data not found at {MINI_ROOT!r} (set TRAFFICRLHF_DATA to the shared data)",
)
ORIGIN = np.array([1000.0, 2000.0])  # world position of the synthetic road's start


# --------------------------------------------------------------------------------------------- synthetic data
def _track(kind: str, pos: np.ndarray, heading: np.ndarray, vel: np.ndarray, valid: np.ndarray,
           size: tuple[float, float]) -> dict:
    n = len(pos)
    return {"type": kind, "metadata": {"type": kind.lower()}, "state": {
        "position": np.concatenate([pos, np.zeros((n, 1))], 1), "heading": heading, "velocity": vel,
        "valid": valid.astype(np.float64), "length": np.full((n, 1), size[0]), "width": np.full((n, 1), size[1]),
        "height": np.full((n, 1), 1.5)}}


def synthetic_scenario(length: int = 200) -> dict:
    """A straight two-lane road along +x (world y in [1996, 2007]) with five tracks, in ScenarioNet layout."""
    t = np.arange(length) * 0.1
    ones, zeros = np.ones(length), np.zeros(length)
    ego_xy = np.stack([ORIGIN[0] + 5 * t, ORIGIN[1] + zeros], 1)
    back_xy = np.stack([ORIGIN[0] + 30 - t, ORIGIN[1] + 3.5 + zeros], 1)
    ped_valid = (np.arange(length) >= 50) & (np.arange(length) < 150)
    tracks = {
        "car_reversing": _track("VEHICLE", back_xy, zeros, np.stack([-ones, zeros], 1), ones > 0, (4.5, 1.9)),
        "ego": _track("VEHICLE", ego_xy, zeros + 2 * math.pi, np.stack([5 * ones, zeros], 1), ones > 0, (1.8, 4.5)),
        "ped": _track("PEDESTRIAN", np.tile(ORIGIN + [5.0, 10.0], (length, 1)), zeros + math.pi,
                      np.zeros((length, 2)), ped_valid, (0.5, 0.5)),
        "cone": _track("TRAFFIC_CONE", np.tile(ORIGIN + [20.0, -3.0], (length, 1)), zeros, np.zeros((length, 2)),
                       ones > 0, (0.3, 0.3)),
        "ghost": _track("VEHICLE", np.zeros((length, 2)), zeros, np.zeros((length, 2)), zeros > 0, (4.0, 2.0)),
    }
    line = lambda y, x0=-50.0, x1=150.0: np.array([[x0, y], [x1, y]]) + ORIGIN  # noqa: E731
    box = lambda x0, x1, y0, y1: np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]) + ORIGIN  # noqa: E731
    map_features = {
        "lane_a": {"type": "LANE_SURFACE_STREET", "polyline": np.c_[line(0.0), [0.0, 0.0]],
                   "polygon": box(-50, 150, -1.75, 1.75)},
        "lane_b": {"type": "LANE_SURFACE_STREET", "polyline": np.c_[line(3.5), [0.0, 0.0]], "speed_limit_kmh": 50},
        "yellow": {"type": "ROAD_LINE_SOLID_SINGLE_YELLOW", "polyline": line(1.75)},
        "white": {"type": "ROAD_LINE_BROKEN_SINGLE_WHITE", "polyline": line(5.25)},
        "boundary_0": {"type": "ROAD_LINE_SOLID_SINGLE_WHITE",
                       "polyline": np.concatenate([box(-50, 150, -4, 7), box(-50, 150, -4, 7)[:1]])},
        "xing": {"type": "CROSSWALK", "polygon": box(60, 64, -4, 7)},
        "stop": {"type": "STOP_SIGN", "position": ORIGIN},
    }
    return {"id": "synthetic", "version": "test", "length": length, "dynamic_map_states": {},
            "metadata": {"dataset": "synthetic", "sample_rate": 0.1, "sdc_id": "ego", "ts": t},
            "tracks": tracks, "map_features": map_features}


@pytest.fixture()
def synthetic_root(tmp_path) -> str:
    """``tmp_path`` holding one 20 s scenario, one 5 s scenario and an (ignored) ScenarioNet summary file."""
    for name, length in (("sd_long", 200), ("sd_short", 50)):
        (tmp_path / f"{name}.pkl").write_bytes(pickle.dumps(synthetic_scenario(length), protocol=4))
    (tmp_path / "dataset_summary.pkl").write_bytes(pickle.dumps({"sd_long.pkl": {}}))
    return str(tmp_path)


def test_registered_as_scenarionet():
    from trafficrlhf_sdk.plugins import registry

    assert registry("scenario_sources").get("scenarionet") is ScenarioNetSource
    assert ScenarioNetSource().root == MINI_ROOT


def test_synthetic_scene(synthetic_root):
    source = ScenarioNetSource(root=synthetic_root)
    assert source.splits() == ["all"]
    assert source.scene_ids("all") == ["sd_long"]  # sd_short (4.9 s) < 3 s + 10 s; the summary is ignored
    s = source.load_scene("all", "sd_long")
    assert s.agent_ids == (("ego", "car_reversing", "ped", "cone"),)  # SDC first; never-valid "ghost" dropped
    assert s.num_steps == 200 and s.current_index == 30 and s.dt == pytest.approx(0.1)
    assert s.agent_type[0].tolist() == [AgentType.VEHICLE, AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.OTHER]
    assert s.controlled[0].tolist() == [True, True, False, False]
    assert s.extent[0, 0].tolist() == pytest.approx([4.5, 1.8])  # the ego's (width, length) swap is undone
    assert s.extras == {"split": "all", "dataset": "synthetic"} and s.source == "scenarionet"
    world = s.xy[0].double() + s.origin[0]
    assert torch.allclose(world[0, :, 0], torch.tensor(ORIGIN[0] + 0.5 * np.arange(200)), atol=1e-3)
    assert s.speed[0, 0].tolist() == pytest.approx([5.0] * 200)
    assert s.speed[0, 1].tolist() == pytest.approx([-1.0] * 200)  # driving backwards: negative speed
    assert (s.yaw[0, 0].abs() < 1e-5).all() and (s.yaw[0, 2][s.valid[0, 2]] == pytest.approx(-math.pi))
    assert s.valid[0, 2].sum() == 100 and (s.states[0, 2][~s.valid[0, 2]] == 0).all()
    # origin = min corner of the valid positions minus the 20 m margin; x runs along rows (H)
    assert s.origin[0].tolist() == pytest.approx([ORIGIN[0] - 20.0, ORIGIN[1] - 3.0 - 20.0])
    h, w = s.map.scene_raster(0).shape[1:]
    assert (h, w) == (math.ceil((99.5 + 40) * 3), math.ceil((13.0 + 40) * 3))
    road = lambda dx, dy: torch.tensor([[[ORIGIN[0] + dx, ORIGIN[1] + dy]]]) - s.origin.float()  # noqa: E731
    assert s.map.lookup(s.xy[:, :2]).all()  # both cars always on the road
    assert not s.map.lookup(road(5.0, 10.0)).any() and not s.map.lookup(road(-60.0, 0.0)).any()
    assert s.map.lookup(road(10.0, 6.5)).all()  # inside the boundary ring only
    assert s.map.lookup(road(10.2, 1.75), "road_divider").all() and s.map.lookup(road(10.2, 5.25), "lane_divider").all()
    assert not s.map.lookup(road(10.2, 3.5), "road_divider").any()
    poly = s.map.polylines[0]
    assert poly.shape[1:] == (20, 2) and s.map.polyline_valid.all()
    assert set(s.map.polyline_type[0].tolist()) == {PolylineType.LANE_CENTER, PolylineType.ROAD_LINE,
                                                   PolylineType.ROAD_EDGE, PolylineType.CROSSWALK}
    assert (poly >= 0).all() and (poly[..., 0] <= h / 3).all() and (poly[..., 1] <= w / 3).all()
    assert (poly[:, 1:] - poly[:, :-1]).norm(dim=-1).max() <= 30.0 / 19 + 1e-3  # pieces of <= 30 m


def test_rasterize_roles():
    from trafficrlhf_scenarionet.map_raster import parse_map_features, rasterize

    def ring(x0: float, x1: float, y0: float, y1: float) -> list[list[float]]:
        return [[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]

    features = parse_map_features({
        "connector": {"type": "LANE_SURFACE_STREET", "polyline": [[10.0, 10.0, 1.5], [10.0, 40.0, 1.5]]},
        "boundary_0": {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": ring(30, 60, 0, 50)},
        "boundary_1": {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": ring(40, 50, 10, 40)},  # a hole
        "bike": {"type": "LANE_BIKE_LANE", "polyline": [[5.0, 5.0], [5.0, 45.0]]},
        "stop": {"type": "STOP_SIGN", "position": [1.0, 2.0]},
    }, "unit")
    assert [f.role for f in features] == ["lane", "road_edge", "road_edge", "other"]
    raster = rasterize(features, np.zeros(2), (200, 150), 3.0, 4.0)  # H: x in [0, 66.7) m, W: y in [0, 50) m
    px = lambda x, y: raster[0, int(x * 3), int(y * 3)]  # noqa: E731
    assert px(10, 25) == 1 and px(8.5, 25) == 1 and px(7.0, 25) == 0  # centerline drawn 4 m wide
    assert px(35, 25) == 1 and px(45, 25) == 0 and px(45, 5) == 1 and px(62, 25) == 0  # even-odd fill
    assert px(5, 25) == 0 and raster[1:].sum() == 0  # bike lanes are not drivable; no divider lines here


def test_dt_stride_and_future(synthetic_root):
    base = ScenarioNetSource(root=synthetic_root).load_scene("all", "sd_long")
    coarse = ScenarioNetSource(root=synthetic_root, dt=0.2).load_scene("all", "sd_long")
    assert coarse.current_index == 15 and coarse.num_steps == 100
    world = lambda s: s.xy.double() + s.origin[:, None, None]  # noqa: E731
    assert torch.allclose(world(coarse), world(base)[:, :, ::2], atol=1e-3)
    assert torch.equal(coarse.valid, base.valid[:, :, ::2])
    short = ScenarioNetSource(root=synthetic_root, max_future_s=5.0).load_scene("all", "sd_long")
    assert short.num_steps == 30 + 1 + 50
    with pytest.raises(DataFormatError, match="multiple of the data's sample rate"):
        ScenarioNetSource(root=synthetic_root, dt=0.15).load_scene("all", "sd_long")


def test_splits_from_subfolders(tmp_path):
    for split in ("train", "val"):
        (tmp_path / split).mkdir()
        (tmp_path / split / "sd_a.pkl").write_bytes(pickle.dumps(synthetic_scenario(), protocol=4))
    (tmp_path / "empty").mkdir()
    source = ScenarioNetSource(root=str(tmp_path))
    assert source.splits() == ["train", "val"]
    assert source.scene_ids("val") == ["sd_a"] and source.load_scene("train", "sd_a").num_scenes == 1
    with pytest.raises(KeyError, match="all"):
        source.scene_ids("all")
    with pytest.raises(DataNotFoundError, match="sd_b"):
        source.load_scene("val", "sd_b")


def test_missing_root(tmp_path):
    missing = str(tmp_path / "nowhere")
    with pytest.raises(DataNotFoundError) as info:
        ScenarioNetSource(root=missing).scene_ids("all")
    message = str(info.value)
    assert missing in message and "--root" in message and "TRAFFICRLHF_DATA" in message


# ------------------------------------------------------------------------------------------ restricted unpickler
def test_unpickler_round_trips_allowed_types():
    from collections import defaultdict

    value = {"a": np.arange(6.0).reshape(2, 3), "b": defaultdict(int, {"x": 2}), "c": np.float64(1.5),
             "d": [1, (2.0, "s")], "e": np.array(["u", "v"])}
    loaded = restricted_loads(pickle.dumps(value, protocol=4))
    assert np.array_equal(loaded["a"], value["a"]) and loaded["b"] == value["b"] and loaded["c"] == 1.5
    assert loaded["d"] == value["d"] and loaded["e"].tolist() == ["u", "v"]


def test_unpickler_refuses_os_system(tmp_path):
    marker = tmp_path / "pwned"
    evil = tmp_path / "sd_evil.pkl"
    evil.write_bytes(b"cos\nsystem\n(S'touch " + str(marker).encode() + b"'\ntR.")  # protocol 0 GLOBAL os.system
    with pytest.raises(UnsafePickleError) as info:
        restricted_load(str(evil))
    assert "os.system" in str(info.value) and str(evil) in str(info.value)
    with pytest.raises(UnsafePickleError, match=r"os\.system"):
        ScenarioNetSource(root=str(tmp_path)).load_scene("all", "sd_evil")
    assert not marker.exists()


def test_unpickler_refuses_reduce_to_builtin_eval():
    class Exploit:
        def __reduce__(self):  # type: ignore[no-untyped-def]
            return (eval, ("1 + 1",))

    with pytest.raises(UnsafePickleError, match=r"builtins\.eval"):
        restricted_loads(pickle.dumps({"x": Exploit()}, protocol=4), source="exploit.pkl")


@pytest.mark.parametrize("cut", [0, 1, 100, -1])
def test_unpickler_truncated_file(tmp_path, cut):
    data = pickle.dumps(synthetic_scenario(), protocol=4)
    path = tmp_path / "sd_cut.pkl"
    path.write_bytes(data[:cut] if cut >= 0 else data[: len(data) // 2])
    with pytest.raises(DataFormatError, match=r"sd_cut\.pkl") as info:
        restricted_load(str(path))
    assert not isinstance(info.value, UnsafePickleError)
    with pytest.raises(DataFormatError, match=r"sd_cut\.pkl"):
        ScenarioNetSource(root=str(tmp_path), min_future_s=0.0).scene_ids("all")


def test_not_a_scenario(tmp_path):
    (tmp_path / "sd_list.pkl").write_bytes(pickle.dumps([1, 2, 3]))
    with pytest.raises(DataFormatError, match="must be a dict"):
        ScenarioNetSource(root=str(tmp_path)).load_scene("all", "sd_list")


# ------------------------------------------------------------------------------------------ nuScenes-mini scenes
@pytest.fixture(scope="module")
def mini_batch() -> ScenarioTensor:
    if not os.path.isdir(MINI_ROOT):
        pytest.skip(f"nuScenes-mini ScenarioNet data not found at {MINI_ROOT!r}")
    return ScenarioNetSource().load_batch("all")


@needs_data
@pytest.mark.data
def test_mini_scenes(mini_batch):
    source = ScenarioNetSource()
    names = sorted(n[:-4] for n in os.listdir(MINI_ROOT) if n.endswith(".pkl"))
    assert source.splits() == ["all"] and len(names) == 10 and source.scene_ids("all") == names
    s = mini_batch
    assert s.num_scenes == 10 and s.scene_ids == tuple(names) and s.source == "scenarionet"
    assert s.current_index == 30 and s.num_steps == 201 and s.dt == pytest.approx(0.1)
    assert s.states.dtype == torch.float32 and s.valid.dtype == torch.bool and s.agent_type.dtype == torch.int64
    assert s.origin.dtype == torch.float64 and s.origin.shape == (10, 2)
    assert s.map.pixels.dtype == torch.uint8 and s.map.layers == ("drivable", "road_divider", "lane_divider")
    assert s.map.polylines.shape[0] == 10 and s.map.polylines.shape[2:] == (20, 2)
    assert all(ids[0] == "ego" for ids in s.agent_ids) and s.controlled[:, 0].all()
    kinds = set(s.agent_type[s.valid.any(-1)].tolist())
    assert kinds == {AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST, AgentType.OTHER}
    assert (s.yaw[s.valid] >= -math.pi).all() and (s.yaw[s.valid] < math.pi).all()
    assert (s.states[~s.valid] == 0).all() and not (s.controlled & ~s.valid[:, :, 30]).any()
    ext = s.extent[s.agent_type == AgentType.VEHICLE]
    assert (ext[:, 0] >= ext[:, 1]).all() and (ext > 0.5).all()
    assert s.extras == {"split": "all", "dataset": "nuscenes"}


@needs_data
@pytest.mark.data
def test_mini_states_match_the_log(mini_batch):
    from trafficrlhf_scenarionet import read_scenario

    name = mini_batch.scene_ids[3]
    raw = read_scenario(os.path.join(MINI_ROOT, f"{name}.pkl"))["tracks"]["ego"]["state"]
    s = mini_batch[3]
    t = min(s.num_steps, raw["position"].shape[0])
    world = s.xy[0, 0, :t].double() + s.origin[0]
    assert torch.allclose(world, torch.from_numpy(raw["position"][:t, :2]), atol=1e-3)
    speed = np.linalg.norm(raw["velocity"][:t], axis=1)
    assert np.allclose(s.speed[0, 0, :t].abs().numpy(), speed, atol=1e-4)
    yaw_err = (s.yaw[0, 0, :t].double() - torch.from_numpy(raw["heading"][:t]) + math.pi) % (2 * math.pi) - math.pi
    assert yaw_err.abs().max() < 1e-5


@needs_data
@pytest.mark.data
def test_mini_drivable_share(mini_batch, capsys):
    """Share of logged positions on drivable pixels. Parked cars in car parks (absent from the ScenarioNet map)
    keep the all-vehicle figure low; moving vehicles and the ego car must lie on the road."""
    s = mini_batch
    on = s.map.lookup(s.xy)
    vehicle = s.valid & (s.agent_type == AgentType.VEHICLE)[..., None]
    moving = vehicle & (s.speed.abs() > 1.0)
    masks = {"vehicles": vehicle, "moving_vehicles": moving, "all_agents": s.valid}
    share = {name: float((on & m).sum() / m.sum()) for name, m in masks.items()}
    share["ego"] = float((on[:, :1] & s.valid[:, :1]).sum() / s.valid[:, :1].sum())
    with capsys.disabled():
        print("\ndrivable share:", {k: round(v, 4) for k, v in share.items()})
    assert share["ego"] >= 0.99
    assert share["moving_vehicles"] >= 0.97
    assert share["vehicles"] >= 0.55 and share["all_agents"] >= 0.5


@needs_data
@pytest.mark.data
def test_mini_round_trip(mini_batch, tmp_path):
    s = mini_batch[0]
    path = str(tmp_path / "scene.safetensors")
    s.save(path)
    back = ScenarioTensor.load(path)
    for name in ("states", "valid", "extent", "agent_type", "controlled", "origin"):
        assert torch.equal(getattr(back, name), getattr(s, name)), name
    for name in ("pixels", "sizes", "world_to_pixel", "polylines", "polyline_valid", "polyline_type"):
        assert torch.equal(getattr(back.map, name), getattr(s.map.dense(), name)), name
    assert (back.dt, back.current_index, back.scene_ids, back.agent_ids, back.source, back.extras, back.map.layers) \
        == (s.dt, s.current_index, s.scene_ids, s.agent_ids, s.source, s.extras, s.map.layers)


@needs_data
@pytest.mark.data
def test_mini_truncated_copy(tmp_path):
    name = sorted(n for n in os.listdir(MINI_ROOT) if n.endswith(".pkl"))[0]
    with open(os.path.join(MINI_ROOT, name), "rb") as handle:
        head = handle.read(100_000)
    (tmp_path / name).write_bytes(head)
    with pytest.raises(DataFormatError, match=name) as info:
        ScenarioNetSource(root=str(tmp_path)).load_scene("all", name[:-4])
    assert "truncated or corrupt" in str(info.value)
