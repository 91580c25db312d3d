"""Where the fine-tuner's contexts come from: logged windows and failure-focused states.

Every context is a window ``[t - 30, t + future_steps]`` with ``current_index = 30`` (3 s of history), paired with
the same window of the *log* (the imitation loss always learns from logged behaviour).

* **log**: a training scene and a start step ``t`` drawn at random.
* **failure-focused** (``failure_fraction``): the current model drives ``failure_scenes`` training scenes in
  closed loop for 10 s; for every controlled agent that collides or leaves the road at step ``f``, a context is
  cut at ``t = f - d`` (``d`` uniform in 5..15 steps) from the simulated scene. Failures build up over a 10 s
  rollout while a sample covers a few seconds, so contexts drawn from the log rarely contain a sample that fails;
  these contexts put the states that lead to the model's own failures in front of the reward model (a
  prioritized replay of its mistakes, as DAgger-style data aggregation does for imitation).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

from trafficrlhf_sdk.alignment.config import FAILURE_DRIVE_S, FAILURE_LEAD_STEPS, HISTORY_STEPS, AlignConfig
from trafficrlhf_sdk.errors import DataNotFoundError
from trafficrlhf_sdk.simulation.guidance import GuidanceSet, guidance_swapped
from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_per_step
from trafficrlhf_sdk.models.adapter import TrafficModelAdapter
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

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
        self.failure_drive: FailureDrive | None = None  # the newest closed-loop failure run

    def draw(self, gen: torch.Generator) -> tuple[ScenarioTensor, ScenarioTensor]:
        """``(contexts, logged)``: ``contexts_per_epoch`` windows each, failure-focused ones first, then logged
        windows."""
        cfg = self.config
        total = cfg.contexts_per_epoch
        failing = min(total, round(cfg.failure_fraction * total))
        pairs: list[tuple[ScenarioTensor, ScenarioTensor]] = []
        if failing:
            pairs.append(self.failure_contexts(failing, gen))
            failing = pairs[-1][0].num_scenes  # may fall short: the log fills in
        if total - failing:
            pairs.append(self.log_contexts(total - failing, gen))
        return (ScenarioTensor.concat([p[0] for p in pairs]), ScenarioTensor.concat([p[1] for p in pairs]))

    # ------------------------------------------------------------------ pieces
    def window(self, scene: ScenarioTensor, start: int) -> ScenarioTensor:
        """Steps ``start .. start + history_steps + future_steps`` of ``scene``; "now" = ``history_steps``."""
        hist = HISTORY_STEPS
        window = scene.time_slice(start, start + hist + self.future_steps + 1)
        return window.replace_unchecked(current_index=hist, controlled=window.controlled & window.valid.any(-1))

    def log_contexts(self, count: int, gen: torch.Generator) -> tuple[ScenarioTensor, ScenarioTensor]:
        """``count`` logged windows at random scenes and start steps (with a controlled agent valid now)."""
        scenes, hist, h = self.scenes(), HISTORY_STEPS, self.future_steps
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

    def drive_for_failures(self, gen: torch.Generator) -> FailureDrive:
        """Drive ``failure_scenes`` random training scenes closed loop for 10 s with the current model."""
        cfg, scenes, hist, h = self.config, self.scenes(), HISTORY_STEPS, self.future_steps
        dt = scenes[0].dt
        drive = max(1, round(FAILURE_DRIVE_S / dt))
        fits = [i for i, s in enumerate(scenes) if s.num_steps >= hist + drive + h + 1]
        if not fits:
            raise DataNotFoundError(f"no training scene is long enough for a {drive * dt:.1f} s closed-loop run "
                                    f"plus {h} future steps.")
        order = [fits[i] for i in torch.randperm(len(fits), generator=gen)[: cfg.failure_scenes].tolist()]
        batch = self._drive_batch(order, drive)
        hybrid = self._drive(batch, drive)
        return FailureDrive(order, hybrid.states, hybrid.valid, hybrid.controlled, batch)

    def _drive_batch(self, order: Sequence[int], drive: int) -> ScenarioTensor:
        scenes, hist = self.scenes(), HISTORY_STEPS
        batch = ScenarioTensor.concat([scenes[i].time_slice(0, hist + drive + self.future_steps + 1)
                                       for i in order])
        return batch.replace_unchecked(current_index=hist)

    def failure_contexts(self, count: int, gen: torch.Generator) -> tuple[ScenarioTensor, ScenarioTensor]:
        """Up to ``count`` contexts cut shortly before the failures of a closed-loop run of the current model on
        ``failure_scenes`` training scenes (fewer if it produced fewer failures). Sets ``last_failure_events``."""
        hist = HISTORY_STEPS
        run = self.failure_drive = self.drive_for_failures(gen)
        drive = max(1, round(FAILURE_DRIVE_S / self.scenes()[0].dt))
        batch = run.batch
        hybrid = batch.replace_unchecked(states=run.states, valid=run.valid, controlled=run.controlled)
        driven = slice(hist + 1, hist + drive + 1)
        sim = hybrid.time_slice(0, hist + drive + 1)
        failed = torch.zeros_like(sim.valid)
        failed |= collisions_per_step(sim) & sim.valid
        if sim.map is not None and "drivable" in sim.map.layers:
            failed |= offroad_per_step(sim)
        failed = failed[:, :, driven] & hybrid.controlled[:, :, None]
        steps = torch.arange(drive) + hist + 1
        first = torch.where(failed, steps, torch.full_like(steps, 1 << 30)).min(-1).values  # (B, A)
        scene_idx, agent_idx = (first < (1 << 30)).nonzero(as_tuple=True)
        self.last_failure_events = int(scene_idx.numel())
        if self.last_failure_events == 0:
            return self.log_contexts(count, gen)
        pick = torch.randperm(self.last_failure_events, generator=gen)[:count]
        lo, hi = FAILURE_LEAD_STEPS
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
    """A closed-loop run of the model being aligned: the indices of the training scenes it drove, its simulated
    ``states (B, A, T, 4)``, ``valid (B, A, T)`` and ``controlled (B, A)`` (the log after the driven steps), and
    ``batch``, the logged scenes it started from."""

    order: list[int]
    states: torch.Tensor
    valid: torch.Tensor
    controlled: torch.Tensor
    batch: ScenarioTensor = field(repr=False)
