"""Closed-loop metrics against independent references: shapely boxes, a per-point pixel lookup, numpy histograms,
``scipy.stats.wasserstein_distance`` and the slow reference module ``trafficrlhf_sdk.testing.reference_metrics``.
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np
import pytest
import torch

hypothesis = pytest.importorskip("hypothesis")
shapely_geometry = pytest.importorskip("shapely.geometry")
scipy_stats = pytest.importorskip("scipy.stats")

from hypothesis import HealthCheck, assume, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from trafficrlhf_sdk.metrics import (  # noqa: E402
    FailureMetric,
    HistogramSpec,
    RealismMetric,
    RewardCostMetric,
    SpeedMetric,
    box_corners,
    boxes_overlap,
    colliding_pairs,
    collisions_per_step,
    histogram_distance,
    kinematics,
    offroad_per_step,
    pairwise_collisions,
    scene_histogram,
)
from trafficrlhf_sdk.metrics.realism import SPECS  # noqa: E402
from trafficrlhf_sdk.scenario import MapRaster, ScenarioTensor, default_data_root  # noqa: E402
from trafficrlhf_sdk.simulation import ConstantVelocityPolicy, NoisyLogPolicy, log_rollout, simulate  # noqa: E402
from trafficrlhf_sdk.testing.reference_metrics import (  # noqa: E402
    reference_collisions,
    reference_failure,
    reference_offroad,
    reference_realism_ctg,
)

Polygon = shapely_geometry.Polygon
NUM_REAL_SCENES = 20
# Boxes whose shapely verdict flips when one of them grows or shrinks by this much (m) touch "within rounding":
# the SDK decides them with float projections, shapely with robust predicates, and neither answer is more right.
TOUCH_EPS = 1e-9
SLOW_SETTINGS = {"deadline": None, "suppress_health_check": [HealthCheck.filter_too_much, HealthCheck.too_slow]}


# --------------------------------------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def real_scenes() -> ScenarioTensor:
    """The first 20 long-enough nuscenes_pred val scenes (skips without the data or the plugin)."""
    if not os.path.isdir(os.path.join(default_data_root(), "nuscenes_pred", "label")):
        pytest.skip(f"nuscenes_pred not found under {default_data_root()!r}")
    from trafficrlhf_sdk import get_scenario_source
    from trafficrlhf_sdk.errors import UnknownComponentError

    try:
        source = get_scenario_source("nuscenes_pred")
    except UnknownComponentError:
        pytest.skip("the nuscenes_pred source plugin is not installed")
    return source.load_batch("val", NUM_REAL_SCENES)


class _Case:
    """A real rollout and its (lazily computed, cached) slow references."""

    def __init__(self, rollout) -> None:  # type: ignore[no-untyped-def]
        self.rollout = rollout
        self._failure = self._realism = None

    @property
    def failure(self):  # type: ignore[no-untyped-def]
        if self._failure is None:
            self._failure = reference_failure(self.rollout)
        return self._failure

    @property
    def realism(self):  # type: ignore[no-untyped-def]
        if self._realism is None:
            self._realism = reference_realism_ctg(self.rollout)
        return self._realism


@pytest.fixture(scope="module", params=["log", "constant_velocity", "noisy_log"])
def case(request, real_scenes) -> _Case:  # type: ignore[no-untyped-def]
    """Log-replay, constant-velocity and noisy-log rollouts of the real scenes, with their references. The noisy
    log keeps the log's validity (agents that vanish mid-window) while changing the kinematics."""
    if request.param == "log":
        return _Case(log_rollout(real_scenes))
    if request.param == "noisy_log":
        return _Case(simulate(NoisyLogPolicy(position_noise_m=1.5, seed=7), real_scenes))
    return _Case(simulate(ConstantVelocityPolicy(), real_scenes))


def _window(rollout):  # type: ignore[no-untyped-def]
    return rollout.simulated.time_slice(rollout.start_index + 1, rollout.end_index + 1)


def test_collisions_on_real_scenes_match_shapely(case) -> None:  # type: ignore[no-untyped-def]
    window = _window(case.rollout)
    sdk = (collisions_per_step(window) & window.valid).numpy()
    ref = case.failure["collision_steps"]
    assert sdk.shape == ref.shape
    assert np.array_equal(sdk, ref), f"{int((sdk != ref).sum())} (agent, step) collision flags differ"


def test_offroad_on_real_scenes_matches_pixel_lookup(case) -> None:  # type: ignore[no-untyped-def]
    window = _window(case.rollout)
    sdk = offroad_per_step(window, "center").numpy()
    ref = case.failure["offroad_steps"]
    assert np.array_equal(sdk, ref), f"{int((sdk != ref).sum())} (agent, step) off-road flags differ"


def test_failure_metric_matches_reference(case) -> None:  # type: ignore[no-untyped-def]
    result = FailureMetric().compute(case.rollout)
    ref = case.failure
    for key in ("failure_rate", "collision_rate", "offroad_rate"):
        assert result.values[key] == ref[key], key  # exact: ratios of counts, exactly rounded mean
        got = result.per_scene[key].tolist()
        assert [v != v for v in got] == [v != v for v in ref["per_scene"][key]], key  # NaN where no agent
        assert [v for v in got if v == v] == [v for v in ref["per_scene"][key] if v == v], key
    assert torch.equal(result.extras["collided"], torch.from_numpy(ref["collided"]))
    assert torch.equal(result.extras["offroad"], torch.from_numpy(ref["offroad"]))
    assert np.array_equal(result.extras["collision_steps"].numpy(), ref["collision_steps"])  # per step
    assert np.array_equal(result.extras["offroad_steps"].numpy(), ref["offroad_steps"])


def test_realism_ctg_matches_reference(case) -> None:  # type: ignore[no-untyped-def]
    result = RealismMetric("ctg").compute(case.rollout)
    ref = case.realism
    for key in ("realism_ctg", "realism_ctg_lon_acc", "realism_ctg_lat_acc", "realism_ctg_jerk"):
        assert result.values[key] == pytest.approx(ref[key], abs=1e-9), key
    for which in ("simulated", "logged"):
        for q, hist in ref["histograms"][which].items():
            np.testing.assert_allclose(result.extras[which][q].numpy(), hist, rtol=0, atol=1e-12)


def _numpy_pace_histogram(rollout, which: str, preset: str) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Scene-normalized speed histogram on 0-20 m/s (1 m/s bins) with numpy, from the SDK's kinematics."""
    quantities, sample_valid, moving = kinematics(rollout.window(which), preset)  # type: ignore[arg-type]
    mask = (sample_valid & moving[..., None] & rollout.controlled[..., None]).numpy()
    speed = quantities["speed"].numpy()
    total = np.zeros(20)
    for b in range(speed.shape[0]):
        counts, _ = np.histogram(speed[b][mask[b]], bins=np.linspace(0.0, 20.0, 21))
        if counts.sum() > 0:
            total += counts / counts.sum()
    return total / speed.shape[0]


@pytest.mark.parametrize("preset", ["ctg", "body"])
def test_realism_speed_matches_scipy(case, preset) -> None:  # type: ignore[no-untyped-def]
    """``realism_<preset>_speed``: scipy's Wasserstein-1 between numpy speed histograms (0-20 m/s); not part of
    the three-quantity mean."""
    values = RealismMetric(preset).compute(case.rollout).values
    logged = _numpy_pace_histogram(case.rollout, "logged", preset)
    simulated = _numpy_pace_histogram(case.rollout, "simulated", preset)
    centres = np.arange(20) + 0.5
    expected = scipy_stats.wasserstein_distance(centres, centres, logged, simulated)
    assert values[f"realism_{preset}_speed"] == pytest.approx(expected, abs=1e-9)
    mean = sum(values[f"realism_{preset}_{q}"] for q in ("lon_acc", "lat_acc", "jerk")) / 3
    assert values[f"realism_{preset}"] == pytest.approx(mean, abs=1e-12)


def test_realism_speed_sees_stopped_traffic(real_scenes) -> None:  # type: ignore[no-untyped-def]
    """Log replay whose agents all stop 4 s into the window: the speed distance rises from 0 to more than a
    metre per second, while the acceleration histograms (mostly near 0 either way) move far less."""
    replay = log_rollout(real_scenes)
    stop = replay.start_index + 40
    states = replay.simulated.states.clone()
    states[:, :, stop:, :2] = states[:, :, stop : stop + 1, :2]
    states[:, :, stop:, 3] = states[:, :, stop : stop + 1, 3]
    states[:, :, stop:, 2] = 0.0
    stopped = dataclasses.replace(replay, simulated=replay.simulated.replace_unchecked(states=states))
    before = RealismMetric("body").compute(replay).values
    after = RealismMetric("body").compute(stopped).values
    assert before["realism_body_speed"] == 0.0
    assert after["realism_body_speed"] > 1.0
    assert after["realism_body_speed"] > 5 * after["realism_body"]


def test_real_comparisons_are_not_vacuous(real_scenes) -> None:  # type: ignore[no-untyped-def]
    """Constant velocity on these scenes produces both collisions and off-road steps, and a nonzero realism gap."""
    rollout = simulate(ConstantVelocityPolicy(), real_scenes)
    window = _window(rollout)
    assert collisions_per_step(window).any() and offroad_per_step(window).any()
    assert 0 < FailureMetric().compute(rollout).values["failure_rate"] < 1
    assert RealismMetric("ctg").compute(rollout).values["realism_ctg"] > 0.05


def test_ctg_kinematics_quirk_on_real_data(case) -> None:  # type: ignore[no-untyped-def]
    quantities, sample_valid, _ = kinematics(case.rollout.window("simulated"), "ctg")
    for name in ("lon_acc", "lat_acc", "jerk"):
        assert torch.all(quantities[name][:, :, :2] == 0), name
    assert sample_valid.shape == quantities["speed"].shape


# ----------------------------------------------------------------------------------- box geometry
def _polygon(x: float, y: float, yaw: float, length: float, width: float) -> Polygon:
    corners = box_corners(torch.tensor([x, y], dtype=torch.float64), torch.tensor(yaw, dtype=torch.float64),
                          torch.tensor([length, width], dtype=torch.float64))
    return Polygon(corners.tolist())


def _touch_ambiguous(a: Polygon, b: Polygon) -> bool:
    """The shapely verdict changes when ``a`` grows or shrinks by TOUCH_EPS: touching within rounding."""
    return a.buffer(TOUCH_EPS).intersects(b) != a.buffer(-TOUCH_EPS).intersects(b)


coordinates = st.floats(-30.0, 30.0)
offsets = st.floats(0.0, 500.0)  # scene-frame magnitudes
yaws = st.one_of(
    st.sampled_from([0.0, math.pi / 2, -math.pi / 2, math.pi, math.pi / 4, -3 * math.pi / 4]),
    st.floats(-math.pi, math.pi),
)
lengths = st.floats(2.5, 14.0)  # cars .. articulated buses (m)
widths = st.floats(1.4, 3.2)
gaps = st.one_of(
    st.sampled_from([-0.3, -1e-2, -1e-4, -1e-6, 1e-6, 1e-4, 1e-2, 0.3]),
    st.floats(-0.5, 0.5),
)


def _contact_distance(a: Polygon, yaw: float, length: float, width: float, cx: float, cy: float,
                      ux: float, uy: float) -> float:
    """Distance along (ux, uy) from (cx, cy) at which box b first touches ``a`` (bisection on shapely)."""
    lo, hi = 0.0, 20.0  # centres coincide: overlap; 20 m apart: separated (boxes are at most 14 m long)
    for _ in range(60):
        mid = (lo + hi) / 2
        if a.intersects(_polygon(cx + mid * ux, cy + mid * uy, yaw, length, width)):
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2


@st.composite
def box_pairs(draw):  # type: ignore[no-untyped-def]
    """Two boxes ``(x, y, yaw, l, w)``: half at random nearby positions, half placed at the contact distance along
    a random direction and then moved apart or together by a small gap (near-touching)."""
    ox, oy = draw(offsets), draw(offsets)
    a = (ox + draw(coordinates) / 3, oy + draw(coordinates) / 3, draw(yaws), draw(lengths), draw(widths))
    yaw_b, length_b, width_b = draw(yaws), draw(lengths), draw(widths)
    if draw(st.booleans()):
        b = (ox + draw(coordinates) / 3, oy + draw(coordinates) / 3, yaw_b, length_b, width_b)
    else:
        direction = draw(yaws)
        ux, uy = math.cos(direction), math.sin(direction)
        d = _contact_distance(_polygon(*a), yaw_b, length_b, width_b, a[0], a[1], ux, uy) + draw(gaps)
        b = (a[0] + d * ux, a[1] + d * uy, yaw_b, length_b, width_b)
    return a, b


@settings(max_examples=300, **SLOW_SETTINGS)
@given(box_pairs())
def test_boxes_overlap_matches_shapely(pair) -> None:  # type: ignore[no-untyped-def]
    a, b = pair
    pa, pb = _polygon(*a), _polygon(*b)
    assume(not _touch_ambiguous(pa, pb))
    corners = [torch.tensor(p.exterior.coords[:4], dtype=torch.float64) for p in (pa, pb)]
    assert bool(boxes_overlap(corners[0], corners[1])) == pa.intersects(pb)
    assert bool(boxes_overlap(corners[1], corners[0])) == pa.intersects(pb)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("signs", [(1, 1), (1, -1), (-1, 1), (-1, -1), (1, 0), (0, 1)])
@pytest.mark.parametrize("dims", [(4.5, 1.75, 4.625, 1.875), (12.125, 2.5, 3.5, 1.75), (5.25, 1.875, 5.25, 1.875)])
def test_exact_touching_counts_as_collision(dims, signs, dtype) -> None:  # type: ignore[no-untyped-def]
    """Axis-aligned boxes with dyadic sizes touching exactly along an edge or at a corner: shapely says they
    intersect and so must the SDK, including the circle pre-test of ``pairwise_collisions``."""
    l1, w1, l2, w2 = dims
    bx, by = signs[0] * (l1 + l2) / 2, signs[1] * (w1 + w2) / 2
    assert _polygon(0, 0, 0, l1, w1).intersects(_polygon(bx, by, 0, l2, w2))
    xy = torch.tensor([[[[0.0, 0.0]], [[bx, by]]]], dtype=dtype)
    extent = torch.tensor([[[l1, w1], [l2, w2]]], dtype=dtype)
    yaw, valid = torch.zeros(1, 2, 1, dtype=dtype), torch.ones(1, 2, 1, dtype=torch.bool)
    assert pairwise_collisions(xy, yaw, extent, valid).all()
    apart = xy.clone()
    apart[0, 1, 0] += 0.125 * torch.tensor(signs, dtype=dtype)
    assert not pairwise_collisions(apart, yaw, extent, valid).any()


@st.composite
def crowded_scenes(draw):  # type: ignore[no-untyped-def]
    """float64 ``(xy, yaw, extent, valid)`` of 2-6 agents over 1-4 steps packed into a 16 m square."""
    b, a, t = draw(st.integers(1, 2)), draw(st.integers(2, 6)), draw(st.integers(1, 4))
    origin = draw(offsets)
    xy = [[[[origin + draw(st.floats(0, 16)), origin + draw(st.floats(0, 16))] for _ in range(t)] for _ in range(a)]
          for _ in range(b)]
    yaw = [[[draw(yaws) for _ in range(t)] for _ in range(a)] for _ in range(b)]
    extent = [[[draw(lengths), draw(widths)] for _ in range(a)] for _ in range(b)]
    valid = [[[draw(st.booleans()) or draw(st.booleans()) for _ in range(t)] for _ in range(a)] for _ in range(b)]
    return (torch.tensor(xy, dtype=torch.float64), torch.tensor(yaw, dtype=torch.float64),
            torch.tensor(extent, dtype=torch.float64), torch.tensor(valid))


@settings(max_examples=150, **SLOW_SETTINGS)
@given(crowded_scenes())
def test_pairwise_collisions_matches_shapely(scene) -> None:  # type: ignore[no-untyped-def]
    xy, yaw, extent, valid = scene
    b, a, t = valid.shape
    for s in range(b):
        for step in range(t):
            boxes = [_polygon(*xy[s, i, step].tolist(), float(yaw[s, i, step]), *extent[s, i].tolist())
                     for i in range(a)]
            for i in range(a):
                for j in range(i + 1, a):
                    assume(not _touch_ambiguous(boxes[i], boxes[j]))
    expected = reference_collisions(xy, yaw, extent, valid)
    assert np.array_equal(pairwise_collisions(xy, yaw, extent, valid).numpy(), expected)
    # the pair list behind the flags: each overlapping pair once (i < j), both valid, and shapely agrees per pair
    scene_idx, i, j, step = colliding_pairs(xy, yaw, extent, valid)
    pairs = set(zip(scene_idx.tolist(), i.tolist(), j.tolist(), step.tolist()))
    assert len(pairs) == len(scene_idx) and all(p < q for _, p, q, _ in pairs)
    expected_pairs = set()
    for s in range(b):
        for step_ in range(t):
            for p in range(a):
                for q in range(p + 1, a):
                    if valid[s, p, step_] and valid[s, q, step_]:
                        box_p = _polygon(*xy[s, p, step_].tolist(), float(yaw[s, p, step_]), *extent[s, p].tolist())
                        box_q = _polygon(*xy[s, q, step_].tolist(), float(yaw[s, q, step_]), *extent[s, q].tolist())
                        if box_p.intersects(box_q):
                            expected_pairs.add((s, p, q, step_))
    assert pairs == expected_pairs


# ------------------------------------------------------------------------------------ off-road lookup
@settings(max_examples=100, deadline=None)
@given(
    raster=st.lists(st.lists(st.booleans(), min_size=5, max_size=5), min_size=4, max_size=4),
    scale=st.sampled_from([1.0, 2.0, 3.0, 0.5]),
    shift=st.tuples(st.floats(-3, 3), st.floats(-3, 3)),
    points=st.lists(st.tuples(st.floats(-5, 12), st.floats(-5, 12)), min_size=1, max_size=12),
)
def test_offroad_matches_reference_on_small_maps(raster, scale, shift, points) -> None:  # type: ignore[no-untyped-def]
    """Centre lookup (floor of the affine pixel coordinates, outside the raster = off-road) on random maps."""
    drivable = torch.tensor(raster, dtype=torch.uint8)
    layers = torch.stack([drivable, torch.zeros_like(drivable), torch.zeros_like(drivable)])[None]
    transform = torch.tensor([[[scale, 0.0, shift[0]], [0.0, scale, shift[1]], [0.0, 0.0, 1.0]]])
    scene_map = MapRaster(raster=layers, world_to_pixel=transform)
    a = len(points)
    xy = torch.tensor(points, dtype=torch.float32).reshape(1, a, 1, 2)
    states = torch.cat([xy, torch.zeros(1, a, 1, 2)], -1)
    scenario = ScenarioTensor(states=states, valid=torch.ones(1, a, 1, dtype=torch.bool),
                              extent=torch.full((1, a, 2), 2.0), agent_type=torch.ones(1, a, dtype=torch.long),
                              controlled=torch.ones(1, a, dtype=torch.bool), map=scene_map)
    expected = reference_offroad(scene_map, scenario.xy, scenario.valid)
    assert np.array_equal(offroad_per_step(scenario, "center").numpy(), expected)


def test_offroad_lookup_is_not_fooled_by_float32_rounding() -> None:
    """x = 10933589 * 2**-15 m (a float32 value) maps to pixel row 3x - 995 = 5.99997, i.e. row 5; a float32
    transform rounds 3x to 1001 and lands in row 6."""
    raster = torch.zeros(1, 3, 10, 4, dtype=torch.uint8)
    raster[0, 0, 5] = 1  # only row 5 is drivable
    scene_map = MapRaster(raster=raster, world_to_pixel=torch.tensor([[[3.0, 0, -995], [0, 3, 0], [0, 0, 1]]]))
    states = torch.tensor([[[[10933589 * 2.0**-15, 0.5, 0.0, 0.0]]]])
    scenario = ScenarioTensor(states=states, valid=torch.ones(1, 1, 1, dtype=torch.bool),
                              extent=torch.full((1, 1, 2), 2.0), agent_type=torch.ones(1, 1, dtype=torch.long),
                              controlled=torch.ones(1, 1, dtype=torch.bool), map=scene_map)
    assert not reference_offroad(scene_map, scenario.xy, scenario.valid).any()
    assert not offroad_per_step(scenario, "center").any()


# -------------------------------------------------------------------------------------- histograms
def _centres(spec: HistogramSpec) -> np.ndarray:
    edges = np.linspace(spec.low, spec.high, spec.num_bins + 1)
    return (edges[:-1] + edges[1:]) / 2


weights = st.lists(st.floats(0.0, 1.0), min_size=20, max_size=20).filter(lambda w: sum(w) > 1e-3)


@settings(max_examples=200, deadline=None)
@given(h1=weights, h2=weights, spec=st.sampled_from(list(SPECS.values())))
def test_histogram_distance_equals_scipy_wasserstein(h1, h2, spec) -> None:  # type: ignore[no-untyped-def]
    expected = scipy_stats.wasserstein_distance(_centres(spec), _centres(spec), h1, h2)
    got = histogram_distance(torch.tensor(h1, dtype=torch.float64), torch.tensor(h2, dtype=torch.float64), spec)
    assert got == pytest.approx(expected, abs=1e-9)
    same = histogram_distance(torch.tensor(h1, dtype=torch.float64), torch.tensor(h1, dtype=torch.float64), spec)
    assert same == pytest.approx(0.0, abs=1e-12)


def test_histogram_distance_of_an_empty_histogram_is_nan() -> None:
    empty, full = torch.zeros(20, dtype=torch.float64), torch.ones(20, dtype=torch.float64)
    assert math.isnan(histogram_distance(empty, full, SPECS["jerk"]))


def _away_from_edges(value: float, spec: HistogramSpec) -> float:
    """Move ``value`` off a bin edge by 1e-6: a value within rounding of an interior edge may land in either bin
    (the SDK bins by ``floor((x - low) / width)``, numpy by comparing with rounded edges)."""
    edges = np.linspace(spec.low, spec.high, spec.num_bins + 1)
    return value + 1e-6 if np.abs(edges[1:-1] - value).min() < 1e-9 else value


@settings(max_examples=150, deadline=None)
@given(
    data=st.data(),
    shape=st.tuples(st.integers(1, 4), st.integers(1, 5), st.integers(1, 6)),
    spec=st.sampled_from(list(SPECS.values())),
)
def test_scene_histogram_equals_numpy(data, shape, spec) -> None:  # type: ignore[no-untyped-def]
    """Per-scene np.histogram over [low, high] (outside dropped, high in the last bin), each scene normalized,
    empty scenes 0, averaged over all scenes."""
    span = spec.high - spec.low
    size = int(np.prod(shape))
    raw = data.draw(st.lists(st.one_of(st.floats(spec.low - span / 4, spec.high + span / 4),
                                       st.sampled_from([spec.low, spec.high, (spec.low + spec.high) / 2])),
                             min_size=size, max_size=size))
    values = np.array([_away_from_edges(v, spec) for v in raw]).reshape(shape)
    mask = np.array(data.draw(st.lists(st.booleans(), min_size=size, max_size=size))).reshape(shape)
    expected = np.zeros(spec.num_bins)
    for scene in range(shape[0]):
        counts, _ = np.histogram(values[scene][mask[scene]], bins=spec.num_bins, range=(spec.low, spec.high))
        if counts.sum():
            expected += counts / counts.sum()
    expected /= shape[0]
    got = scene_histogram(torch.from_numpy(values), torch.from_numpy(mask), spec)
    np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-12)


def test_scene_histogram_bin_boundaries() -> None:
    """low goes into the first bin, high into the last, values outside are dropped, 0 opens the middle bin."""
    spec = SPECS["lon_acc"]
    values = torch.tensor([[spec.low, spec.high, 0.0, spec.low - 1e-9, spec.high + 1e-9]], dtype=torch.float64)
    hist = scene_histogram(values, torch.ones_like(values, dtype=torch.bool), spec) * 3
    expected = torch.zeros(20, dtype=torch.float64)
    expected[[0, 19, 10]] = 1
    assert torch.allclose(hist, expected)


# ---------------------------------------------------------------------------------- ctg kinematics
def _one_agent(xy: torch.Tensor, yaw: float) -> ScenarioTensor:
    """One scene, one agent, positions ``xy (T, 2)`` at 0.1 s, every step valid, no map."""
    t = xy.shape[0]
    states = torch.cat([xy, torch.zeros(t, 1, dtype=xy.dtype), torch.full((t, 1), yaw, dtype=xy.dtype)], -1)
    return ScenarioTensor(states=states[None, None].float(), valid=torch.ones(1, 1, t, dtype=torch.bool),
                          extent=torch.tensor([[[4.0, 2.0]]]), agent_type=torch.ones(1, 1, dtype=torch.long),
                          controlled=torch.ones(1, 1, dtype=torch.bool))


def test_ctg_kinematics_quirk_constant_acceleration() -> None:
    """Under a constant 1 m/s^2 acceleration, the extrapolated first samples give a = 0 at samples 0 and 1, the
    true |a| = 1 afterwards; lon/lat use the world yaw; jerk is d|a|/dt (2 at sample 2, 0 after)."""
    time_s = torch.arange(101, dtype=torch.float64) * 0.1
    distance = 2.0 * time_s + 0.5 * time_s**2
    xy = torch.stack([distance * math.cos(0.3), distance * math.sin(0.3)], -1)
    quantities, sample_valid, moving = kinematics(_one_agent(xy, 0.3), "ctg")
    lon, lat, jerk = (quantities[k][0, 0].double() for k in ("lon_acc", "lat_acc", "jerk"))
    assert lon[:2].tolist() == [0.0, 0.0] and lat[:2].tolist() == [0.0, 0.0] and jerk[:2].tolist() == [0.0, 0.0]
    torch.testing.assert_close(lon[2:], torch.full((19,), math.cos(0.3), dtype=torch.float64), atol=1e-4, rtol=0)
    torch.testing.assert_close(lat[2:], torch.full((19,), math.sin(0.3), dtype=torch.float64), atol=1e-4, rtol=0)
    assert jerk[2].item() == pytest.approx(2.0, abs=1e-3)
    torch.testing.assert_close(jerk[3:], torch.zeros(18, dtype=torch.float64), atol=1e-3, rtol=0)
    assert sample_valid.all() and moving.all()


# ------------------------------------------------------------------------------------- reward cost
@pytest.fixture(scope="module")
def synthetic_rollout():  # type: ignore[no-untyped-def]
    """Log replay of a synthetic 1-scene, 13.1 s scenario (two agents driving side by side at 5 m/s, no map)."""
    time_s = torch.arange(131, dtype=torch.float32) * 0.1

    def lane(y: float) -> torch.Tensor:
        return torch.stack([5.0 * time_s, torch.full_like(time_s, y), torch.full_like(time_s, 5.0),
                            torch.zeros_like(time_s)], -1)

    scenario = ScenarioTensor(
        states=torch.stack([lane(0.0), lane(10.0)])[None], valid=torch.ones(1, 2, 131, dtype=torch.bool),
        extent=torch.full((1, 2, 2), 3.0), agent_type=torch.ones(1, 2, dtype=torch.long),
        controlled=torch.ones(1, 2, dtype=torch.bool), current_index=30,
    )
    return log_rollout(scenario)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(r=st.floats(-1.0, 1.0))
def test_constant_reward_gives_linear_cost(synthetic_rollout, r) -> None:  # type: ignore[no-untyped-def]
    seen = []

    def reward_fn(s: ScenarioTensor) -> torch.Tensor:
        seen.append((s.num_steps, s.dt))
        return torch.full((s.num_scenes, s.num_steps), r, dtype=torch.float64)

    result = RewardCostMetric(reward_fn).compute(synthetic_rollout)
    assert seen == [(20, pytest.approx(0.5))]  # 10 s sampled at 2 Hz
    assert result.values["reward_cost"] == pytest.approx(20 * (1 - r) / 2, abs=1e-9)
    assert result.values["reward_mean"] == pytest.approx(r, abs=1e-12)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda s: torch.zeros(s.num_scenes, s.num_steps + 1), "shape"),
        (lambda s: torch.zeros(s.num_scenes), "shape"),
        (lambda s: torch.zeros(s.num_scenes, s.num_agents, s.num_steps), "shape"),
        (lambda s: torch.full((s.num_scenes, s.num_steps), 1.5), r"\[-1, 1\]"),
        (lambda s: torch.full((s.num_scenes, s.num_steps), -2.0), r"\[-1, 1\]"),
        (lambda s: torch.full((s.num_scenes, s.num_steps), float("nan")), r"\[-1, 1\]"),
    ],
)
def test_bad_reward_fn_raises(synthetic_rollout, make, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=match):
        RewardCostMetric(make).compute(synthetic_rollout)


# ------------------------------------------------------------------------------------- speed against the log
def test_speed_metric_on_log_replay_and_a_slowed_copy(synthetic_rollout) -> None:  # type: ignore[no-untyped-def]
    """Log replay runs at the log's pace (ratio 1, same stopped share); a copy at 40 % speed whose second
    agent stops for the last steps gives the pooled speed ratio and one stopped agent of two."""
    values = SpeedMetric().compute(synthetic_rollout).values
    assert values["speed_ratio"] == pytest.approx(1.0)
    assert values["stopped_share"] == values["stopped_share_logged"] == 0.0
    states = synthetic_rollout.simulated.states.clone()
    states[..., 2] *= 0.4
    states[0, 1, -5:, 2] = 0.0
    slowed = dataclasses.replace(synthetic_rollout,
                                 simulated=synthetic_rollout.simulated.replace_unchecked(states=states))
    values = SpeedMetric().compute(slowed).values
    window = slice(synthetic_rollout.start_index + 1, synthetic_rollout.end_index + 1)
    expected = states[0, :, window, 2].double().sum() / synthetic_rollout.logged.states[0, :, window, 2].double().sum()
    assert values["speed_ratio"] == pytest.approx(float(expected))
    assert values["stopped_share"] == 0.5 and values["stopped_share_logged"] == 0.0


def test_speed_metric_splits_turning_from_straight_agents(synthetic_rollout) -> None:  # type: ignore[no-untyped-def]
    """An agent whose logged heading turns by more than TURN_RAD over the window counts as turning: slowing only it
    moves ``speed_ratio_turning`` and leaves ``speed_ratio_straight`` at 1; with no turning agent the turning ratio
    is NaN (no scene has one), and a turn of just under TURN_RAD is straight."""
    from trafficrlhf_sdk.metrics.speed import TURN_RAD

    values = SpeedMetric().compute(synthetic_rollout).values
    assert math.isnan(values["speed_ratio_turning"]) and values["speed_ratio_straight"] == pytest.approx(1.0)
    for turn, turning in ((TURN_RAD + 0.05, True), (TURN_RAD - 0.05, False), (-(TURN_RAD + 0.05), True)):
        logged = synthetic_rollout.logged.states.clone()
        first, last = synthetic_rollout.start_index + 1, synthetic_rollout.end_index  # the window's steps
        logged[0, 1, first:last + 1, 3] = torch.linspace(0.0, turn, last + 1 - first)  # heading only
        simulated = synthetic_rollout.simulated.states.clone()
        simulated[0, 1, :, 2] *= 0.5
        rollout = dataclasses.replace(synthetic_rollout,
                                      logged=synthetic_rollout.logged.replace_unchecked(states=logged),
                                      simulated=synthetic_rollout.simulated.replace_unchecked(states=simulated))
        values = SpeedMetric().compute(rollout).values
        assert values["speed_ratio"] == pytest.approx(0.75)
        if turning:
            assert values["speed_ratio_turning"] == pytest.approx(0.5)
            assert values["speed_ratio_straight"] == pytest.approx(1.0)
        else:
            assert math.isnan(values["speed_ratio_turning"])
            assert values["speed_ratio_straight"] == pytest.approx(0.75)


def test_failure_rate_is_split_between_agents_that_turn_in_the_log_and_the_others() -> None:
    """Three agents in parallel lanes; the simulated agent 1 drives on top of agent 0, so both collide. With agent
    2 turning in the log, the turning agents' failure rate is 0 and the others' 1; with agent 0 turning, 1 and
    0.5. The split uses the speed metric's own TURN_RAD."""
    from trafficrlhf_sdk.metrics.turns import TURN_RAD

    time_s = torch.arange(131, dtype=torch.float32) * 0.1

    def lane(y: float) -> torch.Tensor:
        return torch.stack([5.0 * time_s, torch.full_like(time_s, y), torch.full_like(time_s, 5.0),
                            torch.zeros_like(time_s)], -1)

    drivable = MapRaster(raster=torch.ones(1, 1, 100, 100, dtype=torch.uint8), layers=("drivable",),
                         world_to_pixel=torch.tensor([[[1.0, 0.0, 10.0], [0.0, 1.0, 10.0], [0.0, 0.0, 1.0]]]))
    scenario = ScenarioTensor(
        states=torch.stack([lane(0.0), lane(10.0), lane(20.0)])[None], valid=torch.ones(1, 3, 131, dtype=torch.bool),
        extent=torch.full((1, 3, 2), 3.0), agent_type=torch.ones(1, 3, dtype=torch.long),
        controlled=torch.ones(1, 3, dtype=torch.bool), current_index=30, map=drivable)
    replay = log_rollout(scenario)
    simulated = replay.simulated.states.clone()
    simulated[0, 1, 31:, 1] = 0.5  # agent 1 drives into agent 0
    for turner, expected in ((2, (0.0, 1.0)), (0, (1.0, 0.5))):
        logged = replay.logged.states.clone()
        logged[0, turner, 31:, 3] = torch.linspace(0.0, TURN_RAD + 0.1, 100)
        rollout = dataclasses.replace(replay, simulated=replay.simulated.replace_unchecked(states=simulated),
                                      logged=replay.logged.replace_unchecked(states=logged))
        values = FailureMetric().compute(rollout).values
        assert values["failure_rate"] == pytest.approx(2 / 3)
        assert (values["failure_rate_turning"], values["failure_rate_straight"]) == pytest.approx(expected)
    assert math.isnan(FailureMetric().compute(replay).values["failure_rate_turning"])  # nobody turns


def test_pooled_speed_ratio_sums_over_scenes_and_is_not_swung_by_a_slow_scene(  # type: ignore[no-untyped-def]
        synthetic_rollout) -> None:
    """Two scenes: the first at the log's pace, the second's logged agents crawl at 0.2 m/s and its simulated ones at
    0.6 m/s. The mean of per-scene ratios reads 2 (1 and 3); the pooled ratio is the sums' quotient, counted here
    agent by agent and step by step, and stays near 1; an agent that is not controlled or a step the log lacks
    does not count."""
    from trafficrlhf_sdk.metrics.speed import pooled_speed_ratio

    assert pooled_speed_ratio(synthetic_rollout) == pytest.approx(1.0)
    sim, log = synthetic_rollout.simulated, synthetic_rollout.logged
    sim_states, log_states = sim.states.repeat(2, 1, 1, 1), log.states.repeat(2, 1, 1, 1)
    log_states[1, :, :, 2], sim_states[1, :, :, 2] = 0.2, 0.6
    valid = log.valid.repeat(2, 1, 1)
    valid[0, 0, -10:] = False  # the log lacks agent 0's last steps in scene 0
    controlled = torch.tensor([[True, True], [True, False]])  # scene 1's agent 1 is not driven
    sim_states[1, 1, :, 2] = 50.0  # (it would move the ratio if it counted)
    rollout = dataclasses.replace(
        synthetic_rollout, controlled=controlled,
        simulated=sim.replace_unchecked(states=sim_states, valid=sim.valid.repeat(2, 1, 1),
                                        extent=sim.extent.repeat(2, 1, 1), agent_type=sim.agent_type.repeat(2, 1),
                                        controlled=controlled),
        logged=log.replace_unchecked(states=log_states, valid=valid, extent=log.extent.repeat(2, 1, 1),
                                     agent_type=log.agent_type.repeat(2, 1), controlled=controlled))
    sim_sum = log_sum = 0.0
    for b in range(2):
        for a in range(2):
            for t in range(rollout.start_index + 1, rollout.end_index + 1):
                if controlled[b, a] and valid[b, a, t]:
                    sim_sum += abs(float(sim_states[b, a, t, 2]))
                    log_sum += abs(float(log_states[b, a, t, 2]))
    assert pooled_speed_ratio(rollout) == pytest.approx(sim_sum / log_sum)
    assert SpeedMetric().compute(rollout).values["speed_ratio"] == pytest.approx(2.0)
    assert pooled_speed_ratio(rollout) < 1.05
    assert pooled_speed_ratio(rollout, turning=False) == pytest.approx(pooled_speed_ratio(rollout))  # none turns
    assert math.isnan(pooled_speed_ratio(rollout, turning=True))


def test_first_failures_match_the_reference_flags(case) -> None:  # type: ignore[no-untyped-def]
    """The first failing step per controlled agent, from the slow per-step references (shapely, pixel lookup)."""
    from trafficrlhf_sdk.evaluation.failures import first_failures

    found = first_failures(case.rollout)
    collision, offroad = case.failure["collision_steps"], case.failure["offroad_steps"]
    controlled = case.rollout.controlled.numpy()
    first = case.rollout.start_index + 1
    for b, a in np.ndindex(*controlled.shape):
        failing = np.flatnonzero(collision[b, a] | offroad[b, a]) if controlled[b, a] else []
        if len(failing) == 0:
            assert int(found.step[b, a]) == -1 and not found.collision[b, a] and not found.offroad[b, a]
            continue
        t = int(failing[0])
        assert int(found.step[b, a]) == first + t, (b, a)
        assert bool(found.collision[b, a]) == bool(collision[b, a, t])
        assert bool(found.offroad[b, a]) == bool(offroad[b, a, t])


def test_failure_figure_names_who_failed_and_when(case, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.evaluation.failures import first_failures, render_failures, save_failure_png

    found = first_failures(case.rollout)
    index = int((found.step >= 0).sum(-1).argmax())
    failing = int((found.step[index] >= 0).sum())
    title = render_failures(case.rollout, index, found).axes[0].get_title()
    assert f"{failing} of {int(case.rollout.controlled[index].sum())} controlled agents fail" in title
    if failing:  # shown at the first failure, each failing agent named with its kind
        first = int(found.step[index][found.step[index] >= 0].min())
        assert f"shown at +{(first - case.rollout.start_index) * case.rollout.logged.dt:.1f} s" in title
        assert ("collision at" in title) or ("off-road at" in title)
    path = save_failure_png(case.rollout, index, tmp_path / "x.png", failures=found)
    assert open(path, "rb").read(8) == b"\x89PNG\r\n\x1a\n"


def test_collisions_split_by_partner_kind(case) -> None:  # type: ignore[no-untyped-def]
    """``collision_rate_own`` / ``collision_rate_replayed``: per controlled agent, whether any overlapping partner
    (listed pair by pair, the list checked against shapely above) is driven by the policy or replayed; every
    collision has one kind or both."""
    rollout = case.rollout
    result = FailureMetric().compute(rollout)
    window = _window(rollout)
    controlled = rollout.controlled
    own = np.zeros(tuple(controlled.shape), dtype=bool)
    replayed = np.zeros_like(own)
    for b, i, j, _ in zip(*(t.tolist() for t in colliding_pairs(window.xy, window.yaw, window.extent, window.valid))):
        for me, other in ((i, j), (j, i)):
            (own if controlled[b, other] else replayed)[b, me] = True
    mask = controlled.numpy()
    collided = result.extras["collided"].numpy() & mask
    assert np.array_equal((own | replayed) & mask, collided)
    for key, flags in (("collision_rate_own", own), ("collision_rate_replayed", replayed)):
        per_scene = [float((flags[b] & mask[b]).sum() / mask[b].sum()) if mask[b].any() else math.nan
                     for b in range(mask.shape[0])]
        got = result.per_scene[key].tolist()
        assert [v != v for v in got] == [v != v for v in per_scene], key
        assert np.allclose([v for v in got if v == v], [v for v in per_scene if v == v]), key
    assert result.values["collision_rate_own"] + result.values["collision_rate_replayed"] >= \
        result.values["collision_rate"] - 1e-12
