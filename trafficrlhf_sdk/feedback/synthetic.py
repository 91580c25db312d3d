"""A synthetic annotator: a hidden realism judgment plus B-Pref-style noise, labeling through the store API.

**Hidden judgment.** Each candidate future (and the logged one) gets a penalty, a weighted sum of the share of
controlled agents that collide, the share that leave the drivable area, soft excesses of longitudinal and
lateral acceleration and of jerk over plausible bounds, and the share of time an agent stalls (nearly stopped)
where the log drives on. Realism is ``exp(-penalty)`` in (0, 1]. Kinematics are measured in each vehicle's own
frame on positions sampled every 1 s: the logged nuScenes tracks are 2 Hz keyframes with centimetre-level box
noise, and on 0.5 s differences that noise alone gives logged jerk a 90th percentile of 7.9 m/s^3; at 1 s the
log's 99th percentiles are 2.6 m/s^2 (longitudinal), 2.8 m/s^2 (lateral) and 3.0 m/s^3 (jerk) over the first
20 val scenes, hence the default bounds of 3.

**Noisy choice** (B-Pref, Lee et al. 2021, ``teacher_beta`` / ``teacher_eps_mistake`` / skip threshold):

1. if the best candidate's realism is at or below ``none_threshold``: answer "none realistic" (slot 0);
2. with probability ``epsilon``: a mistake, one of the other candidates uniformly;
3. otherwise sample from ``softmax(beta * realism)`` over the candidates (``beta=None``: perfectly rational,
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

from trafficrlhf_sdk.feedback.store import Annotator, Campaign, ContextRecord, FeedbackStore
from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_per_step
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["RealismJudgment", "SyntheticAnnotator", "SyntheticAnnotatorConfig", "judge_realism"]

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
    controlled = record.controlled[None].expand(batch.num_scenes, -1)
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
    # stalling: nearly stopped while the logged agent drives (the log is the same scene in every row)
    log = ScenarioTensor.concat([record.candidate_scenario(None)]).time_slice(start)
    log_kin = _sampled_kinematics(log.states, log.valid, log.dt)
    driving = (log_kin["speed"] > cfg.stall_log_speed) & log_kin["speed_ok"]
    stalled = (kin["speed"] < cfg.stall_ratio * log_kin["speed"]) & driving & kin["speed_ok"]
    stall = stalled.sum(-1) / driving.sum(-1).clamp_min(1)

    def per_agent(x: torch.Tensor) -> torch.Tensor:
        return (x * controlled).sum(-1) / n_agents

    components = {"collision": collided.double(), "offroad": offroad.double(), "accel": per_agent(acc_excess),
                  "jerk": per_agent(jerk_excess), "stall": per_agent(stall.double())}
    penalty = (cfg.weight_collision * components["collision"] + cfg.weight_offroad * components["offroad"]
               + cfg.weight_accel * components["accel"] + cfg.weight_jerk * components["jerk"]
               + cfg.weight_stall * components["stall"])
    return RealismJudgment(torch.exp(-penalty), components)


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

    def choose(self, realism: torch.Tensor, generator: torch.Generator) -> int | None:
        """The candidate index chosen from realism scores ``(N,)``, or None for "none realistic"."""
        cfg = self.config
        if float(realism.max()) <= cfg.none_threshold:
            return None
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
        """Label up to ``limit`` items (all that are left when None); returns counts of labels, none, skips."""
        campaign = self.store.campaign(campaign) if isinstance(campaign, str) else campaign
        counts = {"labeled": 0, "none_realistic": 0, "skipped": 0}
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
            choice = self.choose(realism, generator)
            slot = 0 if choice is None else assignment.permutation.index(choice) + 1  # what a person would press
            self.store.submit_label(self.annotator, campaign, assignment.context_id, slot, source="synthetic")
            counts["labeled"] += 1
            counts["none_realistic"] += int(choice is None)
            if on_label is not None:
                on_label(assignment.context_id, choice)
        return counts
