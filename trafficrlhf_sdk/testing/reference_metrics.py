"""Slow, deliberately straightforward reference implementations of the closed-loop metrics.

**For tests and benchmarks only.** These functions re-derive the numbers of
:class:`~trafficrlhf_sdk.metrics.FailureMetric` (centre off-road mode) and
``RealismMetric("ctg")`` from the definitions in ``shared/reference/upstream-models-and-metrics.md`` §1.5/§2.5,
with plain Python loops, :mod:`shapely` polygons, a per-point pixel lookup, :func:`numpy.histogram` and
:func:`scipy.stats.wasserstein_distance`. They share no code with the vectorized SDK metrics (only the
:class:`~trafficrlhf_sdk.simulation.Rollout` container is read), so agreement between the two is evidence that
both implement the definitions. They are orders of magnitude slower than the SDK; never use them in a pipeline.

Definitions implemented here:

- **Collision** at a step: the agent's oriented box (centre, yaw, length x width) ``intersects`` (shapely; touching
  counts) the box of another agent of the same scene that is valid at that step.
- **Off-road** at a step: the agent's centre, mapped through the scene's ``world_to_pixel`` and floored, falls on a
  pixel that is 0 on the ``drivable`` layer or outside the raster.
- Steps ``start_index + 1 .. end_index`` of the simulated scene, valid steps only.
- Per scene: share of controlled agents that ever collide / ever go off-road / either; scalar = mean over scenes
  with at least one controlled agent (NaN if none).
- **Realism, CTG preset**: positions and yaws of steps ``start_index .. end_index`` down-sampled to 0.5 s;
  ``v = diff(p, prepend=p0 - (p1 - p0)) / dt``, ``a`` likewise from ``v``; lon/lat acceleration
  ``|a| cos(yaw)``, ``|a| sin(yaw)`` (world yaw, the upstream quirk); ``jerk = diff(|a|, same prepend) / dt``; a
  sample counts when every position it reads is valid; agents slower than 0.5 m/s at the first sample are skipped;
  20 bins on [-2, 2] m/s^2 / [-1, 1] m/s^3, values outside dropped; each scene's histogram normalized to sum 1
  (empty scenes contribute zeros) and averaged over all scenes; Wasserstein-1 distance between the logged and
  simulated histograms on the bin centres; ``realism_ctg`` = mean of the lon, lat and jerk distances.

``shapely`` and ``scipy`` are test dependencies (``pip install trafficrlhf-sdk[test]``); they are imported inside
the functions.
"""

from __future__ import annotations

import importlib
import math
from typing import Any

import numpy as np

__all__ = ["box_polygon", "reference_collisions", "reference_failure", "reference_offroad", "reference_realism_ctg"]

CTG_STAT_DT = 0.5  # s
CTG_BINS = {"speed": (0.0, 4.0), "lon_acc": (-2.0, 2.0), "lat_acc": (-2.0, 2.0), "jerk": (-1.0, 1.0)}
CTG_NUM_BINS = 20
CTG_MIN_START_SPEED = 0.5  # m/s
CTG_DISTANCE_QUANTITIES = ("lon_acc", "lat_acc", "jerk")


def _require(module: str) -> Any:
    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            f"trafficrlhf_sdk.testing.reference_metrics needs `{module}` (a test dependency); install it with "
            "`pip install trafficrlhf-sdk[test]` or `pip install shapely scipy`."
        ) from exc


def _box_polygon(polygon_cls: Any, x: float, y: float, yaw: float, length: float, width: float) -> Any:
    """A shapely polygon for the box centred at (x, y) with heading ``yaw``, written out corner by corner."""
    c, s = math.cos(yaw), math.sin(yaw)
    hl, hw = length / 2.0, width / 2.0
    corners = []
    for dx, dy in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw)):
        corners.append((x + dx * c - dy * s, y + dx * s + dy * c))
    return polygon_cls(corners)


def box_polygon(x: float, y: float, yaw: float, length: float, width: float) -> Any:
    """The shapely polygon of a box centred at (x, y) m with heading ``yaw`` (rad) and size ``length`` x ``width``
    (m), built without the SDK's geometry (an independent reference for tests)."""
    return _box_polygon(_require("shapely.geometry").Polygon, x, y, yaw, length, width)


def reference_collisions(xy: Any, yaw: Any, extent: Any, valid: Any) -> np.ndarray:
    """Per-step collision flags with shapely: for each scene, step and pair of valid agents, ``intersects``.

    Args:
        xy: ``(B, A, T, 2)`` centres (m); yaw: ``(B, A, T)``; extent: ``(B, A, 2)`` length, width;
            valid: ``(B, A, T)`` bool. Torch tensors or numpy arrays (converted to float64).

    Returns:
        bool ``(B, A, T)``: the agent's box intersects another valid agent's box at that step.
    """
    polygon_cls = _require("shapely.geometry").Polygon
    xy, yaw, extent = (np.asarray(_numpy(v), dtype=np.float64) for v in (xy, yaw, extent))
    valid = np.asarray(_numpy(valid), dtype=bool)
    num_scenes, num_agents, num_steps = valid.shape
    hit = np.zeros((num_scenes, num_agents, num_steps), dtype=bool)
    for b in range(num_scenes):
        for t in range(num_steps):
            agents = [a for a in range(num_agents) if valid[b, a, t]]
            boxes = {
                a: _box_polygon(polygon_cls, xy[b, a, t, 0], xy[b, a, t, 1], yaw[b, a, t], extent[b, a, 0],
                                extent[b, a, 1])
                for a in agents
            }
            for n, i in enumerate(agents):
                for j in agents[n + 1 :]:
                    if boxes[i].intersects(boxes[j]):
                        hit[b, i, t] = True
                        hit[b, j, t] = True
    return hit


def reference_offroad(scene_map: Any, xy: Any, valid: Any) -> np.ndarray:
    """Per-step off-road flags of every valid agent: centre pixel lookup on the ``drivable`` layer.

    Args:
        scene_map: the scenes' :class:`~trafficrlhf_sdk.scenario.MapRaster` (B scenes).
        xy: ``(B, A, T, 2)`` centres (m, scene frame); valid: ``(B, A, T)`` bool.

    For each point, ``(i, j) = floor(M[:2, :2] @ (x, y) + M[:2, 2])`` with ``M = world_to_pixel`` of its scene
    (float64 arithmetic); a point is on the road when ``0 <= i < H``, ``0 <= j < W`` and ``drivable[i, j] > 0``.

    Returns:
        bool ``(B, A, T)``: valid and off the drivable layer.
    """
    if scene_map is None:
        raise ValueError("reference_offroad needs a map raster; the scenario has `map=None`.")
    layer = scene_map.layers.index("drivable")
    rasters = [_numpy(scene_map.scene_raster(b))[layer] for b in range(scene_map.num_scenes)]  # each its own size
    transforms = np.asarray(_numpy(scene_map.world_to_pixel), dtype=np.float64)
    xy = np.asarray(_numpy(xy), dtype=np.float64)
    valid = np.asarray(_numpy(valid), dtype=bool)
    num_scenes, num_agents, num_steps = valid.shape
    off = np.zeros((num_scenes, num_agents, num_steps), dtype=bool)
    for b in range(num_scenes):
        m = transforms[b]
        raster = rasters[b]
        height, width = raster.shape
        for a in range(num_agents):
            for t in range(num_steps):
                if not valid[b, a, t]:
                    continue
                x, y = float(xy[b, a, t, 0]), float(xy[b, a, t, 1])
                i = math.floor(m[0, 0] * x + m[0, 1] * y + m[0, 2])
                j = math.floor(m[1, 0] * x + m[1, 1] * y + m[1, 2])
                on_road = 0 <= i < height and 0 <= j < width and raster[i, j] > 0
                off[b, a, t] = not on_road
    return off


def _numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):
        return value.detach().cpu().numpy()
    return np.asarray(value)


def _rates(flags: np.ndarray, controlled: np.ndarray) -> tuple[list[float], float]:
    """Per-scene share of controlled agents flagged (NaN without controlled agents) and their mean."""
    per_scene = []
    for b in range(flags.shape[0]):
        agents = [a for a in range(flags.shape[1]) if controlled[b, a]]
        per_scene.append(sum(bool(flags[b, a]) for a in agents) / len(agents) if agents else float("nan"))
    finite = [v for v in per_scene if not math.isnan(v)]
    return per_scene, (math.fsum(finite) / len(finite) if finite else float("nan"))


def reference_failure(rollout: Any) -> dict[str, Any]:
    """Failure, collision and off-road rates of ``rollout`` (slow reference for tests and benchmarks).

    Returns:
        ``failure_rate``, ``collision_rate``, ``offroad_rate`` (floats, mean over scenes with a controlled agent);
        ``per_scene`` (dict of lists); ``collided`` / ``offroad`` bool ``(B, A)`` (ever, any agent);
        ``collision_steps`` / ``offroad_steps`` bool ``(B, A, T)`` over steps ``start_index+1 .. end_index``.
    """
    sim = rollout.simulated
    lo, hi = rollout.start_index + 1, rollout.end_index + 1
    xy = _numpy(sim.xy)[:, :, lo:hi]
    yaw = _numpy(sim.yaw)[:, :, lo:hi]
    valid = _numpy(sim.valid)[:, :, lo:hi]
    collision_steps = reference_collisions(xy, yaw, _numpy(sim.extent), valid)
    offroad_steps = reference_offroad(sim.map, xy, valid)

    collided = collision_steps.any(-1)
    offroad = offroad_steps.any(-1)
    controlled = _numpy(rollout.controlled).astype(bool)
    result: dict[str, Any] = {"per_scene": {}}
    for name, flags in (("failure_rate", collided | offroad), ("collision_rate", collided), ("offroad_rate", offroad)):
        per_scene, mean = _rates(flags, controlled)
        result[name] = mean
        result["per_scene"][name] = per_scene
    result.update(collided=collided, offroad=offroad, collision_steps=collision_steps, offroad_steps=offroad_steps)
    return result


def _diff_prepend(x: np.ndarray) -> np.ndarray:
    """``np.diff`` along axis 0 with the first element linearly extrapolated: ``prepend = x0 - (x1 - x0)``."""
    return np.diff(x, axis=0, prepend=(x[0] - (x[1] - x[0]))[None])


def _ctg_histograms(scenario: Any, controlled: np.ndarray, start: int, end: int) -> dict[str, np.ndarray]:
    """Scene-normalized CTG histograms of the controlled, moving agents over steps ``start .. end``."""
    stride = max(1, round(CTG_STAT_DT / scenario.dt))
    dt = stride * scenario.dt
    xy = np.asarray(_numpy(scenario.xy), dtype=np.float64)
    yaw_all = np.asarray(_numpy(scenario.yaw), dtype=np.float64)
    valid_all = np.asarray(_numpy(scenario.valid), dtype=bool)
    num_scenes, num_agents = valid_all.shape[:2]
    total = {q: np.zeros(CTG_NUM_BINS) for q in CTG_BINS}
    for b in range(num_scenes):
        counts = {q: np.zeros(CTG_NUM_BINS) for q in CTG_BINS}
        for a in range(num_agents):
            if not controlled[b, a]:
                continue
            pos = xy[b, a, start : end + 1 : stride]
            yaw = yaw_all[b, a, start : end + 1 : stride]
            valid = valid_all[b, a, start : end + 1 : stride]
            vel = _diff_prepend(pos) / dt
            speed = np.linalg.norm(vel, axis=-1)
            if not speed[0] > CTG_MIN_START_SPEED:
                continue
            acc = _diff_prepend(vel) / dt
            acc_norm = np.linalg.norm(acc, axis=-1)
            values = {
                "speed": speed,
                "lon_acc": acc_norm * np.cos(yaw),
                "lat_acc": acc_norm * np.sin(yaw),
                "jerk": _diff_prepend(acc_norm) / dt,
            }
            # sample k reads positions max(k-3, 0) .. max(k, 1): keep it only if all of them are valid
            keep = np.array([valid[max(k - 3, 0) : max(k, 1) + 1].all() for k in range(len(valid))])
            for q, (low, high) in CTG_BINS.items():
                counts[q] += np.histogram(values[q][keep], bins=CTG_NUM_BINS, range=(low, high))[0]
        for q in CTG_BINS:
            if counts[q].sum() > 0:
                total[q] += counts[q] / counts[q].sum()
    return {q: total[q] / max(num_scenes, 1) for q in CTG_BINS}


def reference_realism_ctg(rollout: Any) -> dict[str, Any]:
    """CTG-preset realism deviation of ``rollout`` (slow reference for tests and benchmarks).

    Returns:
        ``realism_ctg`` and ``realism_ctg_<q>`` for q in lon_acc, lat_acc, jerk (floats), and ``histograms``:
        ``{"simulated": {q: (20,) array}, "logged": {...}}`` including ``speed``.
    """
    wasserstein_distance = _require("scipy.stats").wasserstein_distance
    controlled = _numpy(rollout.controlled).astype(bool)
    hists = {
        which: _ctg_histograms(getattr(rollout, which), controlled, rollout.start_index, rollout.end_index)
        for which in ("simulated", "logged")
    }
    result: dict[str, Any] = {"histograms": hists}
    distances = []
    for q in CTG_DISTANCE_QUANTITIES:
        low, high = CTG_BINS[q]
        edges = np.linspace(low, high, CTG_NUM_BINS + 1)
        centres = (edges[:-1] + edges[1:]) / 2
        logged, simulated = hists["logged"][q], hists["simulated"][q]
        if logged.sum() <= 0 or simulated.sum() <= 0:
            distance = float("nan")
        else:
            distance = float(wasserstein_distance(centres, centres, logged, simulated))
        result[f"realism_ctg_{q}"] = distance
        distances.append(distance)
    result["realism_ctg"] = sum(distances) / len(distances)
    return result
