"""The realism meta-metric against a slow, obvious implementation (Python loops, shapely, numpy histograms),
its ceiling at K rollouts, its ordering (log above constant velocity) and the native-rate kinematics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
import torch

from trafficrlhf_sdk.metrics.realism_meta import (
    META_FEATURES,
    RealismMetaConfig,
    RealismMetaMetric,
    kinematic_features,
    rounded_box_distance,
)
from trafficrlhf_sdk.simulation.policies import ConstantVelocityPolicy, NoisyLogPolicy
from trafficrlhf_sdk.simulation.simulator import Rollout, log_rollout, simulate

shapely = pytest.importorskip("shapely")
from shapely.geometry import MultiPoint, Point  # noqa: E402

K = 3


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _core_corners(x: float, y: float, yaw: float, length: float, width: float) -> tuple[np.ndarray, float]:
    s = 0.7 * min(length, width) / 2
    hl, hw = (length - 2 * s) / 2, (width - 2 * s) / 2
    c, si = math.cos(yaw), math.sin(yaw)
    pts = [(x + dx * c - dy * si, y + dx * si + dy * c) for dx, dy in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))]
    return np.array(pts), s


def slow_box_distance(a: tuple, b: tuple) -> float:
    """Signed distance of the origin to the Minkowski difference of the two core boxes, less both radii."""
    ca, sa = _core_corners(*a)
    cb, sb = _core_corners(*b)
    hull = MultiPoint([tuple(p - q) for p in ca for q in cb]).convex_hull
    origin = Point(0.0, 0.0)
    d = hull.exterior.distance(origin)
    return (-d if hull.contains(origin) else d) - sa - sb


def slow_meta(rollout: Rollout, k: int) -> tuple[float, dict[str, float]]:
    """The meta-metric of a K-rollout stack, scene by scene and agent by agent."""
    from scipy.ndimage import distance_transform_edt

    sim, log = rollout.simulated, rollout.logged
    b = sim.num_scenes // k
    stride = round(float(sim.extras.get("native_dt", sim.dt)) / sim.dt)
    start, end = rollout.start_index, rollout.end_index
    steps = list(range(start - 2 * stride, end + 1, stride))
    first = steps.index(start) + 1
    dt = stride * sim.dt

    def features(scn, n: int, agents: list[int]) -> dict[str, dict[int, list]]:
        """{feature: {agent: [(value, valid) per scored step]}} for scene row n."""
        xy = scn.states[n, :, steps, :2].double().numpy()
        yaw = scn.states[n, :, steps, 3].double().numpy()
        valid = scn.valid[n, :, steps].numpy()
        ext = scn.extent[n].double().numpy()
        a_count, t_count = valid.shape
        out: dict[str, dict[int, list]] = {f: {} for f in META_FEATURES}
        speed = np.full((a_count, t_count), np.nan)
        for a in range(a_count):
            for t in range(1, t_count - 1):
                speed[a, t] = np.linalg.norm((xy[a, t + 1] - xy[a, t - 1]) / 2) / dt
        raster = scn.map.scene_raster(n)[scn.map.layers.index("drivable")].numpy() > 0
        scale = float(scn.map.world_to_pixel[n, 0, 0])
        signed = (distance_transform_edt(~raster) - distance_transform_edt(raster)) / scale
        for a in agents:
            rows = {f: [] for f in META_FEATURES}
            for t in range(first, t_count):
                ok1 = bool(valid[a, t - 1] and valid[a, t + 1]) if t + 1 < t_count else False
                ok2 = bool(t >= 2 and t + 2 < t_count and valid[a, t - 2:t + 3].all())
                v = speed[a, t]
                acc = (speed[a, t + 1] - speed[a, t - 1]) / 2 / dt if t + 1 < t_count else np.nan
                def dh(u: int, a: int = a) -> float:
                    return _wrap(yaw[a, u + 1] - yaw[a, u - 1]) / 2
                ang = dh(t) / dt if t + 1 < t_count else np.nan
                ang_acc = (_wrap(dh(t + 1) - dh(t - 1)) / 2 / dt**2) if t + 2 < t_count else np.nan
                rows["linear_speed"].append((v, ok1))
                rows["linear_acceleration"].append((acc, ok2))
                rows["angular_speed"].append((ang, ok1))
                rows["angular_acceleration"].append((ang_acc, ok2))
                dist, ttc, best = 1e10, 5.0, math.inf
                for o in range(a_count):
                    if o == a or not (valid[a, t] and valid[o, t]):
                        continue
                    dist = min(dist, slow_box_distance((*xy[a, t], yaw[a, t], *ext[a]),
                                                       (*xy[o, t], yaw[o, t], *ext[o])))
                    rel = xy[o, t] - xy[a, t]
                    c, s = math.cos(yaw[a, t]), math.sin(yaw[a, t])
                    rx, ry = rel[0] * c + rel[1] * s, -rel[0] * s + rel[1] * c
                    dyaw = abs(_wrap(yaw[o, t] - yaw[a, t]))
                    lo = ext[o, 0] / 2 * abs(math.cos(dyaw)) + ext[o, 1] / 2 * abs(math.sin(dyaw))
                    la = ext[o, 0] / 2 * abs(math.sin(dyaw)) + ext[o, 1] / 2 * abs(math.cos(dyaw))
                    long_d = rx - ext[a, 0] / 2 - lo
                    lat = abs(ry) - ext[a, 1] / 2 - la
                    follows = (long_d > 0 and dyaw <= math.radians(75) and lat < 0
                               and (lat < -0.5 or dyaw <= math.radians(10)))
                    if follows and long_d < best:
                        best = long_d
                        rel_v = speed[a, t] - speed[o, t]
                        ttc = min(long_d / rel_v, 5.0) if rel_v > 0 else 5.0
                rows["distance_to_nearest_object"].append((dist, bool(valid[a, t])))
                rows["collision_indication"].append((float(dist < 0), bool(valid[a, t])))
                rows["time_to_collision"].append((ttc, bool(valid[a, t])))
                edge = -1e10
                if valid[a, t]:
                    c, s = math.cos(yaw[a, t]), math.sin(yaw[a, t])
                    for dx, dy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
                        px = xy[a, t, 0] + dx * ext[a, 0] / 2 * c - dy * ext[a, 1] / 2 * s
                        py = xy[a, t, 1] + dx * ext[a, 0] / 2 * s + dy * ext[a, 1] / 2 * c
                        i, j = math.floor(px * scale), math.floor(py * scale)
                        inside = 0 <= i < raster.shape[0] and 0 <= j < raster.shape[1]
                        value = signed[min(max(i, 0), raster.shape[0] - 1), min(max(j, 0), raster.shape[1] - 1)]
                        edge = max(edge, value if inside else max(value, 1 / 3))
                rows["distance_to_road_edge"].append((edge, bool(valid[a, t])))
                rows["offroad_indication"].append((float(edge > 0), bool(valid[a, t])))
            for f in META_FEATURES:
                out[f][a] = rows[f]
        return out

    per_scene = []
    feature_means: dict[str, list[float]] = {f: [] for f in META_FEATURES}
    for scene in range(b):
        agents = [int(a) for a in rollout.controlled[scene].nonzero().flatten()]
        logged = features(log, scene, agents)
        sims = [features(sim, r * b + scene, agents) for r in range(k)]
        scores = {}
        for name, feat in META_FEATURES.items():
            if feat.kind == "histogram":
                edges = np.linspace(feat.low, feat.high, feat.bins + 1)
                logs = []
                for a in agents:
                    log_ok = [lv for lv in logged[name][a]]
                    samples = [v for s in sims for (v, ok), (_, lok) in zip(s[name][a], log_ok) if ok and lok]
                    counts, _ = np.histogram(np.clip(samples, feat.low, feat.high), bins=edges)
                    p = (counts + 0.1) / (counts.sum() + 0.1 * feat.bins)
                    for v, ok in log_ok:
                        if ok:
                            idx = min(int(np.searchsorted(edges, np.clip(v, feat.low, feat.high), "right")) - 1,
                                      feat.bins - 1)
                            logs.append(math.log(p[idx]))
                scores[name] = math.exp(sum(logs) / len(logs)) if logs else math.nan
            else:
                logs = []
                for a in agents:
                    if not any(ok for _, ok in logged[name][a]):
                        continue
                    log_flag = any(v > 0 and ok for v, ok in logged[name][a])
                    ones = sum(any(v > 0 and ok and lok for (v, ok), (_, lok) in zip(s[name][a], logged[name][a]))
                               for s in sims)
                    p1 = (ones + 0.1) / (k + 0.2)
                    logs.append(math.log(p1 if log_flag else 1 - p1))
                scores[name] = math.exp(sum(logs) / len(logs)) if logs else math.nan
        ok = {n: v for n, v in scores.items() if not math.isnan(v)}
        weight = sum(META_FEATURES[n].weight for n in ok)
        per_scene.append(sum(META_FEATURES[n].weight * v for n, v in ok.items()) / weight)
        for n, v in scores.items():
            feature_means[n].append(v)
    return float(np.mean(per_scene)), {n: float(np.nanmean(v)) for n, v in feature_means.items()}


def stack(rollouts: list[Rollout]) -> Rollout:
    first = rollouts[0]
    sim = first.simulated.replace_unchecked(
        states=torch.cat([r.simulated.states for r in rollouts]),
        valid=torch.cat([r.simulated.valid for r in rollouts]),
        controlled=torch.cat([r.controlled for r in rollouts]),
        extent=first.simulated.extent.repeat(len(rollouts), 1, 1),
        agent_type=first.simulated.agent_type.repeat(len(rollouts), 1),
        map=first.simulated.map.index(torch.arange(first.simulated.num_scenes).repeat(len(rollouts))))
    log = first.logged[torch.arange(first.logged.num_scenes).repeat(len(rollouts))]
    return Rollout(sim, log, sim.controlled, first.start_index, first.end_index)


@pytest.fixture(scope="module")
def noisy_stack(val_scenes) -> Rollout:  # type: ignore[no-untyped-def]
    scenes = val_scenes[:3]
    return stack([simulate(NoisyLogPolicy(position_noise_m=1.5, seed=s), scenes) for s in range(K)])


@pytest.mark.data
def test_meta_metric_matches_slow_reference(noisy_stack: Rollout) -> None:
    fast = RealismMetaMetric(RealismMetaConfig(rollouts=K)).compute(noisy_stack)
    slow_value, slow_features = slow_meta(noisy_stack, K)
    assert fast.values["realism_meta"] == pytest.approx(slow_value, abs=1e-9)
    for name, value in slow_features.items():
        assert fast.values[f"realism_meta_{name}"] == pytest.approx(value, abs=1e-9, nan_ok=True), name
    assert fast.per_scene["realism_meta"].shape == (3,)


def test_rounded_box_distance_matches_minkowski_hull() -> None:
    rng = np.random.default_rng(0)
    pairs = []
    for _ in range(300):
        a = (*rng.uniform(-3, 3, 2), rng.uniform(-math.pi, math.pi), rng.uniform(3, 6), rng.uniform(1.5, 2.5))
        b = (*rng.uniform(-3, 3, 2), rng.uniform(-math.pi, math.pi), rng.uniform(0.5, 12), rng.uniform(0.5, 3))
        pairs.append((a, b))
    xa = torch.tensor([p[0][:2] for p in pairs], dtype=torch.float64)
    xb = torch.tensor([p[1][:2] for p in pairs], dtype=torch.float64)
    ya = torch.tensor([p[0][2] for p in pairs], dtype=torch.float64)
    yb = torch.tensor([p[1][2] for p in pairs], dtype=torch.float64)
    ea = torch.tensor([p[0][3:] for p in pairs], dtype=torch.float32)
    eb = torch.tensor([p[1][3:] for p in pairs], dtype=torch.float32)
    fast = rounded_box_distance(xa, ya, ea, xb, yb, eb)
    slow = torch.tensor([slow_box_distance((*a[:3], float(np.float32(a[3])), float(np.float32(a[4]))),
                                           (*b[:3], float(np.float32(b[3])), float(np.float32(b[4]))))
                         for a, b in pairs], dtype=torch.float64)
    assert (fast < 0).any() and (fast > 0).any()  # both overlapping and separated pairs
    torch.testing.assert_close(fast, slow, atol=1e-9, rtol=0)


def test_kinematics_at_native_rate_have_no_keyframe_spikes() -> None:
    # a car accelerating steadily at 1 m/s², logged at 2 Hz and interpolated linearly to 10 Hz
    key_t = torch.arange(0, 5.01, 0.5)
    key_x = 0.5 * key_t**2
    fine_t = torch.arange(0, 5.001, 0.1)
    fine_x = torch.from_numpy(np.interp(fine_t.numpy(), key_t.numpy(), key_x.numpy()))
    def accel(x: torch.Tensor, dt: float) -> torch.Tensor:
        xy = torch.stack([x, torch.zeros_like(x)], -1)[None]
        values, masks = kinematic_features(xy, torch.zeros(1, len(x)), torch.ones(1, len(x), dtype=torch.bool), dt)
        return values["linear_acceleration"][0][masks["linear_acceleration"][0]]
    native = accel(key_x.double(), 0.5)
    fine = accel(fine_x.double(), 0.1)
    torch.testing.assert_close(native, torch.ones_like(native), atol=1e-9, rtol=0)
    assert fine.abs().max() >= 2.4  # the interpolated 10 Hz track spikes to 2.5 m/s² at keyframes


@pytest.mark.data
def test_log_ceiling_and_order(val_scenes) -> None:  # type: ignore[no-untyped-def]
    scenes = val_scenes[:4]
    log = log_rollout(scenes)
    cv = simulate(ConstantVelocityPolicy(), scenes)
    metric = RealismMetaMetric(RealismMetaConfig(rollouts=8))
    log_value = metric.compute(stack([log] * 8)).values
    cv_value = metric.compute(stack([cv] * 8)).values
    # a flag feature of a clean agent scores (8 + 0.1) / (8 + 0.2) at K = 8
    assert log_value["realism_meta_collision_indication"] <= 8.1 / 8.2 + 1e-12
    assert log_value["realism_meta"] > cv_value["realism_meta"]
    assert 0 < cv_value["realism_meta"] < 1


@pytest.mark.data
def test_the_ceiling_from_the_logs_own_features_equals_scoring_k_logged_copies(val_scenes) -> None:  # type: ignore[no-untyped-def]
    scenes = val_scenes[:4]
    log = log_rollout(scenes)
    cv = [simulate(ConstantVelocityPolicy(), scenes)] * 2 + [log]
    metric = RealismMetaMetric(RealismMetaConfig(rollouts=3))
    result, ceiling = metric.compute_with_ceiling(stack(cv))
    alone, copies = metric.compute(stack(cv)), metric.compute(stack([log] * 3))
    assert result.values == alone.values and ceiling.values == copies.values
    for key, value in copies.per_scene.items():
        assert torch.equal(ceiling.per_scene[key].nan_to_num(-1.0), value.nan_to_num(-1.0)), key
    assert ceiling.values["realism_meta"] > result.values["realism_meta"]


def test_config_rejects_unknown_feature() -> None:
    with pytest.raises(ValueError, match="unknown feature"):
        RealismMetaConfig(features={"traffic_light_violation": META_FEATURES["offroad_indication"]})


@pytest.mark.data
def test_cli_rollouts_write_the_meta_metric_and_compare_pairs_it(tmp_path, data_root) -> None:  # type: ignore[no-untyped-def]
    import json

    from click.testing import CliRunner

    from trafficrlhf_sdk.cli import get_cli

    def run(*args: str) -> str:
        result = CliRunner().invoke(get_cli(), list(args), catch_exceptions=False)
        assert result.exit_code == 0, result.output
        return result.output

    for name, model, k in (("log", "log_replay", "2"), ("cv", "constant_velocity", "2"), ("cv1", "constant_velocity",
                                                                                          "1")):
        run("evaluate", "--model", model, "--scenes", "3", "--rollouts", k, "--out", str(tmp_path / name), "--json")
    result = json.loads((tmp_path / "cv" / "results.json").read_text())
    assert result["metadata"]["rollouts"] == 2 and len(result["per_scene"]["realism_meta"]) == 3
    assert result["metrics"]["realism_meta"] < result["logged"]["realism_meta"]
    assert "realism_meta" not in json.loads((tmp_path / "cv1" / "results.json").read_text())["metrics"]
    table = run("compare", str(tmp_path / "log"), str(tmp_path / "cv"))
    assert "realism meta-metric (K = 2) against log_replay" in table and "scenes won" in table
    from trafficrlhf_sdk.errors import DataFormatError
    from trafficrlhf_sdk.evaluation.compare import meta_metric_table

    (tmp_path / "cv1" / "results.json").write_text(json.dumps({**result, "metadata": {**result["metadata"],
                                                                                         "rollouts": 4}}))
    with pytest.raises(DataFormatError, match="equal --rollouts"):
        meta_metric_table([str(tmp_path / "log"), str(tmp_path / "cv1")])


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([1.0, 2.0, 3.0]), st.sampled_from(["blobs", "all", "none"]))
def test_signed_road_edge_distance_equals_scipys_distance_transforms(seed: int, scale: float, kind: str) -> None:
    """Against the distance transforms of the whole layer and of its complement (scipy), read at each point's
    pixel: exactly equal within the 40 m the meta-metric uses, the same sign everywhere, and points off the raster
    at least 1/3 m off the road."""
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    from trafficrlhf_sdk.metrics.realism_meta import signed_road_edge_distance
    from trafficrlhf_sdk.scenario.map import MapRaster

    rng = np.random.default_rng(seed)
    sizes = [(int(rng.integers(20, 90)), int(rng.integers(20, 90))) for _ in range(2)]
    rows = []
    for h, w in sizes:
        if kind == "blobs":
            layer = gaussian_filter(rng.standard_normal((h, w)), 3) > 0
        else:
            layer = np.full((h, w), kind == "all")
        raster = np.zeros((1, 90, 90), dtype=np.uint8)
        raster[0, :h, :w] = layer
        rows.append(raster)
    w2p = torch.tensor([[scale, 0.0, 0.0], [0.0, scale, 0.0], [0.0, 0.0, 1.0]]).repeat(2, 1, 1)
    scene_map = MapRaster(raster=torch.from_numpy(np.stack(rows)), world_to_pixel=w2p,
                          sizes=torch.tensor(sizes), layers=("drivable",))
    points = torch.from_numpy(rng.uniform(-5, 95 / scale, (300, 2)))
    scene = torch.from_numpy(rng.integers(0, 2, 300))
    got = signed_road_edge_distance(scene_map, points, scene)
    for n in range(300):
        h, w = sizes[int(scene[n])]
        layer = rows[int(scene[n])][0, :h, :w] > 0
        signed = (torch.from_numpy(distance_transform_edt(~layer) - distance_transform_edt(layer)).float()
                  / scale).double()
        i, j = math.floor(float(points[n, 0]) * scale), math.floor(float(points[n, 1]) * scale)
        inside = 0 <= i < h and 0 <= j < w
        value = float(signed[min(max(i, 0), h - 1), min(max(j, 0), w - 1)])
        if layer.all() or not layer.any():  # no pixel of the other kind: beyond every histogram's range
            value = 41.0 if not layer.any() else -41.0
        expected = value if inside else max(value, 1 / 3)
        assert float(got[n]) == expected, (n, float(got[n]), expected)
