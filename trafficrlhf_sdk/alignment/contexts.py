"""Where the fine-tuner's contexts come from: logged windows, closed-loop lead-ins and failure-focused states.

Every context is a window ``[t - history_steps, t + future_steps]`` with ``current_index = history_steps``,
paired with the same window of the *log* (the imitation loss always learns from logged behaviour).

* **log**: a training scene and a start step ``t`` drawn at random.
* **closed-loop lead-in** (``closed_loop_fraction``): the current model drives for a random 0.5 s multiple first,
  so the history is the model's own.
* **perturbed** (``perturb_fraction``): a logged window whose controlled agents' histories are shifted and turned
  rigidly off the log, so the model starts off its lane on any training road (DART-style noise injection).
* **failure-focused** (``failure_fraction``): the current model drives ``failure_scenes`` training scenes in
  closed loop; for every controlled agent that collides or leaves the road at step ``f``, a context is cut at
  ``t = f - d`` (``d`` drawn in ``failure_lead_steps``) from the simulated scene. Failures build up over a
  10 s rollout while a sample covers 2 s, so contexts drawn from the log rarely contain a sample that fails;
  these contexts put the states that lead to failures in front of the reward model (a prioritized replay of
  the model's own mistakes, as DAgger-style data aggregation does for imitation). With
  ``failure_refresh_every = k`` the closed-loop drive (most of an epoch's rollout time) runs in epochs
  0, k, 2k, ... only; the epochs between cut new contexts (other events, other leads) from the same drive.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

from trafficrlhf_sdk.alignment.config import AlignConfig
from trafficrlhf_sdk.errors import DataNotFoundError
from trafficrlhf_sdk.simulation.guidance import GuidanceSet, guidance_swapped
from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_per_step
from trafficrlhf_sdk.models.adapter import TrafficModelAdapter
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.scenario.transforms import perturb_history

__all__ = ["ContextSampler", "FailureDrive", "held_out_scene_ids", "training_scene_ids"]


def training_scene_ids(scene_ids: Sequence[str], holdout_every: int | None) -> list[str]:
    """``scene_ids`` without every ``holdout_every``-th one (positions k-1, 2k-1, ...); all when None."""
    if holdout_every is None:
        return list(scene_ids)
    return [s for i, s in enumerate(scene_ids) if (i + 1) % holdout_every]


def held_out_scene_ids(scene_ids: Sequence[str], holdout_every: int) -> list[str]:
    """The scenes :func:`training_scene_ids` leaves out: positions k-1, 2k-1, ... of ``scene_ids``."""
    return list(scene_ids[holdout_every - 1 :: holdout_every])


class ContextSampler:
    """Draws an epoch's contexts for :class:`~trafficrlhf_sdk.alignment.AlignTrainer`.

    Args:
        model: the adapter being aligned (drives the closed-loop parts).
        config: the run's :class:`AlignConfig`.
        scenes: a callable returning the training scenes (single-scene tensors), loaded lazily.
        guidance: the guidance used while the model drives (None: the adapter's own).
        future_steps: log steps kept after each context's "now".
    """

    def __init__(self, model: TrafficModelAdapter, config: AlignConfig,
                 scenes: Callable[[], list[ScenarioTensor]], guidance: GuidanceSet | None,
                 future_steps: int) -> None:
        self.model = model
        self.config = config
        self.scenes = scenes
        self.guidance = guidance
        self.future_steps = future_steps
        self.last_failure_events = 0
        self.failure_drive: FailureDrive | None = None  # the newest closed-loop failure run and its epoch

    def draw(self, gen: torch.Generator, epoch: int | None = None) -> tuple[ScenarioTensor, ScenarioTensor]:
        """``(contexts, logged)``: ``contexts_per_epoch`` windows each, in the order failure-focused,
        closed-loop lead-in, perturbed, log. ``epoch`` (0-based) lets failure-focused contexts reuse the drive of an
        earlier epoch of the same ``failure_refresh_every`` block; None: always drive afresh."""
        cfg = self.config
        total = cfg.contexts_per_epoch
        failing = min(total, round(cfg.failure_fraction * total))
        closed = min(total - failing, round(cfg.closed_loop_fraction * total))
        pairs: list[tuple[ScenarioTensor, ScenarioTensor]] = []
        if failing:
            pairs.append(self.failure_contexts(failing, gen, epoch))
            failing = pairs[-1][0].num_scenes  # may fall short: the log fills in
        if closed:
            pairs.append(self.closed_loop_contexts(closed, gen))
        moved = min(total - failing - closed, round(cfg.perturb_fraction * total))
        if moved:
            pairs.append(self.perturbed_contexts(moved, gen))
        if total - failing - closed - moved:
            pairs.append(self.log_contexts(total - failing - closed - moved, gen))
        return (ScenarioTensor.concat([p[0] for p in pairs]), ScenarioTensor.concat([p[1] for p in pairs]))

    # ------------------------------------------------------------------ pieces
    def window(self, scene: ScenarioTensor, start: int) -> ScenarioTensor:
        """Steps ``start .. start + history_steps + future_steps`` of ``scene``; "now" = ``history_steps``."""
        hist = self.config.history_steps
        window = scene.time_slice(start, start + hist + self.future_steps + 1)
        return window.replace_unchecked(current_index=hist, controlled=window.controlled & window.valid.any(-1))

    def log_contexts(self, count: int, gen: torch.Generator) -> tuple[ScenarioTensor, ScenarioTensor]:
        """``count`` logged windows at random scenes and start steps (with a controlled agent valid now)."""
        scenes, hist, h = self.scenes(), self.config.history_steps, self.future_steps
        parts: list[ScenarioTensor] = []
        for _ in range(100 * count):
            if len(parts) == count:
                break
            scene = scenes[int(torch.randint(len(scenes), (1,), generator=gen))]
            last = scene.num_steps - 1 - h
            if last < hist:
                continue
            t = int(torch.randint(hist, last + 1, (1,), generator=gen))
            if not (scene.controlled & scene.valid[:, :, t]).any():
                continue
            parts.append(self.window(scene, t - hist))
        if len(parts) < count:
            raise DataNotFoundError(f"could not find {count} contexts with controlled agents and {hist} history + "
                                    f"{h} future steps in the training scenes.")
        batch = ScenarioTensor.concat(parts)
        return batch, batch

    def perturbed_contexts(self, count: int, gen: torch.Generator) -> tuple[ScenarioTensor, ScenarioTensor]:
        """``count`` logged windows whose controlled agents' histories are moved rigidly off the log
        (:func:`~trafficrlhf_sdk.scenario.perturb_history`, shift and turn uniform in +- ``perturb_lateral_m`` /
        ``perturb_yaw_rad``), paired with the unmoved windows. An agent the move would put off the drivable
        layer now, or into another agent's box, keeps its logged history."""
        cfg = self.config
        logged, _ = self.log_contexts(count, gen)
        shape = logged.controlled.shape
        lateral = (2 * torch.rand(shape, generator=gen) - 1) * cfg.perturb_lateral_m
        turn = (2 * torch.rand(shape, generator=gen) - 1) * cfg.perturb_yaw_rad
        movable = logged.controlled
        moved = perturb_history(logged, lateral * movable, turn * movable)
        now = logged.current_index
        bad = (collisions_per_step(moved.time_slice(now, now + 1))[:, :, 0]
               & ~collisions_per_step(logged.time_slice(now, now + 1))[:, :, 0])
        if logged.map is not None and "drivable" in logged.map.layers:
            bad |= offroad_per_step(moved.time_slice(now, now + 1))[:, :, 0]
        keep = movable & ~bad
        return perturb_history(logged, lateral * keep, turn * keep), logged

    def _drive(self, batch: ScenarioTensor, steps: int) -> ScenarioTensor:
        """``batch`` with its controlled agents driven by the model for ``steps`` steps after ``current_index``
        (the log afterwards and for everyone else); ``controlled`` = the agents the simulator drove."""
        from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

        start = batch.current_index
        with guidance_swapped(self.model, self.guidance), torch.no_grad():
            rollout = simulate(self.model, batch, SimulationConfig(duration_s=steps * batch.dt, start_index=start))
        t = start + steps
        states = torch.cat([rollout.simulated.states[:, :, : t + 1], batch.states[:, :, t + 1:]], 2)
        valid = torch.cat([rollout.simulated.valid[:, :, : t + 1], batch.valid[:, :, t + 1:]], 2)
        return batch.replace_unchecked(states=states * valid[..., None], valid=valid, controlled=rollout.controlled)

    def closed_loop_contexts(self, count: int, gen: torch.Generator) -> tuple[ScenarioTensor, ScenarioTensor]:
        """``count`` contexts at ``t = history_steps + lead``, where the steps up to ``t`` were driven by the model
        (a lead-in of a random multiple of 0.5 s up to ``closed_loop_max_s``)."""
        cfg, scenes, hist, h = self.config, self.scenes(), self.config.history_steps, self.future_steps
        dt = scenes[0].dt
        replan = max(1, round(0.5 / dt))
        most = max(1, int(cfg.closed_loop_max_s / (replan * dt) + 1e-9))
        lead = replan * int(torch.randint(1, most + 1, (1,), generator=gen))
        fits = [s for s in scenes if s.num_steps >= hist + lead + h + 1]
        if not fits:
            raise DataNotFoundError(f"no training scene is long enough for a {lead * dt:.1f} s closed-loop lead-in.")
        picks = [fits[int(torch.randint(len(fits), (1,), generator=gen))] for _ in range(count)]
        batch = ScenarioTensor.concat([s.time_slice(0, hist + lead + h + 1) for s in picks])
        batch = batch.replace_unchecked(current_index=hist)
        hybrid = self._drive(batch, lead)
        sim = self.window(hybrid, lead)
        sim = sim.replace_unchecked(controlled=sim.controlled & sim.valid[:, :, hist])
        log = self.window(batch.replace_unchecked(controlled=hybrid.controlled), lead)
        return sim, log

    def drive_for_failures(self, gen: torch.Generator, epoch: int = 0) -> FailureDrive:
        """Drive ``failure_scenes`` random training scenes closed loop for ``failure_drive_s`` with the current
        model and record each controlled agent's first failure step."""
        cfg, scenes, hist, h = self.config, self.scenes(), self.config.history_steps, self.future_steps
        dt = scenes[0].dt
        drive = max(1, round(cfg.failure_drive_s / dt))
        fits = [i for i, s in enumerate(scenes) if s.num_steps >= hist + drive + h + 1]
        if not fits:
            raise DataNotFoundError(f"no training scene is long enough for a {drive * dt:.1f} s closed-loop run "
                                    f"plus {h} future steps; lower `failure_drive_s`.")
        order = [fits[i] for i in torch.randperm(len(fits), generator=gen)[: cfg.failure_scenes].tolist()]
        batch = self._drive_batch(order, drive)
        hybrid = self._drive(batch, drive)
        return FailureDrive(epoch, order, hybrid.states, hybrid.valid, hybrid.controlled, batch)

    def _drive_batch(self, order: Sequence[int], drive: int) -> ScenarioTensor:
        scenes, hist = self.scenes(), self.config.history_steps
        batch = ScenarioTensor.concat([scenes[i].time_slice(0, hist + drive + self.future_steps + 1)
                                       for i in order])
        return batch.replace_unchecked(current_index=hist)

    def _current_drive(self, gen: torch.Generator, epoch: int | None) -> FailureDrive:
        every, cached = self.config.failure_refresh_every, self.failure_drive
        fresh = (epoch is None or cached is None or every == 1
                 or epoch // every != cached.epoch // every or epoch < cached.epoch)
        if fresh:
            self.failure_drive = self.drive_for_failures(gen, 0 if epoch is None else epoch)
        assert self.failure_drive is not None
        return self.failure_drive

    def failure_contexts(self, count: int, gen: torch.Generator,
                         epoch: int | None = None) -> tuple[ScenarioTensor, ScenarioTensor]:
        """Up to ``count`` contexts cut shortly before the failures of a closed-loop run of the current model on
        ``failure_scenes`` training scenes (fewer if it produced fewer failures); the run is reused within a
        ``failure_refresh_every`` block of epochs. Sets ``last_failure_events``."""
        cfg, hist = self.config, self.config.history_steps
        run = self._current_drive(gen, epoch)
        drive = max(1, round(cfg.failure_drive_s / self.scenes()[0].dt))
        if run.batch is None:  # restored from a checkpoint: rebuild the logged scenes it drove
            run.batch = self._drive_batch(run.order, drive)
        batch = run.batch
        hybrid = batch.replace_unchecked(states=run.states, valid=run.valid, controlled=run.controlled)
        driven = slice(hist + 1, hist + drive + 1)
        sim = hybrid.time_slice(0, hist + drive + 1)
        failed = torch.zeros_like(sim.valid)
        if "collision" in cfg.failure_kinds:
            failed |= collisions_per_step(sim) & sim.valid
        if "offroad" in cfg.failure_kinds and sim.map is not None and "drivable" in sim.map.layers:
            failed |= offroad_per_step(sim)
        failed = failed[:, :, driven] & hybrid.controlled[:, :, None]
        steps = torch.arange(drive) + hist + 1
        first = torch.where(failed, steps, torch.full_like(steps, 1 << 30)).min(-1).values  # (B, A)
        scene_idx, agent_idx = (first < (1 << 30)).nonzero(as_tuple=True)
        self.last_failure_events = int(scene_idx.numel())
        if self.last_failure_events == 0:
            return self.log_contexts(count, gen)
        pick = torch.randperm(self.last_failure_events, generator=gen)[:count]
        lo, hi = cfg.failure_lead_steps
        sims, logs = [], []
        for i in pick.tolist():
            b = int(scene_idx[i])
            lead = int(torch.randint(lo, hi + 1, (1,), generator=gen))
            t = max(hist, int(first[b, agent_idx[i]]) - lead)
            scene = hybrid[b]
            ctx = self.window(scene, t - hist)
            ctx = ctx.replace_unchecked(controlled=ctx.controlled & ctx.valid[:, :, hist])
            if not ctx.controlled.any():
                continue
            sims.append(ctx)
            logs.append(self.window(batch[b].replace_unchecked(controlled=scene.controlled), t - hist))
        if not sims:
            return self.log_contexts(count, gen)
        return ScenarioTensor.concat(sims), ScenarioTensor.concat(logs)


@dataclass
class FailureDrive:
    """A closed-loop run of the model being aligned, kept for reuse: the epoch (0-based) it was driven in, the
    indices of the training scenes it drove, and its simulated ``states (B, A, T, 4)``, ``valid (B, A, T)`` and
    ``controlled (B, A)`` (the log after the driven steps); ``batch``: the logged scenes it started from (not
    saved, rebuilt from ``order``)."""

    epoch: int
    order: list[int]
    states: torch.Tensor
    valid: torch.Tensor
    controlled: torch.Tensor
    batch: ScenarioTensor | None = field(default=None, repr=False)

    def to_tensors(self) -> dict[str, torch.Tensor]:
        """Flat tensors for a safetensors checkpoint."""
        return {"epoch": torch.tensor([self.epoch]), "order": torch.tensor(self.order, dtype=torch.long),
                "states": self.states.contiguous(), "valid": self.valid.contiguous(),
                "controlled": self.controlled.contiguous()}

    @classmethod
    def from_tensors(cls, tensors: dict[str, torch.Tensor]) -> FailureDrive:
        """The inverse of :meth:`to_tensors`."""
        return cls(int(tensors["epoch"][0]), tensors["order"].tolist(), tensors["states"], tensors["valid"],
                   tensors["controlled"])
