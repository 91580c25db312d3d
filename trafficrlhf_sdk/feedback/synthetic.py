"""A stand-in annotator: a hidden realism judgment plus B-Pref-style noise, labeling through the store API.

It stands in for people in tests, experiments and the main job; it is not a truth about realism. Several
:data:`PROFILES` weigh what they notice differently and make mistakes at different rates, so that their labels
disagree as people's do. A reward model can only learn what the judgment contains: a term it lacks is a blind spot
that an optimized policy will find.

**Hidden judgment.** Each candidate future (and the logged one) gets a penalty, a weighted sum, per controlled
agent and averaged, of what a person watching the video notices:

- collisions and leaving the drivable area (shares of agents);
- harsh kinematics: soft excesses of longitudinal and lateral acceleration and of jerk over plausible bounds;
- stalling (nearly stopped where the log drives on), and **pace** against the flow: the agent's mean speed
  against the logged agent's, outside a tolerance, faster or slower;
- **tailgating**: the share of time with a time to collision to the agent ahead below ``ttc_s`` or a time headway
  below ``headway_s`` while driving;
- **lane keeping**: time spent on lane or road dividers beyond what the logged agent spends there, and box
  corners off the drivable area;
- **heading against the flow**: driving more than 90 degrees off the logged agent's heading;
- **stop-and-go**: reversals of a longitudinal acceleration above 1 m/s^2 within the window.

Realism is ``exp(-penalty)`` in (0, 1]. Kinematics are measured in each vehicle's own frame on positions sampled
every 1 s: the logged nuScenes tracks are 2 Hz keyframes with centimetre-level box noise, which finer differences
turn into spurious jerk.

**Noisy choice** (B-Pref, Lee et al. 2021, ``teacher_beta`` / ``teacher_eps_mistake`` / skip threshold):

1. if the best candidate's realism is at or below ``none_threshold``: answer "none realistic" (slot 0);
2. if every candidate's realism lies within ``tie_margin`` of the best and the campaign allows ties: answer
   "equally realistic";
3. with probability ``epsilon``: a mistake, one of the other candidates uniformly;
4. otherwise sample from ``softmax(beta * realism)`` over the candidates (``beta=None``: perfectly rational,
   the argmax).

Every draw comes from a generator seeded by (``seed``, annotator name, item id), so a labeling run is
reproducible whatever the order in which items are served.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from collections.abc import Callable

import torch
from pydantic import BaseModel, ConfigDict, Field

from trafficrlhf_sdk.feedback.records import TIE_SLOT
from trafficrlhf_sdk.feedback.store import Annotator, Campaign, ContextRecord, FeedbackStore
from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_corner_share, offroad_per_step
from trafficrlhf_sdk.metrics.geometry import path_gaps
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["PROFILES", "RealismJudgment", "SyntheticAnnotator", "SyntheticAnnotatorConfig", "judge_realism",
           "judge_scenarios"]

STAT_DT = 1.0  # s between the samples used for kinematics


class SyntheticAnnotatorConfig(BaseModel):
    """The hidden judgment's weights and bounds, and the noise model."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    beta: float | None = Field(
        20.0, gt=0, description="Rationality: inverse temperature on realism (0..1); None = always the argmax."
    )
    epsilon: float = Field(0.0, ge=0, le=1, description="Mistake rate: probability of picking another candidate.")
    none_threshold: float = Field(0.35, ge=0, le=1, description="Best realism at or below this: 'none realistic'.")
    skip_rate: float = Field(0.0, ge=0, le=1, description="Probability of skipping an item (tests the skip path).")
    seed: int = Field(0, description="Seed of every random draw.")
    weight_collision: float = Field(4.0, ge=0, description="Penalty per unit share of agents that collide.")
    weight_offroad: float = Field(3.0, ge=0, description="Penalty per unit share of agents that leave the road.")
    weight_accel: float = Field(1.5, ge=0, description="Penalty per unit of mean relative acceleration excess.")
    weight_jerk: float = Field(1.0, ge=0, description="Penalty per unit of mean relative jerk excess.")
    weight_stall: float = Field(2.0, ge=0, description="Penalty per unit share of time stalled against the log.")
    max_lon_accel: float = Field(3.0, gt=0, description="Plausible |longitudinal acceleration| bound (m/s^2).")
    max_lat_accel: float = Field(3.0, gt=0, description="Plausible |lateral acceleration| bound (m/s^2).")
    max_jerk: float = Field(3.0, gt=0, description="Plausible |longitudinal jerk| bound (m/s^3).")
    stall_log_speed: float = Field(2.0, ge=0, description="The log counts as driving above this speed (m/s).")
    stall_ratio: float = Field(0.25, gt=0, lt=1, description="Stalled: speed below this fraction of the log's.")
    weight_pace: float = Field(2.0, ge=0, description="Penalty per unit of pace error: |log(speed / logged speed)| "
                               "beyond `pace_tolerance`, over 0.3, capped at 3.")
    pace_tolerance: float = Field(0.15, ge=0, description="Pace error (|log speed ratio|) noticed by nobody.")
    weight_tailgate: float = Field(2.0, ge=0, description="Penalty per unit share of time tailgating.")
    ttc_s: float = Field(1.5, gt=0, description="Tailgating: time to collision to the agent ahead below this (s).")
    headway_s: float = Field(0.6, gt=0, description="Tailgating: time headway to the agent ahead below this (s) "
                             "while driving above `stall_log_speed`.")
    weight_lane: float = Field(1.5, ge=0, description="Penalty per unit of lane keeping error: share of time on a "
                               "divider beyond the logged agent's, plus the mean share of box corners off-road.")
    weight_wrong_way: float = Field(3.0, ge=0, description="Penalty per unit share of time heading more than 90 "
                                    "degrees off the logged agent's heading while driving.")
    weight_stop_go: float = Field(0.5, ge=0, description="Penalty per reversal of a longitudinal acceleration above "
                                  "1 m/s^2 (per agent, capped at 3).")
    tie_margin: float = Field(0.0, ge=0, le=1, description="Answer 'equally realistic' when every candidate's "
                              "realism is within this of the best (campaigns that allow ties); 0: never.")


PROFILES: dict[str, SyntheticAnnotatorConfig] = {
    "attentive": SyntheticAnnotatorConfig(beta=40.0, epsilon=0.02, tie_margin=0.02),
    "safety": SyntheticAnnotatorConfig(beta=25.0, epsilon=0.05, weight_collision=6.0, weight_offroad=4.0,
                                       weight_tailgate=3.0, weight_accel=1.0, weight_jerk=0.5, weight_pace=1.0,
                                       tie_margin=0.03),
    "flow": SyntheticAnnotatorConfig(beta=25.0, epsilon=0.05, weight_pace=3.0, weight_stall=3.0, weight_stop_go=1.0,
                                     weight_lane=2.0, tie_margin=0.03),
    "hurried": SyntheticAnnotatorConfig(beta=10.0, epsilon=0.15, tie_margin=0.05),
}
"""Named stand-in annotators that weigh the judgment differently and err at different rates (so that their labels
disagree as people's do): ``attentive`` (few mistakes), ``safety`` (collisions, off-road and tailgating first),
``flow`` (pace, stalling, stop-and-go and lane keeping first) and ``hurried`` (noisy)."""


@dataclass(frozen=True)
class RealismJudgment:
    """Realism ``(K,)`` in (0, 1] of K futures of one context, and the penalty components ``(K,)`` by name."""

    realism: torch.Tensor
    components: dict[str, torch.Tensor]


def _sampled_kinematics(states: torch.Tensor, valid: torch.Tensor, dt: float) -> dict[str, torch.Tensor]:
    """Speed, body-frame accelerations and jerk ``(K, A, S)`` from positions ``(K, A, T, 4)`` every ``STAT_DT``."""
    every = max(1, round(STAT_DT / dt))
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


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over the last axis where ``mask``, 0 where nothing is valid: ``(K, A, S) -> (K, A)``."""
    return (values * mask).sum(-1) / mask.sum(-1).clamp_min(1)


def judge_realism(record: ContextRecord, config: SyntheticAnnotatorConfig | None = None,
                  include_logged: bool = True) -> RealismJudgment:
    """Score the N candidates of ``record`` (and, last, its logged future when ``include_logged``)."""
    cfg = config or SyntheticAnnotatorConfig()
    futures = [record.candidate_scenario(k) for k in range(record.num_candidates)]
    if include_logged:
        futures.append(record.candidate_scenario(None))
    start = record.scenario.current_index
    batch = ScenarioTensor.concat(futures).time_slice(start)  # (K, A, 1 + H): the start step, then the future
    log = ScenarioTensor.concat([record.candidate_scenario(None)]).time_slice(start)
    return judge_scenarios(batch, log, record.controlled[None].expand(batch.num_scenes, -1), cfg)


def judge_scenarios(batch: ScenarioTensor, log: ScenarioTensor, controlled: torch.Tensor,
                    config: SyntheticAnnotatorConfig | None = None) -> RealismJudgment:
    """The hidden judgment of K futures ``batch (K, A, 1 + H)`` (the start step, then the future) against the
    logged ``log`` (one window for all, or one per future), over the ``controlled (K, A)`` agents."""
    cfg = config or SyntheticAnnotatorConfig()
    controlled = controlled.to(torch.bool)
    n_agents = controlled.sum(-1).clamp_min(1).double()
    future_valid = batch.valid.clone()
    future_valid[:, :, 0] = False
    collided = ((collisions_per_step(batch) & future_valid).any(-1) & controlled).sum(-1) / n_agents
    if batch.map is not None and "drivable" in batch.map.layers:
        offroad = ((offroad_per_step(batch) & future_valid).any(-1) & controlled).sum(-1) / n_agents
    else:
        offroad = torch.zeros_like(collided)
    kin = _sampled_kinematics(batch.states, batch.valid, batch.dt)

    def excess(x: torch.Tensor, bound: float) -> torch.Tensor:
        return ((x.abs() - bound).clamp_min(0) / bound).clamp_max(3.0)

    acc_excess = _masked_mean(excess(kin["lon"], cfg.max_lon_accel) + excess(kin["lat"], cfg.max_lat_accel),
                              kin["acc_ok"])
    jerk_excess = _masked_mean(excess(kin["jerk"], cfg.max_jerk), kin["jerk_ok"])
    # stalling: nearly stopped while the logged agent drives
    log_kin = _sampled_kinematics(log.states, log.valid, log.dt)
    driving = (log_kin["speed"] > cfg.stall_log_speed) & log_kin["speed_ok"]
    stalled = (kin["speed"] < cfg.stall_ratio * log_kin["speed"]) & driving & kin["speed_ok"]
    stall = stalled.sum(-1) / driving.sum(-1).clamp_min(1)

    # pace against the logged agent's, over the steps where both are measured
    both = kin["speed_ok"] & log_kin["speed_ok"]
    mean_speed = _masked_mean(kin["speed"], both)
    log_speed = _masked_mean(log_kin["speed"].expand_as(kin["speed"]), both)
    moving = log_speed > cfg.stall_log_speed
    ratio = torch.log(mean_speed.clamp_min(0.1) / log_speed.clamp_min(0.1))
    pace = torch.where(moving, ((ratio.abs() - cfg.pace_tolerance).clamp_min(0) / 0.3).clamp_max(3.0),
                       torch.zeros_like(ratio))
    tailgate = _tailgating(batch, future_valid, cfg)
    lane = _lane_error(batch, log, future_valid)
    # heading against the logged agent's while driving (10 Hz steps)
    off = torch.cos(batch.yaw - log.yaw) < 0
    drives = (batch.states[..., 2] > cfg.stall_log_speed) & future_valid & log.valid
    wrong_way = (off & drives).sum(-1) / future_valid.sum(-1).clamp_min(1)
    # stop-and-go: reversals of a sizeable longitudinal acceleration
    strong = kin["acc_ok"] & (kin["lon"].abs() > 1.0)
    sign = torch.sign(kin["lon"]) * strong
    flips = ((sign[:, :, 1:] * sign[:, :, :-1]) < 0).sum(-1).clamp_max(3)

    def per_agent(x: torch.Tensor) -> torch.Tensor:
        return (x * controlled).sum(-1) / n_agents

    components = {"collision": collided.double(), "offroad": offroad.double(), "accel": per_agent(acc_excess),
                  "jerk": per_agent(jerk_excess), "stall": per_agent(stall.double()),
                  "pace": per_agent(pace.double()), "tailgate": per_agent(tailgate.double()),
                  "lane": per_agent(lane.double()), "wrong_way": per_agent(wrong_way.double()),
                  "stop_go": per_agent(flips.double())}
    penalty = (cfg.weight_collision * components["collision"] + cfg.weight_offroad * components["offroad"]
               + cfg.weight_accel * components["accel"] + cfg.weight_jerk * components["jerk"]
               + cfg.weight_stall * components["stall"] + cfg.weight_pace * components["pace"]
               + cfg.weight_tailgate * components["tailgate"] + cfg.weight_lane * components["lane"]
               + cfg.weight_wrong_way * components["wrong_way"] + cfg.weight_stop_go * components["stop_go"])
    return RealismJudgment(torch.exp(-penalty), components)


def _tailgating(batch: ScenarioTensor, future_valid: torch.Tensor, cfg: SyntheticAnnotatorConfig) -> torch.Tensor:
    """``(K, A)``: share of each agent's future steps with a short time to collision or time headway to the
    nearest agent in its path ahead."""
    speed = batch.states[..., 2]
    gap, closing, in_path = path_gaps(batch.xy, batch.yaw, speed, batch.extent, batch.valid)
    inf = torch.full_like(gap, float("inf"))
    ttc = torch.where(in_path & (closing > 0), gap / closing.clamp_min(1e-6), inf).amin(2)
    headway = torch.where(in_path, gap / speed[:, :, None].clamp_min(1e-6), inf).amin(2)
    close = (ttc < cfg.ttc_s) | ((headway < cfg.headway_s) & (speed > cfg.stall_log_speed))
    return (close & future_valid).sum(-1) / future_valid.sum(-1).clamp_min(1)


def _lane_error(batch: ScenarioTensor, log: ScenarioTensor, future_valid: torch.Tensor) -> torch.Tensor:
    """``(K, A)``: time on lane or road dividers beyond the logged agent's, plus the mean share of box corners
    off the drivable layer (0 without a map)."""
    if batch.map is None:
        return torch.zeros(future_valid.shape[:2], dtype=torch.float64)
    error = torch.zeros(future_valid.shape[:2], dtype=torch.float64)
    steps = future_valid.sum(-1).clamp_min(1)
    for layer in ("lane_divider", "road_divider"):
        if layer in batch.map.layers:
            on = batch.map.lookup(batch.xy, layer) & future_valid
            log_valid = future_valid if log.num_scenes == batch.num_scenes else future_valid[:1]
            on_log = log.map.lookup(log.xy, layer) & log_valid if log.map is not None else on & False
            error += ((on.sum(-1) - on_log.sum(-1)).clamp_min(0) / steps).double()
    if "drivable" in batch.map.layers:
        error += ((offroad_corner_share(batch) * future_valid).sum(-1) / steps).double()
    return error


class SyntheticAnnotator:
    """Labels items of a campaign like a person would, through :class:`FeedbackStore`.

    Args:
        store: the feedback database.
        name: the annotator's name (created on first use, like a person with a token).
        config: judgment and noise settings.
    """

    def __init__(self, store: FeedbackStore, name: str, config: SyntheticAnnotatorConfig | None = None) -> None:
        self.store = store
        self.config = config or SyntheticAnnotatorConfig()
        try:
            self.annotator: Annotator = store.annotator(name)
        except KeyError:
            self.annotator, _ = store.add_annotator(name)

    def _generator(self, context_id: int) -> torch.Generator:
        digest = hashlib.sha256(f"{self.config.seed}:{self.annotator.name}:{context_id}".encode()).digest()
        return torch.Generator().manual_seed(int.from_bytes(digest[:8], "big") >> 1)

    def choose(self, realism: torch.Tensor, generator: torch.Generator, allow_tie: bool = False) -> int | None:
        """The candidate index chosen from realism scores ``(N,)``, None for "none realistic", or
        :data:`~trafficrlhf_sdk.feedback.schema.TIE_SLOT` for "equally realistic" (when ``allow_tie``)."""
        cfg = self.config
        if float(realism.max()) <= cfg.none_threshold:
            return None
        if allow_tie and cfg.tie_margin > 0 and float(realism.max() - realism.min()) <= cfg.tie_margin:
            return TIE_SLOT
        if cfg.beta is None:
            best = int(torch.argmax(realism))
        else:
            probs = torch.softmax(cfg.beta * realism.double(), 0)
            best = int(torch.multinomial(probs, 1, generator=generator))
        if cfg.epsilon > 0 and float(torch.rand((), generator=generator)) < cfg.epsilon:
            others = [k for k in range(len(realism)) if k != best]
            best = others[int(torch.randint(len(others), (), generator=generator))]
        return best

    def label(self, campaign: Campaign | str, limit: int | None = None,
              on_label: Callable[[int, int | None], None] | None = None) -> dict[str, int]:
        """Label up to ``limit`` items (all that are left when None); returns counts of labels, none, ties, skips."""
        campaign = self.store.campaign(campaign) if isinstance(campaign, str) else campaign
        counts = {"labeled": 0, "none_realistic": 0, "ties": 0, "skipped": 0}
        while limit is None or counts["labeled"] + counts["skipped"] < limit:
            assignment = self.store.next_item(self.annotator, campaign)
            if assignment is None:
                break
            generator = self._generator(assignment.context_id)
            if self.config.skip_rate > 0 and float(torch.rand((), generator=generator)) < self.config.skip_rate:
                self.store.skip(self.annotator, campaign, assignment.context_id, "synthetic: random skip")
                counts["skipped"] += 1
                continue
            record = self.store.load_context(assignment.context_id, campaign)
            realism = judge_realism(record, self.config, include_logged=False).realism
            choice = self.choose(realism, generator, allow_tie=bool(getattr(campaign.settings, "allow_tie", False)))
            if choice == TIE_SLOT:
                slot = TIE_SLOT
            else:  # what a person would press
                slot = 0 if choice is None else assignment.permutation.index(choice) + 1
            self.store.submit_label(self.annotator, campaign, assignment.context_id, slot, source="synthetic")
            counts["labeled"] += 1
            counts["none_realistic"] += int(choice is None)
            counts["ties"] += int(choice == TIE_SLOT)
            if on_label is not None:
                on_label(assignment.context_id, choice)
        return counts
