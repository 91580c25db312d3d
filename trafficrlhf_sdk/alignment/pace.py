"""The pace constraint of the fine-tuner: fewer failures without driving slower (a PPO-Lagrangian).

A reward that punishes collisions can be satisfied by braking, and a head trained to brake where a sample fails
brakes elsewhere too: the failure rate falls while the traffic slows down, which the evaluation reads as
``speed_ratio`` (speed / logged speed) against the base's. ``pace_tolerance`` turns "keep the base's pace" into a
constraint of the optimization instead of a number read after it, in the way constrained PPO does
(PPO-Lagrangian: Ray, Achiam and Amodei 2019, "Benchmarking Safe Exploration in Deep RL"; RCPO: Tessler, Mankowitz
and Mannor 2019):

1. **Measure.** Before each epoch's rollout the current policy drives fixed held-out scenes (all the
   ``holdout_every`` scenes the fine-tuner never trains on and loads, up to ``2 * failure_scenes``; its training
   scenes when none are held out) in closed loop for 10 s with a fixed seed, exactly as the evaluation does;
   ``pace_change`` is its pooled speed ratio (every driven agent's summed speed over the log's,
   :func:`~trafficrlhf_sdk.metrics.speed.pooled_speed_ratio`) over the starting weights' on the same scenes and
   seed, minus 1. The pairing keeps the spread between scenes out of the comparison, and pooling keeps scenes whose
   logged agents barely move from swinging it (the evaluation's ``speed_ratio``, a mean of per-scene ratios, moves
   several times more between seeds of the same weights). The same run's failure rate is recorded as
   ``heldout_failure``: the fine-tuner's progress on scenes it never trained on.
2. **Dual step.** Two multipliers, one per side of the band ``|pace_change| <= pace_tolerance``, each with its
   signed violation ``e_slow = -pace_change - tol`` and ``e_fast = pace_change - tol``: the accumulated
   ``I <- max(0, I + lr * e)``, and the epoch uses ``max(0, I + kp * e)`` (``pace_multiplier_kp``; 0: the plain
   Lagrangian, ``I`` itself). The plain Lagrangian is an integral controller, and the policy's pace integrates the
   push it gets, so a model that answers within a few epochs swings ever wider around the band; the proportional
   term damps that (the PID Lagrangian of Stooke, Achiam and Abbeel 2020, "Responsive Safety in Reinforcement
   Learning by PID Lagrangian Methods"). Both stay 0 while the pace is inside the band.
3. **Advantage.** Each sampled agent's samples are also ranked by their mean speed over the sampled future
   (normalized over the samples, as the reward's advantage is), and
   ``A = (A_reward + (slow - fast) * A_speed) / (1 + slow + fast)``. Agents the passing anchor holds (advantage 0
   from the reward) get the speed term alone; the others get both.
4. **Two bands** (``pace_by_turning``). A policy that brakes in turns and speeds up on the straight can keep the
   pooled pace of one set of scenes while the pace of another, with more turns, falls. With two bands the drive's
   agents whose logged heading turns by more than ``TURN_RAD`` (the speed metric's split) and the others each have
   their own ``pace_change`` and multipliers, and a training sample's agent takes the turning band's multipliers
   when the log of its context's window turns that much.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch

from trafficrlhf_sdk.alignment.config import ADVANTAGE_CLIP, FAILURE_DRIVE_S, HISTORY_STEPS
from trafficrlhf_sdk.errors import DataNotFoundError
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.guidance import GuidanceSet, guidance_swapped

__all__ = ["PaceConstraint", "logged_turning", "sample_speeds"]

PACE_SEED = 0
"""Seed of every pace drive (the same random numbers each epoch, so that the pace moves with the weights only)."""


def sample_speeds(scenario: ScenarioTensor, steps: int) -> torch.Tensor:
    """``(B, A)``: each agent's mean absolute speed over the ``steps`` steps after ``current_index`` (its valid
    steps; 0 where it has none)."""
    now = scenario.current_index
    window = slice(now + 1, now + 1 + steps)
    valid = scenario.valid[:, :, window].to(scenario.states.dtype)
    speed = scenario.states[:, :, window, 2].abs() * valid
    return speed.sum(-1) / valid.sum(-1).clamp_min(1.0)


def _normalized(values: torch.Tensor, dim: int) -> torch.Tensor:
    centred = values - values.mean(dim, keepdim=True)
    return (centred / (values.std(dim, unbiased=False, keepdim=True) + 1e-6)).clamp(-ADVANTAGE_CLIP, ADVANTAGE_CLIP)


class _Multipliers:
    """The two multipliers of one band (slow and fast side) and their accumulated parts."""

    def __init__(self) -> None:
        self.slow = self.fast = 0.0  # what the epoch uses
        self.slow_sum = self.fast_sum = 0.0  # the accumulated (integral) parts

    def update(self, change: float, tolerance: float, lr: float, kp: float) -> None:
        if math.isnan(change):  # nothing of this kind was driven: nothing to hold
            return
        e_slow, e_fast = -change - tolerance, change - tolerance
        self.slow_sum = max(0.0, self.slow_sum + lr * e_slow)
        self.fast_sum = max(0.0, self.fast_sum + lr * e_fast)
        self.slow = max(0.0, self.slow_sum + kp * e_slow)
        self.fast = max(0.0, self.fast_sum + kp * e_fast)


class PaceConstraint:
    """The multipliers, the pace drive and the advantage mix of the pace constraint (module docstring).

    Args:
        tolerance: the band ``|pace_change| <= tolerance`` (0.03: within 3 % of the starting pace).
        lr: step size of the multipliers per unit of violation.
        scenes: a callable returning the scenes to drive (single-scene tensors).
        count: at most how many of them (those long enough for 3 s of history and a 10 s drive).
        guidance: the guidance the model drives with (None: its own).
        kp: the proportional gain (0: the plain Lagrangian).
        by_turning: hold two bands, one for the agents that turn in the log and one for the others
            (``AlignConfig.pace_by_turning``), instead of one for all agents.
    """

    def __init__(self, tolerance: float, lr: float, scenes: Callable[[], Sequence[ScenarioTensor]], count: int,
                 guidance: GuidanceSet | None, kp: float = 0.0, by_turning: bool = False) -> None:
        self.tolerance = tolerance
        self.lr = lr
        self.kp = kp
        self.scenes = scenes
        self.count = count
        self.guidance = guidance
        self.kinds: tuple[str, ...] = ("turning", "straight") if by_turning else ("",)
        self.bands = {kind: _Multipliers() for kind in self.kinds}
        self.base: dict[str, float] | None = None  # the starting weights' pooled ratios, by kind
        self._batch: ScenarioTensor | None = None

    @property
    def by_turning(self) -> bool:
        """Whether turning and straight agents have bands of their own."""
        return len(self.kinds) == 2

    @staticmethod
    def _key(name: str, kind: str) -> str:
        return f"{name}_{kind}" if kind else name

    # ------------------------------------------------------------------ measurement
    def batch(self) -> ScenarioTensor:
        """The fixed held-out scenes, cut to 3 s of history and the 10 s drive."""
        if self._batch is None:
            scenes = list(self.scenes())
            drive = max(1, round(FAILURE_DRIVE_S / scenes[0].dt)) if scenes else 1
            fits = [s for s in scenes if s.num_steps >= HISTORY_STEPS + drive + 1][: self.count]
            if not fits:
                raise DataNotFoundError(f"pace_tolerance: no held-out scene is long enough for {HISTORY_STEPS} "
                                        f"history steps and a {FAILURE_DRIVE_S:g} s drive; set pace_tolerance to "
                                        "None or give longer scenes.")
            batch = ScenarioTensor.concat([s.time_slice(0, HISTORY_STEPS + drive + 1) for s in fits])
            self._batch = batch.replace_unchecked(current_index=HISTORY_STEPS)
        return self._batch

    def drive(self, model: Any) -> dict[str, float]:
        """``pooled_speed_ratio`` (and ``pooled_speed_ratio_turning`` / ``_straight`` with ``by_turning``) and
        ``failure_rate`` of ``model`` on the pace scenes, 10 s closed loop, fixed seed (the global generator is left
        as it was)."""
        from trafficrlhf_sdk.metrics.failure import FailureMetric
        from trafficrlhf_sdk.metrics.speed import pooled_speed_ratio
        from trafficrlhf_sdk.simulation.policies import policy_seed, seed_policy
        from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

        own_seed = policy_seed(model, PACE_SEED)
        with torch.random.fork_rng(devices=[]), guidance_swapped(model, self.guidance), torch.no_grad():
            torch.manual_seed(PACE_SEED)
            seed_policy(model, PACE_SEED)
            try:
                rollout = simulate(model, self.batch(), SimulationConfig(duration_s=FAILURE_DRIVE_S))
            finally:
                seed_policy(model, own_seed)
        measured = {"pooled_speed_ratio": pooled_speed_ratio(rollout),
                    "failure_rate": FailureMetric().compute(rollout).values["failure_rate"]}
        if self.by_turning:
            for kind in self.kinds:
                measured[f"pooled_speed_ratio_{kind}"] = pooled_speed_ratio(rollout, turning=kind == "turning")
        return measured

    def step(self, model: Any, measured: dict[str, float] | None = None) -> dict[str, float]:
        """Drive the current ``model`` (or take its ``measured`` :meth:`drive`), update the multipliers; the first
        call sets the starting pace unless :attr:`base` is set. Returns the epoch's statistics (``pace_change``,
        ``heldout_failure``, the multipliers; with ``by_turning`` each of the two kinds' as well)."""
        measured = measured or self.drive(model)
        if self.base is None:
            self.set_base(measured)
        assert self.base is not None
        stats = {"pace_change": measured["pooled_speed_ratio"] / self.base[""] - 1.0,
                 "heldout_failure": measured["failure_rate"]}
        for kind, band in self.bands.items():
            key = self._key("pooled_speed_ratio", kind)
            change = measured[key] / self.base[kind] - 1.0
            band.update(change, self.tolerance, self.lr, self.kp)
            if kind:
                stats[f"pace_change_{kind}"] = change
            stats[self._key("pace_multiplier_slow", kind)] = band.slow
            stats[self._key("pace_multiplier_fast", kind)] = band.fast
            if self.kp > 0:
                stats[self._key("pace_integral_slow", kind)] = band.slow_sum
                stats[self._key("pace_integral_fast", kind)] = band.fast_sum
        return stats

    def set_base(self, measured: dict[str, float]) -> None:
        """Take the starting weights' :meth:`drive` as the reference of every band."""
        self.base = {"": measured["pooled_speed_ratio"]}
        for kind in self.kinds:
            if kind:
                self.base[kind] = measured[f"pooled_speed_ratio_{kind}"]

    def restore(self, history: Sequence[dict[str, float]]) -> None:
        """Take the multipliers back from a resumed run's history (the starting pace is measured again)."""
        if history:
            last = history[-1]
            for kind, band in self.bands.items():
                band.slow = float(last.get(self._key("pace_multiplier_slow", kind), 0.0))
                band.fast = float(last.get(self._key("pace_multiplier_fast", kind), 0.0))
                band.slow_sum = float(last.get(self._key("pace_integral_slow", kind), band.slow))
                band.fast_sum = float(last.get(self._key("pace_integral_fast", kind), band.fast))

    # ------------------------------------------------------------------ advantages
    def mix(self, advantages: torch.Tensor, speeds: torch.Tensor, dim: int, mask: torch.Tensor,
            turning: torch.Tensor | None = None) -> torch.Tensor:
        """``(A_reward + (slow - fast) * A_speed) / (1 + slow + fast)``: ``advantages`` and ``speeds`` have the same
        shape, samples along ``dim``; ``mask`` (broadcastable) zeroes entries that get no advantage. With
        ``by_turning``, ``turning`` (bool, broadcastable) says which agents take the turning band's multipliers."""
        if all(band.slow == 0.0 and band.fast == 0.0 for band in self.bands.values()):
            return advantages
        if self.by_turning:
            if turning is None:
                raise ValueError("mix: `turning` is needed when the pace is held apart for turning agents.")
            turn, straight = self.bands["turning"], self.bands["straight"]
            slow = torch.where(turning, turn.slow, straight.slow).to(advantages.dtype)
            fast = torch.where(turning, turn.fast, straight.fast).to(advantages.dtype)
        else:
            slow = torch.tensor(self.bands[""].slow, dtype=advantages.dtype)
            fast = torch.tensor(self.bands[""].fast, dtype=advantages.dtype)
        speed_adv = _normalized(speeds, dim) * mask.to(speeds.dtype)
        return (advantages + (slow - fast) * speed_adv) / (1.0 + slow + fast)


def logged_turning(logged: ScenarioTensor) -> torch.Tensor:
    """``(B, A)``: agents whose logged heading turns by more than ``TURN_RAD`` over the steps after
    ``current_index`` of ``logged`` (the log of a training context's window), as the speed metric splits them."""
    from trafficrlhf_sdk.metrics.turns import turning_agents

    future = logged.time_slice(logged.current_index + 1, logged.num_steps)
    return turning_agents(future, future.valid)
