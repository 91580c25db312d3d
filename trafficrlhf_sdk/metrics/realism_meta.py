"""The field's realism meta-metric (WOSAC style): how likely the logged behaviour is under K simulated rollouts.

For every evaluated (controlled) agent, the simulated values of a feature, pooled over the K rollouts and the
simulated steps, form a fixed-bin histogram with an additive pseudo-count; each logged value of that agent is
scored by the probability of its bin. A feature's score in a scene is ``exp(mean log-likelihood)`` over the
scene's evaluated agents and steps; collision and off-road are per-agent "ever" flags scored against the
Bernoulli of the K simulated flags. The meta-metric is the weighted sum of the feature scores (2024 weights, no
traffic lights), averaged over scenes.

Kinematics are taken at the data's native rate (``native_dt``: nuScenes keyframes are 2 Hz, so the 0.1 s grid
is sampled every 0.5 s for both the log and the rollouts): central differences of interpolated positions would
put an acceleration spike at every keyframe. The score depends on K (few rollouts lower its ceiling): compare
models only at equal K.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator

from trafficrlhf_sdk.metrics.base import Metric, MetricResult
from trafficrlhf_sdk.metrics.geometry import box_corners
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.simulation.simulator import Rollout

__all__ = ["META_FEATURES", "MetaFeature", "RealismMetaConfig", "RealismMetaMetric", "meta_features",
           "road_edge_features", "rounded_box_distance", "signed_road_edge_distance"]

MAX_TTC_S = 5.0
CORNER_ROUNDING = 0.7
FOLLOW_MAX_YAW = math.radians(75.0)
FOLLOW_ALIGNED_YAW = math.radians(10.0)
FOLLOW_LATERAL_M = 0.5
FAR = 1e10


class MetaFeature(BaseModel):
    """One feature of the meta-metric: its estimator (histogram or Bernoulli), range, bins and weight."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: str = Field(..., pattern="^(histogram|bernoulli)$", description="'histogram' or 'bernoulli'.")
    low: float = Field(0.0, description="Histogram range start; values below are clipped into the first bin.")
    high: float = Field(1.0, description="Histogram range end; values above are clipped into the last bin.")
    bins: int = Field(2, ge=1, description="Number of equal-width histogram bins.")
    weight: float = Field(..., ge=0, description="Weight in the meta-metric (the weights sum to 1).")


# the 2024 configuration (shared/reference rlhf-anchors.md §5.5): nuScenes has no traffic-light states
META_FEATURES: dict[str, MetaFeature] = {
    "linear_speed": MetaFeature(kind="histogram", low=0.0, high=25.0, bins=10, weight=0.05),
    "linear_acceleration": MetaFeature(kind="histogram", low=-12.0, high=12.0, bins=11, weight=0.05),
    "angular_speed": MetaFeature(kind="histogram", low=-0.628, high=0.628, bins=11, weight=0.05),
    "angular_acceleration": MetaFeature(kind="histogram", low=-3.14, high=3.14, bins=11, weight=0.05),
    "distance_to_nearest_object": MetaFeature(kind="histogram", low=-5.0, high=40.0, bins=10, weight=0.10),
    "collision_indication": MetaFeature(kind="bernoulli", weight=0.25),
    "time_to_collision": MetaFeature(kind="histogram", low=0.0, high=MAX_TTC_S, bins=10, weight=0.10),
    "distance_to_road_edge": MetaFeature(kind="histogram", low=-20.0, high=40.0, bins=10, weight=0.10),
    "offroad_indication": MetaFeature(kind="bernoulli", weight=0.25),
}


class RealismMetaConfig(BaseModel):
    """How :class:`RealismMetaMetric` scores K rollouts of the same scenes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rollouts: int = Field(8, ge=1, description="K: rollouts per scene, stacked rollout-major along B.")
    native_dt: float | None = Field(
        None, gt=0, description="Seconds between the data's own samples; None reads the scenario's "
        "extras['native_dt'] (0.5 for nuscenes_pred keyframes), else its dt.")
    pseudocount: float = Field(0.1, gt=0, description="Additive smoothing added to every histogram bin.")
    features: dict[str, MetaFeature] = Field(
        default_factory=lambda: dict(META_FEATURES), description="Features, their estimators and weights.")
    max_pair_elements: int = Field(
        20_000_000, ge=1000, description="Scenes are processed in chunks of at most this many agent-pair-steps.")

    @model_validator(mode="after")
    def _known_features(self) -> RealismMetaConfig:
        unknown = sorted(set(self.features) - set(META_FEATURES))
        if unknown:
            raise ValueError(f"`features` names unknown feature(s) {unknown}; known: {sorted(META_FEATURES)}.")
        total = sum(f.weight for f in self.features.values())
        if not total > 0:
            raise ValueError(f"`features` weights sum to {total}; give at least one feature a positive weight.")
        return self


def _central_diff(x: torch.Tensor) -> torch.Tensor:
    """``(x[t+1] - x[t-1]) / 2`` along the last axis, NaN at both ends."""
    out = torch.full_like(x, math.nan)
    out[..., 1:-1] = (x[..., 2:] - x[..., :-2]) / 2
    return out


def _central_valid(valid: torch.Tensor) -> torch.Tensor:
    out = torch.zeros_like(valid)
    out[..., 1:-1] = valid[..., 2:] & valid[..., :-2]
    return out


def kinematic_features(xy: torch.Tensor, yaw: torch.Tensor, valid: torch.Tensor, dt: float
                       ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Linear and angular speed and acceleration ``(..., T)`` by central differences at step ``dt`` (s), and
    their validity (speed: both neighbours valid; acceleration: that rule applied twice)."""
    step = torch.linalg.vector_norm(_central_diff(xy.transpose(-1, -2)), dim=-2)  # (..., T)
    speed = step / dt
    accel = _central_diff(speed) / dt
    dh_step = wrap_angle(2 * _central_diff(yaw)) / 2
    ang_speed = dh_step / dt
    ang_accel = wrap_angle(2 * _central_diff(dh_step)) / 2 / dt**2
    v1 = _central_valid(valid)
    v2 = _central_valid(v1)
    return ({"linear_speed": speed, "linear_acceleration": accel, "angular_speed": ang_speed,
             "angular_acceleration": ang_accel},
            {"linear_speed": v1, "linear_acceleration": v2, "angular_speed": v1, "angular_acceleration": v2})


def rounded_box_distance(xy_a: torch.Tensor, yaw_a: torch.Tensor, ext_a: torch.Tensor, xy_b: torch.Tensor,
                         yaw_b: torch.Tensor, ext_b: torch.Tensor) -> torch.Tensor:
    """Signed distance (m) between boxes with rounded corners, ``(P,)`` for ``P`` pairs (negative: overlap).

    Each box (centre ``xy (P, 2)``, ``yaw (P,)``, ``extent (P, 2)`` length, width) is a core rectangle shrunk by
    ``s = 0.7 · min(length, width) / 2`` on every side, grown back by a disc of radius ``s``. The distance is the
    cores' signed distance (the origin's signed distance to their Minkowski difference) less both radii:
    apart, the smallest corner-to-edge distance; overlapping, the largest separating-axis gap (minus the depth).
    """
    xy_a, xy_b = xy_a.double(), xy_b.double()
    shrink_a = CORNER_ROUNDING * ext_a.double().amin(-1) / 2
    shrink_b = CORNER_ROUNDING * ext_b.double().amin(-1) / 2
    ca = box_corners(xy_a, yaw_a.double(), ext_a.double() - 2 * shrink_a[:, None])  # (P, 4, 2)
    cb = box_corners(xy_b, yaw_b.double(), ext_b.double() - 2 * shrink_b[:, None])
    edges = torch.cat([ca[:, 1:3] - ca[:, 0:2], cb[:, 1:3] - cb[:, 0:2]], 1)  # (P, 4, 2): both boxes' edge axes
    axes = torch.stack([-edges[..., 1], edges[..., 0]], -1)
    axes = axes / torch.linalg.vector_norm(axes, dim=-1, keepdim=True).clamp_min(1e-12)
    pa = torch.einsum("pkc,pnc->pkn", axes, ca)
    pb = torch.einsum("pkc,pnc->pkn", axes, cb)
    gap = torch.maximum(pb.amin(-1) - pa.amax(-1), pa.amin(-1) - pb.amax(-1)).amax(-1)  # (P,)

    def corner_to_edges(points: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
        start = corners  # (P, 4, 2) edge k runs from corner k to corner k+1
        seg = corners.roll(-1, 1) - corners
        rel = points[:, :, None] - start[:, None]  # (P, 4 points, 4 edges, 2)
        t = ((rel * seg[:, None]).sum(-1) / (seg * seg).sum(-1).clamp_min(1e-12)[:, None]).clamp(0, 1)
        closest = start[:, None] + t[..., None] * seg[:, None]
        return torch.linalg.vector_norm(points[:, :, None] - closest, dim=-1).flatten(1).amin(-1)

    apart = torch.minimum(corner_to_edges(ca, cb), corner_to_edges(cb, ca))
    return torch.where(gap > 0, apart, gap) - shrink_a - shrink_b


EDGE_FAR_M = 41.0  # beyond the histogram range [-20, 40] m: where a layer has no pixel of the other kind


def _edge_trees(layer: np.ndarray) -> tuple[Any, Any]:
    """KD-trees of the boundary pixels of a boolean layer: drivable pixels with a 4-neighbour off it, and
    off-road pixels with a 4-neighbour on it (None where there are none). The pixel of one kind nearest to a
    pixel of the other is always such a boundary pixel: a step from it toward the query along the larger axis
    would be closer, so that neighbour is of the query's kind."""
    from scipy.spatial import cKDTree

    padded = np.pad(layer, 1, mode="edge")
    centre = padded[1:-1, 1:-1]
    differs = np.zeros_like(layer)
    for di, dj in ((0, 1), (2, 1), (1, 0), (1, 2)):
        differs |= padded[di : di + layer.shape[0], dj : dj + layer.shape[1]] != centre
    boundary = np.argwhere(differs)
    kind = layer[boundary[:, 0], boundary[:, 1]]
    on, off = boundary[kind], boundary[~kind]
    return (cKDTree(on) if len(on) else None), (cKDTree(off) if len(off) else None)


def signed_road_edge_distance(rollout_map: object, corners: torch.Tensor, scene: torch.Tensor,
                              cache: dict | None = None) -> torch.Tensor:
    """Signed distance (m) of points to the edge of the drivable layer: positive off it, negative on it.

    ``rollout_map``: a :class:`~trafficrlhf_sdk.scenario.MapRaster` with a ``drivable`` layer; ``corners``
    ``(N, 2)`` scene-frame points in scenes ``scene (N,)``. The distance is the Euclidean one from each point's
    pixel centre to the nearest pixel centre of the other kind in the raster (the value the distance transforms of
    the layer and of its complement hold there; pixel-centre precision, 1/scale m), found among the layer's
    boundary pixels with a KD-tree; a raster with no pixel of the other kind gives ``EDGE_FAR_M`` (41 m, beyond the
    meta-metric's 40 m clip). Points outside the raster count as off the road. ``cache``: a dict kept across calls
    on the same map (the trees by raster row).
    """
    drivable_index = rollout_map.layers.index("drivable")  # type: ignore[attr-defined]
    rows = rollout_map.scene_rows()  # type: ignore[attr-defined]
    m = rollout_map.world_to_pixel.to(torch.float64)[scene]  # type: ignore[attr-defined]
    ij = torch.floor(torch.einsum("nkc,nc->nk", m[:, :2, :2], corners.double()) + m[:, :2, 2]).long()
    point_rows = rows[scene]
    size = rollout_map.sizes[point_rows]  # type: ignore[attr-defined]  # each point's raster (H, W)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < size[:, 0]) & (ij[:, 1] >= 0) & (ij[:, 1] < size[:, 1])
    i = torch.minimum(ij[:, 0].clamp_min(0), size[:, 0] - 1)
    j = torch.minimum(ij[:, 1].clamp_min(0), size[:, 1] - 1)
    out = torch.zeros(len(scene), dtype=torch.float64)
    cache = {} if cache is None else cache
    order = torch.argsort(point_rows, stable=True)
    found, counts = torch.unique_consecutive(point_rows[order], return_counts=True)
    for row, picked in zip(found.tolist(), torch.split(order, counts.tolist()), strict=True):
        scale = float(rollout_map.world_to_pixel[int(scene[picked[0]]), 0, 0].abs())  # type: ignore[attr-defined]
        key = (id(rollout_map.pixels), row)  # type: ignore[attr-defined]
        if key not in cache:
            layer = rollout_map.row_raster(row)[drivable_index].numpy() > 0  # type: ignore[attr-defined]
            cache[key] = (layer, *_edge_trees(layer))
        layer, on_tree, off_tree = cache[key]
        pixels = np.stack([i[picked].numpy(), j[picked].numpy()], -1)
        on_road = layer[pixels[:, 0], pixels[:, 1]]
        values = np.empty(len(pixels), dtype=np.float32)
        for kind, tree, sign in ((on_road, off_tree, -1.0), (~on_road, on_tree, 1.0)):
            if kind.any():  # pixels, in float32 like a distance transform's map, then metres
                values[kind] = (np.float32(sign) * tree.query(pixels[kind])[0].astype(np.float32)
                                / np.float32(scale)) if tree is not None else sign * EDGE_FAR_M
        out[picked] = torch.from_numpy(values).double()
    return torch.where(inside, out, out.clamp_min(1.0 / 3.0))


def _pairs(eval_agents: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``(scene, i, j, step)`` for every evaluated agent ``i`` and other agent ``j`` both valid at ``step``."""
    a = valid.shape[1]
    others = ~torch.eye(a, dtype=torch.bool)
    mask = (valid & eval_agents[..., None])[:, :, None] & valid[:, None] & others[None, :, :, None]
    return mask.nonzero(as_tuple=True)


def meta_features(xy: torch.Tensor, yaw: torch.Tensor, valid: torch.Tensor, extent: torch.Tensor,
                  agent_type: torch.Tensor, eval_agents: torch.Tensor, dt: float, first: int,
                  scene_map: object | None = None, edge_cache: dict | None = None
                  ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Every feature of :data:`META_FEATURES` per scene, agent and step, and where each is valid.

    Args:
        xy: ``(N, A, T, 2)`` positions (m) at the native rate, history included; yaw ``(N, A, T)`` (rad); valid
            ``(N, A, T)``; extent ``(N, A, 2)``; agent_type ``(N, A)``; eval_agents bool ``(N, A)``: the agents
            scored (all valid agents take part in the interactions).
        dt: seconds per step; first: index of the first scored step (earlier steps only feed the derivatives).
        scene_map: a MapRaster of the N scenes with a ``drivable`` layer, or None (road features left out).
        edge_cache: passed to :func:`signed_road_edge_distance`.

    Returns:
        ``(values, masks)``: per feature ``(N, A, T - first)`` values (flags for the indications, per step) and
        bool validity; the road-edge features are absent without a map.
    """
    n, a, t = valid.shape
    xy, yaw = xy.double(), yaw.double()
    values, masks = kinematic_features(xy, yaw, valid, dt)
    speed = values["linear_speed"]
    distance = torch.full((n, a, t), FAR, dtype=torch.float64)
    ttc = torch.full((n, a, t), MAX_TTC_S, dtype=torch.float64)
    scene, i, j, step = _pairs(eval_agents, valid)
    if scene.numel():
        d = rounded_box_distance(xy[scene, i, step], yaw[scene, i, step], extent[scene, i],
                                 xy[scene, j, step], yaw[scene, j, step], extent[scene, j])
        flat = (scene * a + i) * t + step
        distance.view(-1).scatter_reduce_(0, flat, d, reduce="amin")
        # time to collision with the nearest box followed ahead, in the evaluated agent's frame
        heading = yaw[scene, i, step]
        rel = xy[scene, j, step] - xy[scene, i, step]
        cos, sin = torch.cos(heading), torch.sin(heading)
        rel_x = rel[:, 0] * cos + rel[:, 1] * sin
        rel_y = -rel[:, 0] * sin + rel[:, 1] * cos
        yaw_diff = wrap_angle(yaw[scene, j, step] - heading).abs()
        len_i, wid_i = extent[scene, i, 0].double(), extent[scene, i, 1].double()
        len_j, wid_j = extent[scene, j, 0].double(), extent[scene, j, 1].double()
        long_offset = len_j / 2 * torch.cos(yaw_diff).abs() + wid_j / 2 * torch.sin(yaw_diff).abs()
        lat_offset = len_j / 2 * torch.sin(yaw_diff).abs() + wid_j / 2 * torch.cos(yaw_diff).abs()
        long_distance = rel_x - len_i / 2 - long_offset
        lat_overlap = rel_y.abs() - wid_i / 2 - lat_offset
        followed = ((long_distance > 0) & (yaw_diff <= FOLLOW_MAX_YAW) & (lat_overlap < 0)
                    & ((lat_overlap < -FOLLOW_LATERAL_M) | (yaw_diff <= FOLLOW_ALIGNED_YAW)))
        if followed.any():
            f = followed.nonzero().squeeze(-1)
            nearest = torch.full((n * a * t,), math.inf, dtype=torch.float64)
            nearest.scatter_reduce_(0, flat[f], long_distance[f], reduce="amin")
            is_nearest = long_distance[f] == nearest[flat[f]]
            f = f[is_nearest]
            rel_speed = speed[scene[f], i[f], step[f]] - speed[scene[f], j[f], step[f]]
            value = torch.where(rel_speed > 0, (long_distance[f] / rel_speed).clamp(max=MAX_TTC_S),
                                torch.full_like(rel_speed, MAX_TTC_S))
            ttc.view(-1).scatter_reduce_(0, flat[f], value, reduce="amin")
    values["distance_to_nearest_object"] = distance
    masks["distance_to_nearest_object"] = valid
    values["collision_indication"] = (distance < 0).double()
    masks["collision_indication"] = valid
    values["time_to_collision"] = ttc
    masks["time_to_collision"] = valid & (agent_type == AgentType.VEHICLE)[..., None]
    if scene_map is not None and "drivable" in getattr(scene_map, "layers", ()):
        edge_values, edge_masks = road_edge_features(xy, yaw, valid, extent, eval_agents, scene_map, edge_cache)
        values.update(edge_values)
        masks.update(edge_masks)
    return ({k: v[:, :, first:] for k, v in values.items()}, {k: m[:, :, first:] for k, m in masks.items()})


def road_edge_features(xy: torch.Tensor, yaw: torch.Tensor, valid: torch.Tensor, extent: torch.Tensor,
                       eval_agents: torch.Tensor, scene_map: object, edge_cache: dict | None = None
                       ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """``distance_to_road_edge`` (the largest signed distance of the box's four corners; ``-FAR`` where not
    scored) and ``offroad_indication`` of the evaluated agents, ``(N, A, T)`` each with its validity, for the
    shapes of :func:`meta_features` (every step, history included). One call builds each map row's boundary
    trees once, so callers that chunk the pairwise features pass every scene here at once."""
    n, a, t = valid.shape
    scene_of, agent_of, step_of = (valid & eval_agents[..., None]).nonzero(as_tuple=True)
    edge = torch.full((n, a, t), -FAR, dtype=torch.float64)
    if scene_of.numel():
        corners = box_corners(xy[scene_of, agent_of, step_of].double(), yaw[scene_of, agent_of, step_of].double(),
                              extent[scene_of, agent_of].double())  # (M, 4, 2)
        per_corner = signed_road_edge_distance(scene_map, corners.reshape(-1, 2), scene_of.repeat_interleave(4),
                                                edge_cache)
        edge[scene_of, agent_of, step_of] = per_corner.reshape(-1, 4).amax(-1)
    return {"distance_to_road_edge": edge, "offroad_indication": (edge > 0).double()}, \
        {"distance_to_road_edge": valid, "offroad_indication": valid}


def _bin(values: torch.Tensor, feature: MetaFeature) -> torch.Tensor:
    clipped = values.clamp(feature.low, feature.high).nan_to_num(feature.low)
    index = ((clipped - feature.low) / (feature.high - feature.low) * feature.bins).floor().long()
    return index.clamp(0, feature.bins - 1)


def _histogram_scores(sim: torch.Tensor, sim_mask: torch.Tensor, log: torch.Tensor, log_mask: torch.Tensor,
                      feature: MetaFeature, pseudocount: float) -> torch.Tensor:
    """Per scene ``exp(mean log p)`` of the logged values ``(B, A, T)`` under each agent's histogram of the
    simulated values ``(K, B, A, T)`` pooled over rollouts and steps; NaN for a scene with no scored value."""
    k, b, a, t = sim.shape
    sim_bins = _bin(sim, feature).permute(1, 2, 0, 3).reshape(b * a, k * t)
    weights = sim_mask.permute(1, 2, 0, 3).reshape(b * a, k * t).double()
    counts = torch.zeros(b * a, feature.bins, dtype=torch.float64).scatter_add_(1, sim_bins, weights)
    prob = (counts + pseudocount) / (counts.sum(-1, keepdim=True) + pseudocount * feature.bins)
    log_p = prob.log().gather(1, _bin(log, feature).reshape(b * a, t)).reshape(b, a, t)
    mask = log_mask.double()
    total = (log_p * mask).sum((1, 2))
    count = mask.sum((1, 2))
    return torch.where(count > 0, (total / count.clamp_min(1)).exp(), torch.full_like(total, math.nan))


def _bernoulli_scores(sim_flag: torch.Tensor, log_flag: torch.Tensor, agents: torch.Tensor,
                      pseudocount: float) -> torch.Tensor:
    """Per scene ``exp(mean over agents of log p(logged flag))`` with ``p`` the smoothed share of the K simulated
    flags ``(K, B, A)``; ``agents (B, A)`` are the scored ones."""
    k = sim_flag.shape[0]
    ones = sim_flag.double().sum(0)
    p_one = (ones + pseudocount) / (k + 2 * pseudocount)
    log_p = torch.where(log_flag, p_one, 1 - p_one).log()
    mask = agents.double()
    count = mask.sum(-1)
    return torch.where(count > 0, ((log_p * mask).sum(-1) / count.clamp_min(1)).exp(),
                       torch.full_like(count, math.nan))


class RealismMetaMetric(Metric):
    """The WOSAC-style realism meta-metric of K rollouts (higher is better, at most 1).

    :meth:`compute` takes a :class:`Rollout` whose scenes are the K rollouts of B scenes stacked rollout-major
    (scene ``k * B + b`` is rollout k of scene b); the logged scenes are the first B. Values: ``realism_meta``
    (mean over scenes), ``realism_meta_<feature>`` per feature, per-scene tensors ``(B,)`` of each, and the
    ``simulated_collision_rate`` / ``simulated_offroad_rate`` (share of (rollout, agent) pairs with an event).
    """

    name = "realism_meta"
    lower_is_better = False

    def __init__(self, config: RealismMetaConfig | None = None, **options: object) -> None:
        self.config = config if config is not None else RealismMetaConfig(**options)  # type: ignore[arg-type]

    def compute(self, rollout: Rollout) -> MetricResult:
        """Score ``rollout`` (K·B scenes, rollout-major); see the class docstring."""
        return self._compute(rollout, ceiling=False)[0]

    def compute_with_ceiling(self, rollout: Rollout) -> tuple[MetricResult, MetricResult]:
        """:meth:`compute` of ``rollout`` and of the log scored against K copies of itself (the ceiling at this
        K), featurizing the logged scenes once: equal to ``compute`` of a rollout of K logged copies."""
        sim, ceiling = self._compute(rollout, ceiling=True)
        assert ceiling is not None
        return sim, ceiling

    def _compute(self, rollout: Rollout, ceiling: bool) -> tuple[MetricResult, MetricResult | None]:
        k = self.config.rollouts
        total = rollout.simulated.num_scenes
        if total % k:
            raise ValueError(f"the rollout holds {total} scenes, not a multiple of rollouts={k}; stack K rollouts "
                             "of the same B scenes rollout-major (EvaluationConfig(rollouts=K) does).")
        b = total // k
        sim, log = rollout.simulated, rollout.logged
        dt = sim.dt
        native = self.config.native_dt or float(sim.extras.get("native_dt", dt))
        stride = max(1, round(native / dt))
        start = rollout.start_index
        # native-rate grid: two samples before the start feed the derivatives; scored steps follow the start
        first_step = start - 2 * stride
        while first_step < 0:
            first_step += stride
        steps = torch.arange(first_step, rollout.end_index + 1, stride)
        first = int((steps <= start).sum())
        eval_agents = rollout.controlled[:b]
        cache: dict = {}
        sim_values, sim_masks = self._features(sim, steps, first, eval_agents.repeat(k, 1), cache)
        log_values, log_masks = self._features(log[:b], steps, first, eval_agents, cache)
        extras = {"rollouts": k, "native_stride": stride}
        result = MetricResult(*self._score(sim_values, sim_masks, log_values, log_masks, eval_agents, k), extras)
        if not ceiling:
            return result, None
        # the log's own features stand for each of its K copies (features are per scene)
        tiled_values = {key: v.repeat(k, *([1] * (v.dim() - 1))) for key, v in log_values.items()}
        tiled_masks = {key: m.repeat(k, *([1] * (m.dim() - 1))) for key, m in log_masks.items()}
        own = MetricResult(*self._score(tiled_values, tiled_masks, log_values, log_masks, eval_agents, k), extras)
        return result, own

    def _score(self, sim_values: dict[str, torch.Tensor], sim_masks: dict[str, torch.Tensor],
               log_values: dict[str, torch.Tensor], log_masks: dict[str, torch.Tensor], eval_agents: torch.Tensor,
               k: int) -> tuple[dict[str, float], dict[str, torch.Tensor]]:
        """Values and per-scene scores of K·B simulated scenes' features against the B logged scenes'."""
        b = eval_agents.shape[0]
        scores: dict[str, torch.Tensor] = {}
        for name, feature in self.config.features.items():
            if name not in log_values:
                continue
            sv = sim_values[name].reshape(k, b, *sim_values[name].shape[1:])
            sm = sim_masks[name].reshape(k, b, *sim_masks[name].shape[1:]) & log_masks[name][None]
            lv, lm = log_values[name], log_masks[name] & eval_agents[..., None]
            if feature.kind == "histogram":
                scores[name] = _histogram_scores(sv, sm, lv, lm, feature, self.config.pseudocount)
            else:
                sim_flag = ((sv > 0) & sm).any(-1)  # ever, over the steps where the log is valid
                log_flag = ((lv > 0) & lm).any(-1)
                agents = lm.any(-1)
                scores[name] = _bernoulli_scores(sim_flag, log_flag, agents, self.config.pseudocount)
        meta = self._combine(scores, b)
        values = {"realism_meta": _nanmean(meta)}
        per_scene = {"realism_meta": meta}
        for name, score in scores.items():
            values[f"realism_meta_{name}"] = _nanmean(score)
            per_scene[f"realism_meta_{name}"] = score
        for flag, key in (("collision_indication", "simulated_collision_rate"),
                          ("offroad_indication", "simulated_offroad_rate")):
            if flag in sim_values:
                scored = eval_agents.repeat(k, 1) & sim_masks[flag].any(-1)
                ever = ((sim_values[flag] > 0) & sim_masks[flag]).any(-1) & scored
                values[f"realism_meta_{key}"] = float(ever.sum() / scored.sum().clamp_min(1))
        return values, per_scene

    def _features(self, scenario: ScenarioTensor, steps: torch.Tensor, first: int, eval_agents: torch.Tensor,
                  cache: dict) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Features of ``scenario`` at ``steps``, chunked over scenes to bound the pairwise work."""
        states = scenario.states[:, :, steps]
        valid = scenario.valid[:, :, steps]
        n, a, t = valid.shape
        chunk = max(1, self.config.max_pair_elements // max(a * a * t, 1))
        step_s = float(steps[1] - steps[0]) * scenario.dt if len(steps) > 1 else scenario.dt
        values: dict[str, list[torch.Tensor]] = {}
        masks: dict[str, list[torch.Tensor]] = {}
        for lo in range(0, n, chunk):  # the pairwise features, in chunks of scenes
            part = slice(lo, min(n, lo + chunk))
            v, m = meta_features(states[part, :, :, :2], states[part, :, :, 3], valid[part], scenario.extent[part],
                                 scenario.agent_type[part], eval_agents[part], step_s, first)
            for key in v:
                values.setdefault(key, []).append(v[key])
                masks.setdefault(key, []).append(m[key])
        if scenario.map is not None and "drivable" in scenario.map.layers:  # the road edge: all scenes at once
            v, m = road_edge_features(states[..., :2].double(), states[..., 3].double(), valid, scenario.extent,
                                      eval_agents, scenario.map, cache)
            for key in v:
                values[key] = [v[key][:, :, first:]]
                masks[key] = [m[key][:, :, first:]]
        return {k: torch.cat(v) for k, v in values.items()}, {k: torch.cat(m) for k, m in masks.items()}

    def _combine(self, scores: Mapping[str, torch.Tensor], b: int) -> torch.Tensor:
        """Weighted sum per scene; a feature undefined in a scene (NaN) is left out and the weights renormalized."""
        weighted = torch.zeros(b, dtype=torch.float64)
        weights = torch.zeros(b, dtype=torch.float64)
        for name, score in scores.items():
            w = self.config.features[name].weight
            ok = ~torch.isnan(score)
            weighted += torch.where(ok, score * w, torch.zeros_like(score))
            weights += ok.double() * w
        return torch.where(weights > 0, weighted / weights.clamp_min(1e-12), torch.full_like(weights, math.nan))


def _nanmean(values: torch.Tensor) -> float:
    ok = ~torch.isnan(values)
    return float(values[ok].mean()) if ok.any() else math.nan
