"""What an annotator sees around each agent, as per-(agent, step) reward-model inputs (``scene_context``).

A person judging an item watches every agent's history, the map and the futures at 10 Hz. The stand-in annotator
(:mod:`~trafficrlhf_sdk.feedback.judgment`) judges pace against the agent's own recent speed, its lead and the
flow of its neighbours, lanes from the map's dividers, and events between the 2 Hz samples (a crash, a swerve). A
reward model that sees only the state at each 2 Hz sample cannot learn such a judgment, so for each item (agent
``a`` at scored step ``t``, the candidates starting after ``now = current_index``) these inputs add:

- **events so far**, each as "any since the previous scored step" and "share of the steps since now" at 10 Hz: a
  collision, the centre off the drivable area, a near miss (boxes closer than 0.3 m without touching), a short
  time to collision or headway to the agent ahead, the centre on a road divider, on a lane divider, heading more
  than 90 degrees from the agent's own heading at ``now`` or against the nearest lane centerline; whether it has
  collided or left the road at all since now (a crash stays visible); box corners off the drivable area;
- **pace**: the speed it drove at over the last second before now (distance covered), the flow of the neighbours
  heading its way and the speed of the agent it followed at now, its mean speed since now, and the log-ratio of
  that to its recent speed;
- **the lead**: bumper gap and closing speed to the nearest agent in its path at ``t``, squashed into (0, 1] and
  clipped, so that the model reads "close" or "closing" rather than memorising exact distances;
- **motion between samples**: reversals of lateral acceleration (every 0.5 s) and of longitudinal acceleration
  (every 1 s) since now, and the time since now.

All of it is computed once per batch of scenes, vectorized over scenes, agents and steps (cumulative sums over
time), and only from the scenario given: the history, the map and the futures of its agents.
"""

from __future__ import annotations

import math

import torch

from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_corner_share, offroad_per_step
from trafficrlhf_sdk.metrics.cues import near_misses_per_step, path_cues
from trafficrlhf_sdk.metrics.geometry import lane_direction
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["NUM_SCENE_CONTEXT_FEATURES", "scene_context_features"]

EVENTS = ("collision", "offroad", "near_miss", "tailgate", "road_divider", "lane_divider", "against")
NUM_SCENE_CONTEXT_FEATURES = 2 * len(EVENTS) + 2 + 2 + 9 + 2 + 3
"""Length of the per-item vector :func:`scene_context_features` returns."""

NEAR_MISS_M = 0.3
TTC_S, HEADWAY_S, DRIVING = 1.5, 0.6, 2.0  # s, s, m/s
FLOW_RADIUS_M = 30.0
SPEED_SCALE = 10.0


def _events(scenario: ScenarioTensor) -> dict[str, torch.Tensor]:
    """Per-step flags ``(B, A, T)`` (bool) of what a person notices, the lead of each agent, and the share of box
    corners off the road (float)."""
    valid = scenario.valid
    out = {"collision": collisions_per_step(scenario)}
    out["near_miss"] = near_misses_per_step(scenario, NEAR_MISS_M, out["collision"])
    cues = path_cues(scenario, TTC_S, HEADWAY_S, DRIVING)
    out.update(tailgate=cues.tailgating, lead_gap=cues.lead_gap, lead_closing=cues.lead_closing,
               lead_index=cues.lead_index)
    layers = scenario.map.layers if scenario.map is not None else ()
    zeros = torch.zeros_like(valid)
    out["offroad"] = offroad_per_step(scenario) if "drivable" in layers else zeros
    out["corners"] = offroad_corner_share(scenario).float() if "drivable" in layers else zeros.float()
    for layer in ("road_divider", "lane_divider"):
        out[layer] = scenario.map.lookup(scenario.xy, layer) if layer in layers else zeros  # type: ignore[union-attr]
    now = scenario.current_index
    yaw = scenario.yaw
    against = torch.cos(yaw - yaw[:, :, now : now + 1]) < 0
    lane_yaw, on_lane = lane_direction(scenario)
    if on_lane is not None:
        against |= on_lane & (torch.cos(yaw.double() - lane_yaw) < 0)
    out["against"] = against & (scenario.states[..., 2] > DRIVING)
    return out


def _shifted(x: torch.Tensor, k: int) -> torch.Tensor:
    """``x`` delayed by ``k`` steps along the last axis (the first ``k`` steps repeat step 0)."""
    if k <= 0:
        return x
    if k >= x.shape[-1]:
        return x[..., :1].expand(x.shape)
    return torch.cat([x[..., :1].expand(*x.shape[:-1], k), x[..., :-k]], -1)


def _accel_reversals(xy: torch.Tensor, valid: torch.Tensor, every: int, dt: float, lateral: bool,
                     threshold: float = 1.0) -> torch.Tensor:
    """``(B, A, T)``: whether the (lateral or longitudinal) acceleration over positions ``every`` steps apart
    reverses a sizeable sign at each step, compared with ``every`` steps before."""
    step = every * dt
    v1 = (xy - _shifted(xy.transpose(-1, -2), every).transpose(-1, -2)) / step  # (B, A, T, 2) velocity ending here
    v0 = _shifted(v1.transpose(-1, -2), every).transpose(-1, -2)
    acc = (v1 - v0) / step
    heading = v1 + v0
    unit = heading / torch.linalg.vector_norm(heading, dim=-1, keepdim=True).clamp_min(1e-6)
    if lateral:
        a = acc[..., 1] * unit[..., 0] - acc[..., 0] * unit[..., 1]
    else:
        a = (acc * unit).sum(-1)
    ok = valid & _shifted(valid, every) & _shifted(valid, 2 * every)
    sign = torch.sign(a) * (ok & (a.abs() > threshold))
    return (sign * _shifted(sign, every)) < 0


def scene_context_features(scenario: ScenarioTensor, scene: torch.Tensor, agent: torch.Tensor, step: torch.Tensor,
                           stride: int) -> torch.Tensor:
    """float32 ``(N, NUM_SCENE_CONTEXT_FEATURES)``: the inputs described in the module docstring for the items
    ``(scene, agent, step)`` (each ``(N,)``), scored every ``stride`` steps."""
    valid = scenario.valid
    now, dt = scenario.current_index, scenario.dt
    _, a, t = valid.shape
    after = torch.zeros(t, dtype=torch.bool)
    after[now + 1:] = True
    counted = valid & after  # (B, A, T)
    n_counted = torch.nn.functional.pad(torch.cumsum(counted.long(), -1), (1, 0))  # (B, A, T + 1)
    lo = (step - stride + 1).clamp_min(now + 1)
    hi = step + 1
    since_now = (n_counted[scene, agent, hi] - n_counted[scene, agent, now + 1]).clamp_min(1).float()
    events = _events(scenario)
    parts = []

    def window_sum(signal: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
        c = torch.nn.functional.pad(torch.cumsum((signal * counted).double(), -1), (1, 0))
        return (c[scene, agent, hi] - c[scene, agent, start]).float()

    start_now = torch.full_like(step, now + 1)
    for name in EVENTS:
        parts += [(window_sum(events[name], lo) > 0).float(), window_sum(events[name], start_now) / since_now]
    parts += [(window_sum(events["collision"], start_now) > 0).float(),
              (window_sum(events["offroad"], start_now) > 0).float()]
    parts += [window_sum(events["corners"], lo) / (hi - lo).clamp_min(1).float(),
              window_sum(events["corners"], start_now) / since_now]
    # pace: what the history showed at now, and the speed since
    states = scenario.states
    back = max(0, now - round(1.0 / dt))
    covered = torch.linalg.vector_norm(states[:, :, now, :2] - states[:, :, back, :2], dim=-1)
    seen = valid[:, :, now] & valid[:, :, back] & (now > back)
    v_hist = torch.where(seen, covered / max((now - back) * dt, 1e-9), states[:, :, now, 2] * valid[:, :, now])
    yaw0 = states[:, :, now, 3]
    xy0 = states[:, :, now, :2]
    same_way = torch.cos(yaw0[:, :, None] - yaw0[:, None, :]) > math.cos(math.pi / 4)
    near = (torch.cdist(xy0, xy0) <= FLOW_RADIUS_M) & same_way & ~torch.eye(a, dtype=torch.bool)[None]
    near &= valid[:, :, now, None] & valid[:, None, :, now]
    flow_n = near.sum(-1)
    flow = (near * v_hist[:, None, :]).sum(-1) / flow_n.clamp_min(1)
    lead_gap_now = events["lead_gap"][:, :, now]
    lead_now = events["lead_index"][:, :, now]
    v_lead = torch.where(torch.isfinite(lead_gap_now), v_hist.gather(1, lead_now), torch.zeros_like(v_hist))
    step_dist = torch.linalg.vector_norm(states[:, :, 1:, :2] - states[:, :, :-1, :2], dim=-1)
    step_dist = torch.nn.functional.pad(step_dist * (valid[:, :, 1:] & valid[:, :, :-1]), (1, 0))
    travelled = window_sum(step_dist, start_now)
    elapsed = (step - now).clamp_min(1).float() * dt
    mean_speed = travelled / elapsed
    vh = v_hist[scene, agent].float()
    parts += [vh / SPEED_SCALE, flow[scene, agent].float() / SPEED_SCALE, (flow_n[scene, agent] > 0).float(),
              (1 / (1 + lead_gap_now[scene, agent].float() / 10)), v_lead[scene, agent].float() / SPEED_SCALE,
              mean_speed / SPEED_SCALE, torch.log(mean_speed.clamp_min(0.5) / vh.clamp_min(0.5)).clamp(-2, 2),
              (mean_speed - vh) / elapsed / 3.0, elapsed / 4.0]
    gap_t = events["lead_gap"][scene, agent, step].float()
    closing_t = events["lead_closing"][scene, agent, step].float()
    has_lead = torch.isfinite(gap_t)
    parts += [torch.where(has_lead, 1 / (1 + gap_t.clamp_min(0) / 10), torch.zeros_like(gap_t)),
              torch.where(has_lead, closing_t.clamp(-10, 10) / SPEED_SCALE, torch.zeros_like(gap_t))]
    lat = _accel_reversals(states[..., :2], valid, round(0.5 / dt), dt, lateral=True)
    lon = _accel_reversals(states[..., :2], valid, round(1.0 / dt), dt, lateral=False)
    parts += [window_sum(lat, start_now) / round(0.5 / dt) / 3.0, window_sum(lon, start_now) / round(1.0 / dt) / 3.0,
              (1 - torch.exp(-window_sum(lat, lo)))]
    return torch.stack(parts, -1).float()
