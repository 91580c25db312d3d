"""The stand-in annotators' realism judgment: what a person watching an item notices, and nothing else.

An annotation item shows the map, every agent's history and, in each option, the future of every agent (the
agents a model drove move as the candidate says; the others replay their log). The judgment is a function of
exactly that: **it never reads the logged future of the agents it judges**. A person does not see it, and neither
does a reward model, so a term that depended on it would be noise to the reward model (the logged future is judged
like any candidate only where an item shows it as an option).

For each option ``k`` and controlled agent ``a`` the judgment measures, from what is on screen:

- **failures**, per agent: a collision with any other agent, or the agent's centre leaving the drivable area.
  Each failing agent adds its full weight (they are counted, not averaged over the scene), so one crash outweighs
  any style term, as it does for a person;
- **pace**: the agent's mean future speed against a band built from what is visible: its own speed over the last
  second of history (changed by at most a comfortable acceleration or braking over the window), the flow of the
  neighbours heading its way, the agent it follows, and a plausible top speed for the road;
- **stalling**: nearly stopped while it was driving, with nobody close ahead to stop for;
- **tailgating and near misses**: a short time to collision or time headway to the agent ahead, and boxes passing
  closer than ``near_miss_m`` without touching;
- **lane keeping**: time on a road divider, time on a lane divider beyond a lane change's worth, and box corners
  grazing the road edge;
- **wrong way**: heading against the lane direction where the map has lane centerlines, and turned around against
  its own heading at the start;
- **kinematics**: harsh longitudinal or lateral acceleration and jerk, stop-and-go (reversals of a sizeable
  longitudinal acceleration) and weaving (reversals of a sizeable lateral acceleration between 2 Hz samples).

The style terms are averaged over the controlled agents; the penalty is the failures plus that mean, and realism
is ``exp(-penalty)`` in (0, 1]. Accelerations and jerk are measured on positions sampled every 1 s and weaving on
positions every 0.5 s: finer differences of nuScenes' 2 Hz keyframes turn centimetre box noise into spurious jerk.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from pydantic import BaseModel, ConfigDict, Field

from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_corner_share, offroad_per_step
from trafficrlhf_sdk.metrics.cues import flow_neighbours, near_misses_per_step, path_cues, recent_speed
from trafficrlhf_sdk.metrics.geometry import lane_direction
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["FAILURE_TERMS", "STYLE_TERMS", "JudgmentConfig", "RealismJudgment", "agent_penalties",
           "judge_scenarios"]

FAILURE_TERMS = ("collision", "offroad")
"""Terms counted per failing agent."""
STYLE_TERMS = ("pace", "stall", "tailgate", "near_miss", "lane", "wrong_way", "accel", "jerk", "stop_go", "weave")
"""Terms averaged over the controlled agents."""

STAT_DT = 1.0  # s between the samples used for accelerations and jerk
WEAVE_DT = 0.5  # s between the samples used for weaving (the 2 Hz of the video's keyframes)


class JudgmentConfig(BaseModel):
    """Weights and bounds of the judgment (the noise model is added by the annotator's config)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    weight_collision: float = Field(4.0, ge=0, description="Penalty per controlled agent that collides.")
    weight_offroad: float = Field(3.0, ge=0, description="Penalty per controlled agent whose centre leaves the "
                                  "drivable area.")
    weight_pace: float = Field(2.0, ge=0, description="Penalty per unit of pace error: |log(speed / band edge)| "
                               "outside the plausible band, over 0.3, capped at 3.")
    pace_tolerance: float = Field(0.15, ge=0, description="Pace error (|log speed ratio|) noticed by nobody.")
    comfort_accel: float = Field(2.0, gt=0, description="Speed change a driver makes unprompted (m/s^2): the band "
                                 "around the agent's own recent speed widens by this over the window (95 % of "
                                 "logged nuScenes train agents change their mean speed over 4 s by less).")
    road_max_speed: float = Field(20.0, gt=0, description="Plausible top speed on the mapped roads (m/s).")
    flow_radius_m: float = Field(30.0, gt=0, description="Neighbours within this distance at the start, heading "
                                 "within 45 degrees of the agent, make its flow.")
    lead_range_m: float = Field(40.0, gt=0, description="An agent in the path ahead within this gap is followed.")
    weight_stall: float = Field(2.0, ge=0, description="Penalty per unit share of time stalled without reason.")
    stall_speed: float = Field(2.0, ge=0, description="The agent drove at the start above this speed (m/s); "
                               "below 0.5 m/s later it stalls, unless someone is within `stall_gap_m` ahead.")
    stall_gap_m: float = Field(12.0, ge=0, description="A stop behind an agent this close ahead (m) is a reason.")
    weight_tailgate: float = Field(2.0, ge=0, description="Penalty per unit share of time tailgating.")
    ttc_s: float = Field(1.5, gt=0, description="Tailgating: time to collision to the agent ahead below this (s).")
    headway_s: float = Field(0.6, gt=0, description="Tailgating: time headway below this (s) while driving above "
                             "`stall_speed`.")
    weight_near_miss: float = Field(2.0, ge=0, description="Penalty per unit share of time passing another box "
                                    "closer than `near_miss_m` without touching it.")
    near_miss_m: float = Field(0.3, ge=0, description="Clearance (m) between boxes that looks like a near miss.")
    weight_lane: float = Field(1.5, ge=0, description="Penalty per unit of lane keeping error: share of time on a "
                               "road divider, on a lane divider beyond `lane_change_s`, and box corners off-road.")
    lane_change_s: float = Field(1.5, ge=0, description="Time on a lane divider that a lane change takes (s).")
    weight_wrong_way: float = Field(3.0, ge=0, description="Penalty per unit share of time driving against the "
                                    "lane direction or turned around against the agent's heading at the start.")
    weight_accel: float = Field(1.5, ge=0, description="Penalty per unit of mean relative acceleration excess.")
    weight_jerk: float = Field(1.0, ge=0, description="Penalty per unit of mean relative jerk excess.")
    max_lon_accel: float = Field(3.0, gt=0, description="Plausible |longitudinal acceleration| bound (m/s^2).")
    max_lat_accel: float = Field(3.0, gt=0, description="Plausible |lateral acceleration| bound (m/s^2).")
    max_jerk: float = Field(3.0, gt=0, description="Plausible |longitudinal jerk| bound (m/s^3).")
    weight_stop_go: float = Field(0.5, ge=0, description="Penalty per reversal of a longitudinal acceleration above "
                                  "1 m/s^2 (per agent, capped at 3).")
    weight_weave: float = Field(1.0, ge=0, description="Penalty per reversal of a lateral acceleration above "
                                "`weave_accel` between 2 Hz samples (per agent, capped at 3).")
    weave_accel: float = Field(1.0, gt=0, description="Lateral acceleration (m/s^2) of a visible swerve.")

    def weight(self, term: str) -> float:
        """The weight of ``term`` (one of :data:`FAILURE_TERMS` or :data:`STYLE_TERMS`)."""
        return float(getattr(self, f"weight_{term}"))


@dataclass(frozen=True)
class RealismJudgment:
    """Realism ``(K,)`` in (0, 1] of K options, and each term per option ``(K,)``: failures as counts of agents,
    style terms as means over the controlled agents."""

    realism: torch.Tensor
    components: dict[str, torch.Tensor]


def judge_scenarios(batch: ScenarioTensor, controlled: torch.Tensor,
                    config: JudgmentConfig | None = None) -> RealismJudgment:
    """The judgment of K options ``batch (K, A, T)``: history up to ``current_index``, then each option's future,
    over the ``controlled (K, A)`` agents."""
    cfg = config or JudgmentConfig()
    terms, agents = agent_penalties(batch, controlled, cfg)
    n_agents = agents.sum(-1).clamp_min(1).double()
    components = {name: (terms[name] * agents).sum(-1) for name in FAILURE_TERMS}
    components.update({name: (terms[name] * agents).sum(-1) / n_agents for name in STYLE_TERMS})
    penalty = sum(cfg.weight(name) * components[name] for name in (*FAILURE_TERMS, *STYLE_TERMS))
    return RealismJudgment(torch.exp(-penalty), components)


def agent_penalties(batch: ScenarioTensor, controlled: torch.Tensor,
                    config: JudgmentConfig | None = None) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Every term of the judgment per option and agent, float64 ``(K, A)`` by name, and the judged agents, bool
    ``(K, A)`` (controlled and visible in the future). Reads only what an item shows (see the module docstring)."""
    cfg = config or JudgmentConfig()
    now = batch.current_index
    states, valid = batch.states.double(), batch.valid
    future = valid.clone()
    future[:, :, : now + 1] = False
    agents = controlled.to(torch.bool) & future.any(-1)
    window = batch.time_slice(now)  # the start step, then the future
    w_valid = window.valid
    w_future = w_valid.clone()
    w_future[:, :, 0] = False
    terms: dict[str, torch.Tensor] = {}

    terms["collision"] = (collisions_per_step(window) & w_future).any(-1).double()
    has_drivable = batch.map is not None and "drivable" in batch.map.layers
    terms["offroad"] = ((offroad_per_step(window) & w_future).any(-1).double() if has_drivable
                        else torch.zeros(agents.shape, dtype=torch.float64))

    # what the history shows: the speed over the last second, heading at the start
    v_hist = recent_speed(batch)
    yaw0 = states[:, :, now, 3]
    horizon = (batch.num_steps - 1 - now) * batch.dt

    kin = _sampled_kinematics(window.states, w_valid, batch.dt, STAT_DT)
    v_mean = _masked_mean(kin["speed"], kin["speed_ok"])
    moved = kin["speed_ok"].any(-1)
    # the flow: neighbours near the agent at the start and heading its way, at the speed the item shows them
    # driving at: their history for the agents a model drives (all of which change together in a candidate),
    # their replayed future for the others
    near = flow_neighbours(batch, cfg.flow_radius_m)
    shown = torch.where(controlled.to(torch.bool) | ~moved, v_hist, v_mean)
    flow_n = near.sum(-1)
    flow = (near * shown[:, None, :]).sum(-1) / flow_n.clamp_min(1)
    # the agent followed at the start: nearest in its path
    cues = path_cues(batch, cfg.ttc_s, cfg.headway_s, cfg.stall_speed)
    has_lead = cues.lead_gap[:, :, now] <= cfg.lead_range_m
    v_lead = v_mean.gather(1, cues.lead_index[:, :, now])
    # the band of plausible mean speeds over the window
    reach = cfg.comfort_accel * horizon / 2
    hi = v_hist + reach
    hi = torch.where(flow_n > 0, torch.maximum(hi, flow), hi).clamp(max=cfg.road_max_speed)
    lo = (v_hist - reach).clamp_min(0)
    lo = torch.where(flow_n > 0, torch.minimum(lo, flow), lo)
    lo = torch.where(has_lead, torch.minimum(lo, v_lead), lo)
    too_fast = torch.log(v_mean.clamp_min(0.5) / hi.clamp_min(0.5))
    too_slow = torch.log(lo.clamp_min(0.5) / v_mean.clamp_min(0.5))
    error = torch.maximum(too_fast, too_slow).clamp_min(0) - cfg.pace_tolerance
    terms["pace"] = torch.where(moved, (error.clamp_min(0) / 0.3).clamp_max(3.0), torch.zeros_like(error))

    # stalling: nearly stopped with nobody close ahead, after driving at the start
    every = max(1, round(STAT_DT / batch.dt))
    ahead_s = cues.lead_gap[:, :, now::every][:, :, 1:]
    stalled = (kin["speed"] < 0.5) & kin["speed_ok"] & (ahead_s[:, :, : kin["speed"].shape[2]] > cfg.stall_gap_m)
    drove = v_hist > cfg.stall_speed
    terms["stall"] = torch.where(drove, stalled.sum(-1) / kin["speed_ok"].sum(-1).clamp_min(1),
                                 torch.zeros_like(v_hist))

    terms["tailgate"] = _share(cues.tailgating[:, :, now:], w_future)
    terms["near_miss"] = _share(near_misses_per_step(window, cfg.near_miss_m), w_future)
    terms["lane"] = _lane_error(window, w_future, cfg)
    terms["wrong_way"] = _wrong_way(window, w_future, yaw0, cfg)

    def excess(x: torch.Tensor, bound: float) -> torch.Tensor:
        return ((x.abs() - bound).clamp_min(0) / bound).clamp_max(3.0)

    # kinematics from one second before the start, so a sudden change at the start shows as it does on screen
    lead_in = batch.time_slice(max(0, now - round(STAT_DT / batch.dt)))
    kin = _sampled_kinematics(lead_in.states, lead_in.valid, batch.dt, STAT_DT)
    terms["accel"] = _masked_mean(excess(kin["lon"], cfg.max_lon_accel) + excess(kin["lat"], cfg.max_lat_accel),
                                  kin["acc_ok"])
    terms["jerk"] = _masked_mean(excess(kin["jerk"], cfg.max_jerk), kin["jerk_ok"])
    terms["stop_go"] = _reversals(kin["lon"], kin["acc_ok"], 1.0)
    fine = _sampled_kinematics(lead_in.states, lead_in.valid, batch.dt, WEAVE_DT)
    terms["weave"] = _reversals(fine["lat"], fine["acc_ok"], cfg.weave_accel)
    return {name: t.double() * agents for name, t in terms.items()}, agents


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over the last axis where ``mask``, 0 where nothing is valid: ``(K, A, S) -> (K, A)``."""
    return (values * mask).sum(-1) / mask.sum(-1).clamp_min(1)


def _reversals(values: torch.Tensor, ok: torch.Tensor, threshold: float) -> torch.Tensor:
    """``(K, A)``: sign reversals between consecutive samples whose magnitudes both exceed ``threshold``, capped
    at 3."""
    strong = ok & (values.abs() > threshold)
    sign = torch.sign(values) * strong
    return ((sign[:, :, 1:] * sign[:, :, :-1]) < 0).sum(-1).clamp_max(3).double()


def _sampled_kinematics(states: torch.Tensor, valid: torch.Tensor, dt: float, every_s: float
                        ) -> dict[str, torch.Tensor]:
    """Speed, body-frame accelerations and jerk ``(K, A, S)`` from positions ``(K, A, T, 4)`` every ``every_s``."""
    every = max(1, round(every_s / dt))
    xy, ok = states[:, :, ::every, :2].double(), valid[:, :, ::every]
    step = every * dt
    vel = (xy[:, :, 1:] - xy[:, :, :-1]) / step  # (K, A, S-1, 2)
    vel_ok = ok[:, :, 1:] & ok[:, :, :-1]
    speed = torch.linalg.vector_norm(vel, dim=-1)
    acc = (vel[:, :, 1:] - vel[:, :, :-1]) / step  # (K, A, S-2, 2)
    acc_ok = vel_ok[:, :, 1:] & vel_ok[:, :, :-1]
    heading = vel[:, :, 1:] + vel[:, :, :-1]
    norm = torch.linalg.vector_norm(heading, dim=-1, keepdim=True)
    yaw = states[:, :, ::every, 3].double()[:, :, 1:-1]
    fallback = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)[:, :, : heading.shape[2]]
    unit = torch.where(norm > 0.5, heading / norm.clamp_min(1e-9), fallback)  # slow agents: their yaw
    lon = (acc * unit).sum(-1)
    lat = acc[..., 1] * unit[..., 0] - acc[..., 0] * unit[..., 1]
    jerk = (lon[:, :, 1:] - lon[:, :, :-1]) / step
    return {"speed": speed, "speed_ok": vel_ok, "lon": lon, "lat": lat, "acc_ok": acc_ok,
            "jerk": jerk, "jerk_ok": acc_ok[:, :, 1:] & acc_ok[:, :, :-1]}


def _share(flags: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """``(K, A)``: share of the ``steps (K, A, T)`` where ``flags``."""
    return ((flags & steps).sum(-1) / steps.sum(-1).clamp_min(1)).double()


def _lane_error(window: ScenarioTensor, future: torch.Tensor, cfg: JudgmentConfig) -> torch.Tensor:
    """Time on a road divider, on a lane divider beyond ``lane_change_s``, and the mean share of box corners off
    the drivable layer (0 without a map)."""
    error = torch.zeros(future.shape[:2], dtype=torch.float64)
    if window.map is None:
        return error
    steps = future.sum(-1).clamp_min(1)
    layers = window.map.layers
    if "road_divider" in layers:
        error += _share(window.map.lookup(window.xy, "road_divider"), future)
    if "lane_divider" in layers:
        on = (window.map.lookup(window.xy, "lane_divider") & future).sum(-1)
        allowance = cfg.lane_change_s / window.dt
        error += ((on - allowance).clamp_min(0) / steps).double()
    if "drivable" in layers:
        error += ((offroad_corner_share(window) * future).sum(-1) / steps).double()
    return error


def _wrong_way(window: ScenarioTensor, future: torch.Tensor, yaw0: torch.Tensor, cfg: JudgmentConfig
               ) -> torch.Tensor:
    """Share of future steps, while driving, heading more than 90 degrees off the nearest lane centerline's
    direction (where the map has centerlines within 2 m) or off the agent's own heading at the start."""
    yaw = window.yaw.double()
    driving = (window.states[..., 2] > cfg.stall_speed) & future
    against = torch.cos(yaw - yaw0[:, :, None]) < 0
    lane_yaw, has_lane = lane_direction(window)
    if has_lane is not None:
        against |= has_lane & (torch.cos(yaw - lane_yaw) < 0)
    return _share(against, driving)
