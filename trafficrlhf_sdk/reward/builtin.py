"""Hand-written per-step rewards with the reward-model protocol (``step_rewards(scenario) -> (B, T)``).

They need no training and serve as baselines and ablations for a learned r_HF: tests, the Gymnasium
environment's default, and the recipes of the committed baseline models (their model cards name the reward).
"""

from __future__ import annotations

import math

import torch

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_corner_share, offroad_per_step
from trafficrlhf_sdk.metrics.geometry import pairwise_collisions, path_gaps
from trafficrlhf_sdk.metrics.realism import STAT_DT, HistogramSpec, kinematics
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["FailureReward", "RandomReward", "RealismReward", "kinematic_log_ratio",
           "time_to_collision"]


class FailureReward:
    """Per-step reward in [-1, 0]: minus the share of controlled agents (all valid agents in a scene without
    controlled ones) that collide, or whose centre is off the drivable area (when the scenario has a map).

    With ``margins=True`` a step that is not a failure yet still costs something when the agent is close to
    one: ``corner_weight`` x the share of its four box corners off the drivable area, plus ``near_weight`` if
    its box, grown by ``near_buffer_m`` = (ahead/behind, sideways) metres, overlaps another agent's grown box.
    A failure step costs 1 as before. The binary failure tells samples apart only when one of them actually
    fails within its 2 s horizon; the margins also rank samples that merely graze the road edge or tailgate,
    which is how most later failures start. On 120 nuScenes train scenes of logged driving, 3.0 % of the
    controlled agent-steps have a corner off the drivable layer, 0.8 % are near misses at (0.5, 0.25) m and
    0.03 % have the centre off-road; the mean cost per step is 0.011 with the defaults.

    With ``ttc_weight > 0`` the margins also price closing in on the agent ahead before any box is touched:
    ``ttc_weight * clamp(1 - TTC / ttc_threshold_s, 0, 1)`` per step, TTC the smallest time to collision
    (:func:`time_to_collision`) with an agent in the path ahead. A step at half the threshold costs half the
    weight; an agent keeping its gap or pulling away costs nothing.

    Args:
        collision: count collisions; offroad: count off-road centres; margins: add the near-failure terms;
        corner_weight, near_weight, ttc_weight: their costs per step (in [0, 1]); near_buffer_m: the growth of
        each box; ttc_threshold_s: the time to collision (s) from which closing in starts to cost.
    """

    def __init__(self, collision: bool = True, offroad: bool = True, margins: bool = False,
                 corner_weight: float = 0.5, near_weight: float = 0.5,
                 near_buffer_m: tuple[float, float] = (0.5, 0.25), ttc_weight: float = 0.0,
                 ttc_threshold_s: float = 1.5) -> None:
        for name, value in (("corner_weight", corner_weight), ("near_weight", near_weight),
                            ("ttc_weight", ttc_weight)):
            if not 0 <= value <= 1:
                raise TrafficRLHFError(f"`{name}` is {value}; use a cost per step in [0, 1].")
        if min(near_buffer_m) < 0:
            raise TrafficRLHFError(f"`near_buffer_m` is {near_buffer_m}; give non-negative (ahead, sideways) metres.")
        if not ttc_threshold_s > 0:
            raise TrafficRLHFError(f"`ttc_threshold_s` is {ttc_threshold_s}; give a time in seconds > 0 (e.g. 1.5).")
        if ttc_weight and not margins:
            raise TrafficRLHFError(f"`ttc_weight` is {ttc_weight} but margins are off; use a '-margins' reward "
                                   "(e.g. builtin:realism-margins) or leave ttc_weight at 0.")
        self.ttc_weight, self.ttc_threshold_s = ttc_weight, ttc_threshold_s
        self.collision = collision
        self.offroad = offroad
        self.margins = margins
        self.corner_weight, self.near_weight = corner_weight, near_weight
        self.near_buffer_m = tuple(near_buffer_m)

    def _failures(self, scenario: ScenarioTensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(cost, mask)``: float ``(B, A, T)`` cost in [0, 1] per scored agent-step (1 = failure; without
        margins exactly 0 or 1) and the bool mask of the scored ones."""
        agents = scenario.controlled & scenario.valid.any(-1)
        agents = torch.where(agents.any(-1, keepdim=True), agents, scenario.valid.any(-1))
        mask = agents[:, :, None] & scenario.valid
        bad = torch.zeros_like(mask)
        has_map = self.offroad and scenario.map is not None
        if self.collision:
            bad |= collisions_per_step(scenario)
        if has_map:
            bad |= offroad_per_step(scenario)
        cost = bad.float()
        if self.margins:
            near = torch.zeros_like(cost)
            if self.collision and self.near_weight:
                grown = scenario.extent + 2 * scenario.extent.new_tensor(self.near_buffer_m)
                near += self.near_weight * pairwise_collisions(scenario.xy, scenario.yaw, grown, scenario.valid)
            if has_map and self.corner_weight:
                near += self.corner_weight * offroad_corner_share(scenario)
            if self.collision and self.ttc_weight:
                ttc = time_to_collision(scenario)
                near += self.ttc_weight * (1 - ttc / self.ttc_threshold_s).clamp(0, 1)
            cost = torch.maximum(cost, near.clamp_max(1))
        return cost * mask, mask

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        """``(B, T)`` rewards (0 where no agent is scored)."""
        cost, mask = self._failures(scenario)
        return -(cost.sum(1) / mask.sum(1).clamp_min(1))

    def agent_scores(self, scenario: ScenarioTensor) -> torch.Tensor:
        """``(B, A)``: minus the mean cost of each scored agent's valid steps after ``current_index`` (the share
        of them in failure without margins; 0 for agents not scored). An agent that fails later scores higher
        than one that fails at once."""
        cost, mask = self._failures(scenario)
        future = slice(scenario.current_index + 1, None)
        cost, mask = cost[:, :, future], mask[:, :, future]
        return -(cost.sum(-1) / mask.sum(-1).clamp_min(1))


def time_to_collision(scenario: ScenarioTensor, lane_margin_m: float = 0.5) -> torch.Tensor:
    """``(B, A, T)`` seconds: per agent and step, the smallest time to collision with an agent in its path ahead,
    ``inf`` where none is closing in (or the agent is not valid).

    Who is in the path, the bumper gap and the closing speed are as :func:`~trafficrlhf_sdk.metrics.path_gaps`
    defines them; TTC = gap / closing speed where the latter is positive.
    """
    speed = scenario.states[..., 2]
    gap, closing, in_path = path_gaps(scenario.xy, scenario.yaw, speed, scenario.extent, scenario.valid,
                                      lane_margin_m)
    ttc = torch.where(in_path & (closing > 0), gap / closing.clamp_min(1e-6), torch.full_like(gap, math.inf))
    return ttc.amin(2) if ttc.shape[2] else torch.full_like(speed, math.inf)


class RandomReward:
    """A reward that carries no information: the null control of an alignment run.

    Every per-agent score and per-step reward is a fixed pseudo-random function of the states it scores,
    uniform in [-1, 1] and unrelated to failures or realism (``seed`` picks the function). PPO against it moves
    the weights without a preference, so what such a run changes in the closed loop is the noise floor a real
    reward's gain has to clear (the closed loop compounds small weight changes). A function of the states rather
    than a random stream, so the same samples get the same scores and an interrupted run resumes exactly.

    Args:
        seed: picks the function.
    """

    def __init__(self, seed: int = 0) -> None:
        generator = torch.Generator().manual_seed(int(seed))
        # irrational-looking weights per state feature, so distinct states hash to unrelated values
        self._weights = (torch.rand(4, generator=generator, dtype=torch.float64) + 0.5) * 12.9898

    def _uniform(self, states: torch.Tensor, valid: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
        """Values in [-1, 1): a sine hash of the valid ``states (B, A, T, 4)`` summed over ``dims``."""
        x = (states.double() * self._weights).sum(-1)  # (B, A, T)
        steps = torch.arange(1, x.shape[-1] + 1, dtype=torch.float64) * 0.6180339887
        agents = torch.arange(1, x.shape[1] + 1, dtype=torch.float64)[:, None] * 0.4142135623
        x = torch.where(valid, x * (1 + steps + agents), torch.zeros_like(x)).sum(dims)
        return (torch.frac(torch.sin(x).abs() * 43758.5453) * 2 - 1).float()

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        """``(B, T)`` values in [-1, 1), one per step from the states of all agents at that step."""
        return self._uniform(scenario.states, scenario.valid, (1,))

    def agent_scores(self, scenario: ScenarioTensor) -> torch.Tensor:
        """``(B, A)`` values in [-1, 1), one per agent from its states over the window."""
        return self._uniform(scenario.states, scenario.valid, (2,))


class RealismReward(FailureReward):
    """Failures plus two realism terms a failure reward alone lets a policy trade away.

    The two: stalling against the log and implausible acceleration. Per agent, minus

    ``failure share of steps + stall_weight * stalled share + accel_weight * mean relative acceleration excess``

    * stalled: the agent drives slower than ``stall_ratio`` x its logged speed where the log drives faster than
      ``stall_log_speed`` (the synthetic annotator's stall term with a stricter ratio than its 0.25; 0.8 went
      too far: the aligned CTG then sped, speed-limit violation 0.40 -> 1.50 m/s; it needs the logged future,
      so the fine-tuner passes ``logged``: the same scenarios with the log in place of the samples);
    * acceleration excess: ``relu(|dv/dt| - max_accel) / max_accel`` on 0.5 s speed differences;
    * speed mismatch (``speed_weight > 0``): per future step where both are valid,
      ``min(1, relu(|v - v_log| / max(v_log, speed_floor) - speed_tolerance))``, averaged over the agent's steps.
      Symmetric, so it penalizes driving faster than the log as much as slower; it closes the way out the stall
      term leaves open (avoid failures by slowing to just above ``stall_ratio`` x the logged speed);
    * kinematic mismatch (``kinematics_weight > 0``): minus the mean over the agent's future 0.5 s samples (the
      first ``kinematics_samples`` only, when set) of
      ``log p_log(q) - log p_sampled(q)`` for its body-frame longitudinal and lateral acceleration and jerk
      (:func:`~trafficrlhf_sdk.metrics.realism.kinematics`), with ``p`` the add-one-smoothed histograms of the
      logged futures and of all samples in the call (one fine-tuning epoch), the ratio clipped to +-3. A
      histogram density-ratio discriminator (the reward GAIL learns, here counted instead of learned): samples
      whose accelerations the model produces more often than the log lose, rarer ones gain, so the policy is
      pushed towards the logged histograms the realism metric compares with. The failure terms alone narrow
      them (an aligned model brakes and accelerates less hard than the log).
    * heading mismatch (``heading_weight > 0``): per future step where the log drives faster than
      ``stall_log_speed``, ``min(1, relu(|wrap(yaw - yaw_log)| - heading_tolerance) / heading_scale)``,
      averaged over those steps. A model that under-steers in turns leaves the road there; this term
      asks for the logged turn itself rather than for a recovery at the road edge. Angles in radians.

    ``corner_weight``, ``near_weight``, ``near_buffer_m``, ``ttc_weight`` and ``ttc_threshold_s`` set the margins
    as in :class:`FailureReward` (``--reward-option near_weight=1`` on ``builtin:realism-margins``).

    Without it, aligning CTG on failures alone made agents slow down (mean speed 7.3 -> 4.2 m/s over 10 s,
    39 of 196 agents stopped at the end against 6 in the log): fewer failures, less realism.
    """

    uses_log = True

    def __init__(self, stall_weight: float = 1.0, accel_weight: float = 0.5, stall_ratio: float = 0.5,
                 stall_log_speed: float = 2.0, max_accel: float = 3.0, margins: bool = False,
                 speed_weight: float = 0.0, speed_tolerance: float = 0.25, speed_floor: float = 3.0,
                 kinematics_weight: float = 0.0, kinematics_samples: int | None = None,
                 heading_weight: float = 0.0, heading_tolerance: float = 0.05, heading_scale: float = 0.5,
                 corner_weight: float = 0.5, near_weight: float = 0.5,
                 near_buffer_m: tuple[float, float] = (0.5, 0.25), ttc_weight: float = 0.0,
                 ttc_threshold_s: float = 1.5) -> None:
        super().__init__(margins=margins, corner_weight=corner_weight, near_weight=near_weight,
                         near_buffer_m=near_buffer_m, ttc_weight=ttc_weight, ttc_threshold_s=ttc_threshold_s)
        for name, value in (("speed_weight", speed_weight), ("speed_tolerance", speed_tolerance),
                            ("kinematics_weight", kinematics_weight), ("heading_weight", heading_weight),
                            ("heading_tolerance", heading_tolerance)):
            if value < 0:
                raise TrafficRLHFError(f"`{name}` is {value}; use a value >= 0.")
        if speed_floor <= 0:
            raise TrafficRLHFError(f"`speed_floor` is {speed_floor}; use a speed > 0 in m/s (e.g. 3.0).")
        self.stall_weight, self.accel_weight = stall_weight, accel_weight
        self.stall_ratio, self.stall_log_speed, self.max_accel = stall_ratio, stall_log_speed, max_accel
        self.speed_weight, self.speed_tolerance, self.speed_floor = speed_weight, speed_tolerance, speed_floor
        if kinematics_samples is not None and kinematics_samples < 1:
            raise TrafficRLHFError(f"`kinematics_samples` is {kinematics_samples}; use None (every future 0.5 s "
                                   "sample) or a count >= 1 (1 = the first 0.5 s, what a 2 Hz closed loop executes).")
        self.kinematics_weight, self.kinematics_samples = kinematics_weight, kinematics_samples
        if heading_scale <= 0:
            raise TrafficRLHFError(f"`heading_scale` is {heading_scale}; use an angle > 0 in radians (e.g. 0.5).")
        self.heading_weight, self.heading_tolerance = heading_weight, heading_tolerance
        self.heading_scale = heading_scale

    def agent_scores(self, scenario: ScenarioTensor, logged: ScenarioTensor | None = None) -> torch.Tensor:
        """``(B, A)`` rewards (0 for agents not scored); ``logged``: ``scenario`` with the logged future."""
        if logged is None:
            raise TrafficRLHFError("RealismReward compares with the logged future: pass `logged` (the same "
                                   "scenarios with the log after current_index).")
        cost, mask = self._failures(scenario)
        future = slice(scenario.current_index + 1, None)
        cost, mask = cost[:, :, future], mask[:, :, future]
        steps = mask.sum(-1).float().clamp_min(1)
        speed = scenario.states[:, :, future, 2].abs()
        log_speed = logged.states[:, :, future, 2].abs()
        driving = mask & logged.valid[:, :, future] & (log_speed > self.stall_log_speed)
        stalled = driving & (speed < self.stall_ratio * log_speed)
        lag = max(1, round(0.5 / scenario.dt))
        v = scenario.states[:, :, :, 2]
        accel = (v[:, :, lag:] - v[:, :, :-lag]).abs() / (lag * scenario.dt)
        accel_ok = scenario.valid[:, :, lag:] & scenario.valid[:, :, :-lag]
        accel_ok[:, :, : max(0, scenario.current_index + 1 - lag)] = False  # only differences ending in the future
        excess = ((accel - self.max_accel).clamp_min(0) / self.max_accel).clamp_max(3.0)
        excess = (excess * accel_ok).sum(-1) / accel_ok.sum(-1).clamp_min(1)
        penalty = (cost.sum(-1) / steps + self.stall_weight * stalled.sum(-1) / driving.sum(-1).clamp_min(1)
                   + self.accel_weight * excess)
        if self.speed_weight:
            both = mask & logged.valid[:, :, future]
            relative = (speed - log_speed).abs() / log_speed.clamp_min(self.speed_floor)
            mismatch = (relative - self.speed_tolerance).clamp(0, 1) * both
            penalty = penalty + self.speed_weight * mismatch.sum(-1) / both.sum(-1).clamp_min(1)
        if self.kinematics_weight:
            ratio = kinematic_log_ratio(scenario, logged, mask.any(-1), self.kinematics_samples)
            penalty = penalty - self.kinematics_weight * ratio
        if self.heading_weight:
            turn_error = wrap_angle(scenario.states[:, :, future, 3] - logged.states[:, :, future, 3]).abs()
            mismatch = ((turn_error - self.heading_tolerance).clamp_min(0) / self.heading_scale).clamp_max(1)
            penalty = penalty + self.heading_weight * (mismatch * driving).sum(-1) / driving.sum(-1).clamp_min(1)
        return -(penalty * mask.any(-1))


KINEMATIC_BINS = {  # wider than the realism metric's bins: a reward must also see the values the metric drops
    "lon_acc": HistogramSpec(-6.0, 6.0, 48),
    "lat_acc": HistogramSpec(-6.0, 6.0, 48),
    "jerk": HistogramSpec(-8.0, 8.0, 64),
}
LOG_RATIO_CLIP = 3.0


def kinematic_log_ratio(scenario: ScenarioTensor, logged: ScenarioTensor, agents: torch.Tensor,
                        num_samples: int | None = None) -> torch.Tensor:
    """``(B, A)``: per agent, the mean over its valid future 0.5 s samples and the three body-frame quantities
    (``lon_acc``, ``lat_acc`` in m/s^2, ``jerk`` in m/s^3) of ``log p_log(q) - log p_scenario(q)``, clipped to
    +-3; 0 for agents outside ``agents (B, A)`` or without a future sample.

    ``p_log`` and ``p_scenario`` are add-one-smoothed histograms (:data:`KINEMATIC_BINS`, values outside
    clamped to the end bins) over the ``agents`` of every scenario in ``logged`` / ``scenario``: both sets of
    ``(B, A, T)`` windows must share shape, ``dt`` and ``current_index``. A sample counts as future when its
    newest position lies after ``current_index``; ``num_samples`` keeps only the first ones (None: all). With
    1 and a window whose history is a multiple of 0.5 s, the one sample scored is the first 0.5 s of the plan
    joined to the history: the acceleration and jerk a 2 Hz closed loop actually executes.
    """
    q_sim, ok_sim, _ = kinematics(scenario, "body")
    q_log, ok_log, _ = kinematics(logged, "body")
    stride = max(1, round(STAT_DT / scenario.dt))
    newest = torch.arange(ok_sim.shape[-1], device=ok_sim.device) * stride
    future = newest > scenario.current_index
    if num_samples is not None:
        future &= torch.cumsum(future.long(), 0) <= num_samples
    sim_mask = ok_sim & future & agents[..., None]
    log_mask = ok_log & future & agents[..., None]
    total = torch.zeros(agents.shape, dtype=torch.float64, device=agents.device)
    for name, spec in KINEMATIC_BINS.items():
        bins = []
        for values in (q_sim[name], q_log[name]):
            position = (values - spec.low) / (spec.high - spec.low) * spec.num_bins
            bins.append(position.nan_to_num(0.0).floor().long().clamp(0, spec.num_bins - 1))
        density = []
        for index, mask in zip(bins, (sim_mask, log_mask)):
            counts = torch.bincount(index[mask], minlength=spec.num_bins).double() + 1.0
            density.append(counts / counts.sum())
        ratio = (density[1].log() - density[0].log()).clamp(-LOG_RATIO_CLIP, LOG_RATIO_CLIP)
        total += (ratio[bins[0]] * sim_mask).sum(-1)
    count = sim_mask.sum(-1).clamp_min(1) * len(KINEMATIC_BINS)
    return (total / count).to(scenario.states.dtype)
