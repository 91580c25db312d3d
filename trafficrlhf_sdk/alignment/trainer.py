"""``AlignTrainer``: PPO fine-tuning of any :class:`~trafficrlhf_sdk.models.TrafficModelAdapter` against a reward
model, through the adapter contract only (``sample``, ``log_prob``, ``imitation_loss``, ``parameter_groups``).

One epoch:

1. **Rollout.** ``contexts_per_epoch`` contexts from a :class:`~trafficrlhf_sdk.alignment.contexts.ContextSampler`:
   logged windows and, with ``failure_fraction``, states shortly before the current model's own closed-loop
   failures. Per context the adapter draws ``samples_per_context`` futures (with the configured guidance, no
   gradient). Each sample becomes a scenario: the context's history, then the sample's future for the sampled
   (controlled) agents and the log for everyone else. Its reward is the reward model's score of that scenario
   (``credit="scene"``), or one score per sampled agent (``credit="agent"``, ``agent_scores``).
2. **Advantages.** ``A = (r - mean_context) / (std_context + eps)`` over the samples of a context (of each agent
   of a context with ``credit="agent"``), clipped to +-5. With scene credit one advantage per (context, sample)
   is shared by every sampled agent; for per-step log-probabilities such as a diffusion chain, by every
   denoising step (DDPO), or the first ``denoising_steps`` of them.
3. **Optimization.** ``ppo_epochs`` passes over minibatches of contexts: ``ratio = exp(log_prob - log_prob_old)``
   elementwise (per agent, per denoising step where the adapter returns ``(B, S, A, K)``), surrogate
   ``min(ratio * A, clip(ratio) * A)`` averaged over sampled agents (and steps), loss
   ``imitation_coef * imitation_loss - alpha * surrogate (+ kl_coef * KL to the frozen starting model)``,
   gradient clipping, and the early stop once the approximate KL passes ``1.5 * target_kl``. With
   ``passing_anchor_coef > 0`` (agent credit), agents none of whose samples fails get advantage 0 and
   ``passing_anchor_coef * KL`` to the starting model on their own samples instead. With ``pace_tolerance``, each
   sample's speed also enters the advantages, weighted by a multiplier that tracks the pace of a held-out
   closed-loop drive (:mod:`~trafficrlhf_sdk.alignment.pace`). With ``choice_coef`` and an adapter that offers
   discrete choices (``choice_futures``, e.g. a mixture's modes), every choice's future of every sampled agent is
   scored too, and ``alpha * choice_coef * sum_c pi_c A_c`` (advantages normalized over the choices) joins the
   objective.

``log_prob_old`` is recomputed with ``adapter.log_prob`` before any update, on the very minibatches of the first
pass, so the first minibatch's ratios are exactly 1. Every random draw of epoch ``e`` comes from generators seeded
by ``(seed, e)``, which makes a resumed run match an uninterrupted one.
"""

from __future__ import annotations

import copy
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch

from trafficrlhf_sdk.alignment.checkpointing import TrainerCheckpoints
from trafficrlhf_sdk.alignment.config import ADVANTAGE_CLIP, REWARD_HISTORY_STEPS, AlignConfig
from trafficrlhf_sdk.alignment.distributed import sample_in_chunks
from trafficrlhf_sdk.alignment.contexts import ContextSampler, held_out_scene_ids, training_scene_ids
from trafficrlhf_sdk.alignment.health import health_warnings
from trafficrlhf_sdk.alignment.monitor import HeldOutMonitor, plot_overoptimization
from trafficrlhf_sdk.alignment.pace import PaceConstraint, logged_turning, sample_speeds
from trafficrlhf_sdk.alignment.ppo_update import PPOUpdate, SampledEpoch, derived_generator, mean_over_sampled
from trafficrlhf_sdk.reward.builtin import FailureReward
from trafficrlhf_sdk.reward.scoring import RewardLike, agent_scores, scenario_scores
from trafficrlhf_sdk.alignment.sample_scenarios import SampleScenarios
from trafficrlhf_sdk.console import warn
from trafficrlhf_sdk.errors import DataNotFoundError, TrafficRLHFError
from trafficrlhf_sdk.parallel import ExecutionConfig, ray_session
from trafficrlhf_sdk.simulation.guidance import GuidanceSet
from trafficrlhf_sdk.models.adapter import TrafficModelAdapter
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.scenario.transforms import mirror_scenario

MONITOR_CONTEXTS = 8  # logged contexts the over-optimization monitor samples every epoch
MONITOR_FAILURE_CONTEXTS = 16  # and contexts cut before the starting model's failures
MONITOR_SAMPLES = 4  # futures per monitor context

__all__ = ["AlignResult", "AlignTrainer", "RewardLike", "agent_scores", "scenario_scores"]


def _check_reference(model: TrafficModelAdapter, reference: TrafficModelAdapter) -> None:
    """Raise unless ``reference`` can score ``model``'s samples: same class, same parameter names and shapes."""
    if type(reference) is not type(model):
        raise TrafficRLHFError(f"`reference` is a {type(reference).__name__} but the model is a "
                               f"{type(model).__name__}; pass a reference built by the same adapter.")
    ours = {k: tuple(v.shape) for k, v in model.module.state_dict().items()}
    theirs = {k: tuple(v.shape) for k, v in reference.module.state_dict().items()}
    if ours != theirs:
        missing = sorted(set(ours) - set(theirs))[:3]
        extra = sorted(set(theirs) - set(ours))[:3]
        reshaped = sorted(k for k in set(ours) & set(theirs) if ours[k] != theirs[k])[:3]
        raise TrafficRLHFError(f"`reference` does not have the model's parameters (missing {missing}, extra "
                               f"{extra}, other shapes {reshaped}); build it with the same model options (e.g. "
                               "the same head) from the checkpoint it should hold the policy to.")


class AlignResult(NamedTuple):
    """What :func:`trafficrlhf_sdk.alignment` returns: the aligned adapter (the same object, updated in place) and
    one dict of statistics per epoch."""

    model: TrafficModelAdapter
    history: list[dict[str, float]]


class AlignTrainer(TrainerCheckpoints, SampleScenarios, PPOUpdate):
    """PPO fine-tuner of a traffic-model adapter against a reward model (see the module docstring).

    Args:
        model: the adapter to align; it is updated in place.
        reward_model: anything with ``step_rewards(scenario) -> (B, T)`` (or a ``score(scenario) -> (B,)``).
        config: an :class:`AlignConfig`.
        scenes: training scenes (each ``B = 1`` or a batch, split into single scenes); None loads the 'train'
            split of ``config.source``.
        reference: the frozen model the KL terms (``kl_coef``, ``passing_anchor_coef``) hold the policy to;
            None: a copy of ``model`` as it starts. It must be the same adapter class with the same parameter
            names and shapes.
        monitor_reward: a second reward model the policy never trains on (e.g. one trained on other annotators),
            recorded per epoch as ``heldout_reward`` beside the stand-in annotators' ``heldout_realism``
            (:mod:`trafficrlhf_sdk.alignment.monitor`).
    """

    def __init__(self, model: TrafficModelAdapter, reward_model: Any, config: AlignConfig | None = None,
                 scenes: ScenarioTensor | Sequence[ScenarioTensor] | None = None,
                 reference: TrafficModelAdapter | None = None, monitor_reward: Any = None) -> None:
        self.model = model
        self.reward_model = reward_model
        self.config = config or AlignConfig()
        self.horizon = int(getattr(model, "horizon", 20))
        self.future_steps = self.horizon  # log steps kept after "now"
        self.reward_steps = self.horizon  # sampled steps the reward model scores
        offered = model.parameter_groups()
        names = tuple(offered) if self.config.groups is None else self.config.groups
        unknown = [n for n in names if n not in offered]
        if unknown:
            name = model.name or type(model).__name__
            raise TrafficRLHFError(f"parameter group(s) {unknown} are not offered by {name!r}; it offers "
                                   f"{sorted(offered)}.")
        self.group_names = names
        seen: set[int] = set()
        self.trainable: list[torch.nn.Parameter] = []
        for name in names:
            for p in offered[name]:
                if id(p) not in seen:
                    seen.add(id(p))
                    self.trainable.append(p)
        if not self.trainable:
            raise TrafficRLHFError(f"parameter groups {list(names)} hold no parameters; nothing to train.")
        self.optimizer = torch.optim.AdamW(self.trainable, lr=self.config.learning_rate, weight_decay=0.0)
        self.guidance = GuidanceSet.parse(self.config.guidance)
        keeps_reference = max(self.config.kl_coef, self.config.passing_anchor_coef) > 0
        if reference is not None:
            if not keeps_reference:
                raise TrafficRLHFError("`reference` was given but kl_coef and passing_anchor_coef are both 0, so "
                                       "nothing would use it; set one of them or drop `reference`.")
            _check_reference(model, reference)
            self.reference = copy.deepcopy(reference)
        else:
            self.reference = copy.deepcopy(model) if keeps_reference else None
        if self.reference is not None:
            for p in self.reference.module.parameters():
                p.requires_grad_(False)
        self.scenes_given = scenes
        self.scenes = self._with_mirrored(self._split_scenes(scenes)) if scenes is not None else None
        self.context_sampler = ContextSampler(model, self.config, self._load_scenes, self.guidance,
                                              self.future_steps)
        if getattr(reward_model, "uses_log", False) and self.config.credit != "agent":
            raise TrafficRLHFError(f"{type(reward_model).__name__} compares each agent with its logged future and "
                                   "scores agents only; use credit='agent'.")
        if self.config.choice_coef > 0 and type(model).choice_futures is TrafficModelAdapter.choice_futures:
            raise TrafficRLHFError(f"choice_coef is {self.config.choice_coef} but {type(model).__name__} offers no "
                                   "discrete choices (it does not implement choice_futures and choice_log_prob); "
                                   "set choice_coef = 0.")
        if self.config.credit == "agent" and not callable(getattr(reward_model, "agent_scores", None)):
            raise TrafficRLHFError(f"credit='agent' needs a reward model with `agent_scores(scenario) -> (B, A)`; "
                                   f"{type(reward_model).__name__} has none. Use credit='scene'.")
        self.monitor = HeldOutMonitor(monitor_reward, self.config.early_stopping_patience)
        self.monitor_contexts: ScenarioTensor | None = None
        self.monitor_logged: ScenarioTensor | None = None
        self.held_out: list[ScenarioTensor] | None = None
        self.pace = None if self.config.pace_tolerance is None else PaceConstraint(
            self.config.pace_tolerance, self.config.pace_multiplier_lr, self._held_out_scenes,
            2 * self.config.failure_scenes, self.guidance, kp=self.config.pace_multiplier_kp,
            by_turning=self.config.pace_by_turning)
        self.history: list[dict[str, float]] = []
        self.start_epoch = 0
        self.logger: Any = None
        self.execution: Any = None  # an ExecutionConfig: where each epoch's sample chunks run (distribute_rollouts)

    # ------------------------------------------------------------------ data
    @staticmethod
    def _split_scenes(scenes: ScenarioTensor | Sequence[ScenarioTensor]) -> list[ScenarioTensor]:
        items = [scenes] if isinstance(scenes, ScenarioTensor) else list(scenes)
        return [s[i] for s in items for i in range(s.num_scenes)]

    def _load_scenes(self) -> list[ScenarioTensor]:
        if self.scenes is None:
            from trafficrlhf_sdk.plugins import get_scenario_source

            cfg = self.config
            source = get_scenario_source(cfg.source, **({"root": cfg.root} if cfg.root else {}))
            ids = training_scene_ids(source.scene_ids("train"), cfg.holdout_every)[: cfg.num_scenes]
            if not ids:
                raise DataNotFoundError(f"split 'train' of {cfg.source!r} has no scene long enough.")
            self.scenes = self._with_mirrored([source.load_scene("train", i) for i in ids])
        return self.scenes

    def _with_mirrored(self, scenes: list[ScenarioTensor]) -> list[ScenarioTensor]:
        """``scenes``, followed by their mirror images when ``config.mirror_scenes``."""
        return scenes + [mirror_scenario(scene) for scene in scenes] if self.config.mirror_scenes else scenes

    def _contexts(self, epoch: int) -> tuple[ScenarioTensor, ScenarioTensor]:
        """The epoch's contexts and the same windows of the log (see :class:`ContextSampler`); every draw comes
        from a generator seeded by ``(seed, epoch)``."""
        return self.context_sampler.draw(derived_generator(self.config.seed, epoch, "contexts"))

    # ------------------------------------------------------------------ rollout
    def _sample(self, contexts: ScenarioTensor, generator: torch.Generator, samples: int | None = None) -> Any:
        """``samples`` futures per context, drawn in chunks of contexts with seeds derived from ``generator``
        (:func:`~trafficrlhf_sdk.alignment.distributed.sample_in_chunks`), in this process or on the Ray workers
        of ``self.execution``: the same numbers either way."""
        seed = int(torch.randint(0, 2**31 - 1, (1,), generator=generator))
        return sample_in_chunks(self.model, self.guidance, contexts, samples or self.config.samples_per_context,
                                seed, self.execution)

    def _rollout(self, epoch: int) -> SampledEpoch:
        contexts, logged = self._contexts(epoch)
        gen = derived_generator(self.config.seed, epoch, "sample")
        out = self._sample(contexts, gen)
        trace = out.trace.detach()
        b = contexts.num_scenes
        passing = None
        scenario = self.sample_scenarios(contexts, out.futures, trace.agents)  # B * S scenarios, context-major
        choice_adv = None
        if self.config.credit == "agent":
            per_agent, adv = self._agent_advantages(scenario, logged, trace.agents)
            rewards = mean_over_sampled(per_agent, trace.agents)
            if self.config.passing_anchor_coef > 0:
                passing = self._passing_agents(scenario, trace.agents, self.config.samples_per_context)
                adv = adv * (~passing)[:, None, :].to(adv.dtype)
            if self.config.choice_coef > 0:
                choices = self.model.choice_futures(contexts)
                if choices is None:
                    raise TrafficRLHFError(f"choice_coef is {self.config.choice_coef} but "
                                           f"{type(self.model).__name__} offers no discrete choices "
                                           "(choice_futures returns None); set choice_coef = 0.")
                choice_scenario = self.sample_scenarios(contexts, choices, trace.agents)
                # the reward's advantages alone: a mode's mean plan differs from the others in speed for every
                # agent, so the pace term would rank every agent's modes by speed and drown the failures
                choice_adv = self._agent_advantages(choice_scenario, logged, trace.agents, pace=False)[1]
                if passing is not None:
                    choice_adv = choice_adv * (~passing)[:, None, :].to(choice_adv.dtype)
        else:
            rewards = scenario_scores(self.reward_model, scenario).reshape(b, -1)
            adv = self._normalize(rewards, dim=1)
            if self.pace is not None:
                speeds = sample_speeds(scenario, self.reward_steps).reshape(b, -1, contexts.num_agents)
                adv = self.pace.mix(adv, mean_over_sampled(speeds, trace.agents), 1, torch.ones_like(adv))
        self.last_heldout = self._monitor_scores()
        return SampledEpoch(contexts, logged, trace, rewards, adv, out.log_prob.detach(), passing, choice_adv)

    def _agent_advantages(self, scenario: ScenarioTensor, logged: ScenarioTensor, agents: torch.Tensor,
                          pace: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-agent rewards ``(B, R, A)`` of the ``B * R`` scenarios (context-major) for the sampled ``agents
        (B, A)`` and their advantages over the ``R`` rows of each context (0 for agents not sampled), with the
        pace constraint's speed term mixed in when ``pace``."""
        b, a = agents.shape
        reference = None
        if getattr(self.reward_model, "uses_log", False):
            # the log of the same window, not the context: a failure-focused context continues with the
            # model's own driving, which a comparison with the log must not see
            start = max(0, logged.current_index - REWARD_HISTORY_STEPS)
            stop = logged.current_index + 1 + self.reward_steps
            reference = logged.repeat_scenes(scenario.num_scenes // b).time_slice(start, stop)
        per_agent = agent_scores(self.reward_model, scenario, reference).reshape(b, -1, a)
        sampled = agents[:, None, :].expand_as(per_agent)
        adv = self._normalize(per_agent, dim=1) * sampled.to(per_agent.dtype)
        if self.pace is not None and pace:
            speeds = sample_speeds(scenario, self.reward_steps).reshape(per_agent.shape)
            turning = logged_turning(logged)[:, None, :] if self.pace.by_turning else None
            adv = self.pace.mix(adv, speeds, 1, sampled, turning)
        return per_agent, adv

    def _monitor_scores(self) -> dict[str, float]:
        """The held-out judgments of the current policy on a fixed set of contexts (drawn once, see
        :mod:`~trafficrlhf_sdk.alignment.monitor`), sampled with the same random numbers every epoch, so that the
        curve moves with the policy, not with the draw."""
        cfg = self.config
        if self.monitor_contexts is None:
            self.monitor_contexts, self.monitor_logged = self._draw_monitor_contexts()
        contexts = self.monitor_contexts
        out = self._sample(contexts, derived_generator(cfg.seed, "monitor-samples"), MONITOR_SAMPLES)
        scenario = self.sample_scenarios(contexts, out.futures.detach(), out.trace.agents)
        return self.monitor.scores(scenario, out.trace.agents.repeat_interleave(MONITOR_SAMPLES, 0))

    def _held_out_scenes(self) -> list[ScenarioTensor]:
        """The first ``2 * failure_scenes`` held-out training scenes (``holdout_every``); the training scenes
        themselves when none are held out or scenes were passed in. Loaded once."""
        if self.held_out is None:
            cfg = self.config
            held: list[ScenarioTensor] = []
            if self.scenes_given is None and cfg.holdout_every is not None:
                from trafficrlhf_sdk.plugins import get_scenario_source

                source = get_scenario_source(cfg.source, **({"root": cfg.root} if cfg.root else {}))
                ids = held_out_scene_ids(source.scene_ids("train"), cfg.holdout_every)[: 2 * cfg.failure_scenes]
                held = [source.load_scene("train", i) for i in ids]
            self.held_out = held or self._load_scenes()
        return self.held_out

    def _draw_monitor_contexts(self) -> tuple[ScenarioTensor, ScenarioTensor]:
        """Logged windows and failure-focused windows of the starting model, from the held-out training scenes
        (:meth:`_held_out_scenes`)."""
        cfg = self.config
        sampler = ContextSampler(self.model, cfg, self._held_out_scenes, self.guidance, self.future_steps)
        gen = derived_generator(cfg.seed, "monitor-contexts")
        pairs = [sampler.log_contexts(MONITOR_CONTEXTS, gen)]
        if cfg.failure_fraction > 0:
            pairs.append(sampler.failure_contexts(MONITOR_FAILURE_CONTEXTS, gen))
        return (ScenarioTensor.concat([p[0] for p in pairs]), ScenarioTensor.concat([p[1] for p in pairs]))

    @staticmethod
    def _passing_agents(scenario: ScenarioTensor, agents: torch.Tensor, samples: int) -> torch.Tensor:
        """``(B, A)`` bool: sampled ``agents (B, A)`` none of whose ``samples`` in the ``B * S`` sample scenarios
        (context-major) collides with any agent or has its centre off the drivable area."""
        failing = FailureReward().agent_scores(scenario).reshape(agents.shape[0], samples, agents.shape[1]) < 0
        return agents & ~failing.any(1)

    @staticmethod
    def _normalize(rewards: torch.Tensor, dim: int) -> torch.Tensor:
        """``(r - mean) / (std + eps)`` over the samples of each context (and agent), clipped to +-5."""
        centred = rewards - rewards.mean(dim, keepdim=True)
        scale = rewards.std(dim, unbiased=False, keepdim=True)
        return (centred / (scale + 1e-6)).clamp(-ADVANTAGE_CLIP, ADVANTAGE_CLIP)

    # ------------------------------------------------------------------ logging
    def _configure_logger(self) -> Any:
        from stable_baselines3.common.logger import HumanOutputFormat, Logger, configure

        formats = ["stdout", "csv", "tensorboard"] if self.config.progress_bar else ["csv", "tensorboard"]
        try:
            import tensorboard  # noqa: F401
        except ImportError:
            formats.remove("tensorboard")
        if self.config.output_dir is None:
            # SB3's configure(None, ...) makes a fresh SB3-<date> folder in the temp dir on every call, even for
            # stdout alone: without an output folder, build the logger itself and write nothing to disk.
            return Logger(None, [HumanOutputFormat(sys.stdout)] if "stdout" in formats else [])
        return configure(os.path.join(self.config.output_dir, "logs"), formats)

    # ------------------------------------------------------------------ main loop
    def train(self, callback: Callable[[int, dict[str, float]], bool | None] | None = None) -> list[dict[str, float]]:
        """Run the remaining epochs; returns the history. ``callback(epoch, stats)`` after each epoch may return
        False to stop (the state is checkpointed first when ``output_dir`` is set). With ``execution`` on Ray, one
        Ray session (and its workers) serves every epoch's samples."""
        with ray_session(self.execution or ExecutionConfig()):
            return self._train(callback)

    def _train(self, callback: Callable[[int, dict[str, float]], bool | None] | None) -> list[dict[str, float]]:
        cfg = self.config
        if self.monitor_contexts is None:  # from the starting weights, also when resuming
            self.monitor_contexts, self.monitor_logged = self._draw_monitor_contexts()
        starting_pace = None
        if self.pace is not None and self.pace.base is None:  # the starting weights' pace, also when resuming
            starting_pace = self.pace.drive(self.model)
            self.pace.set_base(starting_pace)
        if cfg.resume:
            self.resume_newest()
            if self.pace is not None:
                self.pace.restore(self.history)
        self.logger = self._configure_logger()
        flags = {id(p): p.requires_grad for p in self.model.module.parameters()}
        chosen = {id(p) for p in self.trainable}
        for p in self.model.module.parameters():
            p.requires_grad_(id(p) in chosen)
        bar = None
        if cfg.progress_bar:
            from trafficrlhf_sdk.console import progress

            bar = progress(total=cfg.epochs, initial=self.start_epoch, desc=f"align {self.model.name}", unit="epoch")
        saved = done = self.start_epoch
        previous_term = _checkpoint_on_sigterm()
        try:
            for epoch in range(self.start_epoch, cfg.epochs):
                start = time.perf_counter()
                pace = {} if self.pace is None else self.pace.step(self.model, starting_pace if epoch == 0 else None)
                rollout = self._rollout(epoch)
                stats = {"epoch": float(epoch + 1),
                         "reward_mean": float(rollout.rewards.mean()),
                         "reward_std": float(rollout.rewards.std(1, unbiased=False).mean()),
                         "reward_min": float(rollout.rewards.min()),
                         "reward_max": float(rollout.rewards.max())}
                if rollout.passing is not None:  # share of the sampled agents that no sample of fails
                    sampled = rollout.trace.agents.sum().clamp_min(1)
                    stats["passing_share"] = float(rollout.passing.sum() / sampled)
                stats.update(self.last_heldout)
                stats.update(pace)
                scored = [p.detach().clone() for p in self.trainable] if cfg.early_stopping_patience else []
                stats.update(self._optimize(epoch, rollout))
                stats["time_s"] = time.perf_counter() - start
                # the held-out realism was measured before this epoch's update: it belongs to the weights after
                # `epoch` updates (0: the starting weights), and those are the ones kept if it is the best
                stop_early = self.monitor.update(epoch, stats["heldout_realism"], scored)
                self.history.append(stats)
                self._log(stats)
                for line in health_warnings(stats):
                    warn(line)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(reward=f"{stats['reward_mean']:.3f}", kl=f"{stats['approx_kl']:.2g}")
                done = epoch + 1
                if cfg.output_dir is not None and (done % cfg.save_every == 0 or done == cfg.epochs):
                    self.save_checkpoint(done)
                    saved = done
                if callback is not None and callback(epoch, stats) is False:
                    if cfg.output_dir is not None and done % cfg.save_every != 0:
                        self.save_checkpoint(done)
                    break
                if stop_early:
                    break
        except KeyboardInterrupt:  # Ctrl-C, or SIGTERM (see _checkpoint_on_sigterm): keep the finished epochs
            if cfg.output_dir is not None and done > saved:
                self.save_checkpoint(done)
            raise
        finally:
            _restore_sigterm(previous_term)
            if bar is not None:
                bar.close()
            for p in self.model.module.parameters():
                p.requires_grad_(flags[id(p)])
            if self.logger is not None:
                self.logger.close()
        finished = len(self.history) == cfg.epochs or (
            cfg.early_stopping_patience is not None and self.monitor.best is not None
            and len(self.history) - 1 - self.monitor.best[1] >= cfg.early_stopping_patience)
        if finished and cfg.early_stopping_patience and len(self.history) == cfg.epochs:
            final = self._monitor_scores()  # the weights after the last update were never scored
            self.history[-1].update({f"final_{k}": v for k, v in final.items()})
            self.monitor.update(cfg.epochs, final["heldout_realism"], [p.detach().clone() for p in self.trainable])
        best_epoch = self.monitor.restore_best(self.trainable) if cfg.early_stopping_patience else None
        if cfg.output_dir is not None and self.history:
            plot_overoptimization(self.history, os.path.join(cfg.output_dir, "overoptimization.png"))
        if cfg.output_dir is not None and finished:
            self.model.save_pretrained(cfg.output_dir)
            with open(os.path.join(cfg.output_dir, "align_history.json"), "w", encoding="utf-8") as handle:
                json.dump({"config": cfg.model_dump(mode="json"), "groups": list(self.group_names),
                           "reward_model": getattr(self.reward_model, "name_or_path", None)
                           or type(self.reward_model).__name__, "best_epoch": best_epoch,
                           "history": self.history}, handle, indent=1)
        return self.history

    def _log(self, stats: dict[str, float]) -> None:
        rollout_keys = ("reward_mean", "reward_std", "reward_min", "reward_max", "passing_share", "heldout_realism",
                        "heldout_reward", "heldout_failure", "pace_change", "pace_change_turning",
                        "pace_change_straight")
        for key, value in stats.items():
            if key == "epoch" or (isinstance(value, float) and math.isnan(value)):
                continue
            prefix = "rollout" if key in rollout_keys else ("time" if key == "time_s" else "train")
            self.logger.record(f"{prefix}/{key}", value)
        self.logger.dump(step=int(stats["epoch"]))


class Terminated(KeyboardInterrupt):
    """SIGTERM during :meth:`AlignTrainer.train`: handled like Ctrl-C (the finished epochs are checkpointed)."""


def _checkpoint_on_sigterm() -> Any:
    """Turn SIGTERM into :class:`Terminated` while training (main thread only); returns the previous handler."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum: int, frame: Any) -> None:
        raise Terminated(f"signal {signum}")

    return signal.signal(signal.SIGTERM, handler)


def _restore_sigterm(previous: Any) -> None:
    import signal

    if previous is not None:
        signal.signal(signal.SIGTERM, previous)
