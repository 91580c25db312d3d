"""``AlignTrainer``: PPO fine-tuning of any :class:`~trafficrlhf_sdk.models.TrafficModelAdapter` against a reward
model, through the adapter contract only (``sample``, ``log_prob``, ``imitation_loss``, ``parameter_groups``).

One epoch:

1. **Rollout.** ``contexts_per_epoch`` contexts from a :class:`~trafficrlhf_sdk.alignment.contexts.ContextSampler`:
   logged windows, optionally states the current model reached in a closed-loop lead-in
   (``closed_loop_fraction``) and states shortly before the current model's own closed-loop failures
   (``failure_fraction``). Per context the adapter draws ``samples_per_context`` futures (with the configured
   guidance, no gradient). Each sample becomes a scenario: the context's history, then the sample's future for
   the sampled (controlled) agents and the log for everyone else. Its reward is the reward model's score of that
   scenario (``credit="scene"``), or one score per sampled agent (``credit="agent"``, ``agent_scores``). With
   ``continuation_steps`` the score is (partly) that of the sample's first steps followed by the current model's
   own closed-loop driving (:mod:`trafficrlhf_sdk.alignment.continuation`).
2. **Advantages.** ``A = (r - mean_context) / (std_context + eps)`` over the samples of a context (of each agent
   of a context with ``credit="agent"``), clipped to ``+- advantage_clip``. With scene credit one advantage per
   (context, sample) is shared by every sampled agent; for per-step log-probabilities such as a diffusion
   chain, by every denoising step (DDPO), or the first ``denoising_steps`` of them. With ``selection_credit``
   ``r`` is first replaced by each sample's best-of-K return under the adapter's selection scores
   (:mod:`trafficrlhf_sdk.alignment.selection`), for planners that execute the best of K samples.
3. **Optimization.** ``ppo_epochs`` passes over minibatches of contexts: ``ratio = exp(log_prob - log_prob_old)``
   elementwise (per agent, per denoising step where the adapter returns ``(B, S, A, K)``), surrogate
   ``min(ratio * A, clip(ratio) * A)`` averaged over sampled agents (and steps), loss
   ``imitation_coef * imitation_loss - alpha * surrogate (+ kl_coef * KL to the frozen starting model)``,
   gradient clipping, and SB3's early stop once the approximate KL passes ``1.5 * target_kl``. With
   ``winner_coef > 0`` the loss also holds ``winner_coef * imitation_loss`` of each context's best sample
   (:meth:`AlignTrainer.winner_scenarios`; reward-ranked fine-tuning beside the surrogate). With
   ``anchor_coef > 0`` it also holds ``anchor_coef * KL`` to the frozen starting model on as many contexts drawn
   uniformly from the log, sampled by the current model each epoch: the PPO contexts are mostly failure-focused,
   and the anchor keeps the driving on ordinary roads where it was. With ``passing_anchor_coef > 0`` (agent
   credit), agents none of whose samples fails get advantage 0 and ``passing_anchor_coef * KL`` to the starting
   model on their own samples instead: the push and the hold act on different agents of the same contexts.

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
from trafficrlhf_sdk.alignment.config import AlignConfig
from trafficrlhf_sdk.alignment.continuation import continuation_scenarios
from trafficrlhf_sdk.alignment.contexts import ContextSampler, held_out_scene_ids, training_scene_ids
from trafficrlhf_sdk.alignment.held_out import HeldOutEvaluator
from trafficrlhf_sdk.alignment.ppo_update import PPOUpdate, Rollout, derived_generator, derived_seed, mean_over_sampled
from trafficrlhf_sdk.reward.builtin import FailureReward
from trafficrlhf_sdk.reward.scoring import RewardLike, agent_scores, scenario_scores
from trafficrlhf_sdk.alignment.sample_scenarios import SampleScenarios
from trafficrlhf_sdk.alignment.selection import best_of_k_returns
from trafficrlhf_sdk.errors import DataNotFoundError, TrafficRLHFError
from trafficrlhf_sdk.simulation.guidance import GuidanceSet
from trafficrlhf_sdk.models.adapter import TrafficModelAdapter
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.scenario.transforms import mirror_scenario

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
        scenes: training scenes (each ``B = 1`` or a batch, split into single scenes); None loads
            ``config.split`` of ``config.source``.
        eval_scenes: held-out scenes ``(B, A, T)`` for ``config.eval_every``; None: the scenes
            ``config.holdout_every`` keeps out of the source's split.
        reference: the frozen model the KL terms (``kl_coef``, ``anchor_coef``, ``passing_anchor_coef``) hold
            the policy to; None: a copy of ``model`` as it starts. Give one to keep a later stage of a
            multi-stage run anchored to the first stage's start (e.g. the base model with a fresh, zero-output
            head). It must be the same adapter class with the same parameter names and shapes.
    """

    def __init__(self, model: TrafficModelAdapter, reward_model: Any, config: AlignConfig | None = None,
                 scenes: ScenarioTensor | Sequence[ScenarioTensor] | None = None,
                 eval_scenes: ScenarioTensor | None = None, reference: TrafficModelAdapter | None = None) -> None:
        self.model = model
        self.reward_model = reward_model
        self.config = config or AlignConfig()
        self.horizon = self.config.horizon or int(getattr(model, "horizon", 20))
        cfg = self.config
        if cfg.continuation_steps and cfg.continuation_executed_steps > self.horizon:
            raise TrafficRLHFError(f"`continuation_executed_steps` is {cfg.continuation_executed_steps} but the model "
                                   f"samples {self.horizon} steps; lower it to at most {self.horizon}.")
        continued = cfg.continuation_executed_steps + cfg.continuation_steps if cfg.continuation_steps else 0
        self.future_steps = max(self.horizon, cfg.reward_horizon or 0, continued)  # log steps kept after "now"
        self.reward_steps = self.config.reward_horizon or self.horizon  # sampled steps the reward model scores
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
        self.optimizer = torch.optim.AdamW(self.trainable, lr=self.config.learning_rate,
                                           weight_decay=self.config.weight_decay)
        self.guidance = GuidanceSet.parse(self.config.guidance)
        keeps_reference = max(self.config.kl_coef, self.config.anchor_coef, self.config.passing_anchor_coef) > 0
        if reference is not None:
            if not keeps_reference:
                raise TrafficRLHFError("`reference` (--reference-checkpoint) was given but kl_coef, anchor_coef "
                                       "and passing_anchor_coef are all 0, so nothing would use it; set one of "
                                       "them or drop `reference`.")
            _check_reference(model, reference)
            self.reference = copy.deepcopy(reference)
        else:
            self.reference = copy.deepcopy(model) if keeps_reference else None
        if self.reference is not None:
            for p in self.reference.module.parameters():
                p.requires_grad_(False)
        self.scenes = self._with_mirrored(self._split_scenes(scenes)) if scenes is not None else None
        self.context_sampler = ContextSampler(model, self.config, self._load_scenes, self.guidance,
                                              self.future_steps)
        if getattr(reward_model, "uses_log", False) and self.config.credit != "agent":
            raise TrafficRLHFError(f"{type(reward_model).__name__} compares each agent with its logged future and "
                                   "scores agents only; use credit='agent'.")
        if self.config.credit == "agent" and not callable(getattr(reward_model, "agent_scores", None)):
            raise TrafficRLHFError(f"credit='agent' needs a reward model with `agent_scores(scenario) -> (B, A)`; "
                                   f"{type(reward_model).__name__} has none. Use credit='scene'.")
        if self.config.selection_credit and type(model).selection_scores is TrafficModelAdapter.selection_scores:
            raise TrafficRLHFError(f"selection_credit=True needs an adapter whose `selection_scores` ranks its "
                                   f"samples as its planner does; {type(model).__name__} executes what it samples. "
                                   "Leave selection_credit off for it.")
        self.held_out = None
        if self.config.eval_every is not None:
            if eval_scenes is None and (scenes is not None or self.config.holdout_every is None):
                raise TrafficRLHFError("`eval_every` needs held-out scenes: set `holdout_every` (scenes of the "
                                       "source's split never trained on) or pass `eval_scenes`.")
            held = (lambda: eval_scenes) if eval_scenes is not None else self._load_held_out
            self.held_out = HeldOutEvaluator(model, self.config, held, self.guidance)
        self.history: list[dict[str, float]] = []
        self.start_epoch = 0
        self.logger: Any = None

    # ------------------------------------------------------------------ data
    @staticmethod
    def _split_scenes(scenes: ScenarioTensor | Sequence[ScenarioTensor]) -> list[ScenarioTensor]:
        items = [scenes] if isinstance(scenes, ScenarioTensor) else list(scenes)
        return [s[i] for s in items for i in range(s.num_scenes)]

    def _source(self) -> Any:
        from trafficrlhf_sdk import get_scenario_source

        cfg = self.config
        return get_scenario_source(cfg.source, **({"root": cfg.root} if cfg.root else {}))

    def _load_scenes(self) -> list[ScenarioTensor]:
        if self.scenes is None:
            cfg = self.config
            source = self._source()
            ids = training_scene_ids(source.scene_ids(cfg.split), cfg.holdout_every)[: cfg.num_scenes]
            if not ids:
                raise DataNotFoundError(f"split {cfg.split!r} of {cfg.source!r} has no scene long enough.")
            self.scenes = self._with_mirrored([source.load_scene(cfg.split, i) for i in ids])
        return self.scenes

    def _with_mirrored(self, scenes: list[ScenarioTensor]) -> list[ScenarioTensor]:
        """``scenes``, followed by their mirror images when ``config.mirror_scenes``."""
        return scenes + [mirror_scenario(scene) for scene in scenes] if self.config.mirror_scenes else scenes

    def _load_held_out(self) -> ScenarioTensor:
        cfg = self.config
        assert cfg.holdout_every is not None
        source = self._source()
        return source.load_batch(cfg.split, scene_ids=held_out_scene_ids(source.scene_ids(cfg.split),
                                                                          cfg.holdout_every))

    def _contexts(self, epoch: int) -> tuple[ScenarioTensor, ScenarioTensor]:
        """The epoch's contexts and the same windows of the log (see :class:`ContextSampler`); every draw comes
        from a generator seeded by ``(seed, epoch)``."""
        return self.context_sampler.draw(derived_generator(self.config.seed, epoch, "contexts"), epoch)

    # ------------------------------------------------------------------ rollout
    def _sample(self, contexts: ScenarioTensor, generator: torch.Generator, samples: int | None = None) -> Any:
        guidance = self.guidance
        samples = samples or self.config.samples_per_context
        if guidance is not None:
            guidance.fit(contexts)
            with torch.enable_grad():
                return self.model.sample(contexts, samples, guidance, generator)
        with torch.no_grad():
            return self.model.sample(contexts, samples, None, generator)

    def _mix_continuation(self, open_loop: torch.Tensor, contexts: ScenarioTensor, futures: torch.Tensor,
                          agents: torch.Tensor, epoch: int, source: ScenarioTensor | None) -> torch.Tensor:
        """``continuation_weight`` x the scores of the samples' closed-loop continuations
        (:func:`~trafficrlhf_sdk.alignment.continuation.continuation_scenarios`) + the rest x ``open_loop``; scores
        ``(B, S)`` (scene credit) or ``(B, S, A)`` (agent credit), like ``open_loop``. ``source``: the windows a
        reward with ``uses_log`` compares with."""
        cfg = self.config
        b, s, a = futures.shape[:3]
        states, valid = self._future_states(contexts, futures, agents)
        scenes = continuation_scenarios(self.model, contexts, states, valid, agents, cfg.continuation_executed_steps,
                                        cfg.continuation_steps, derived_seed(cfg.seed, epoch, "continuation"),
                                        self.guidance)
        now = contexts.current_index
        window = (max(0, now - cfg.reward_history_steps), now + 1 + cfg.continuation_executed_steps
                  + cfg.continuation_steps)
        scenes = scenes.time_slice(*window)
        if open_loop.dim() == 2:
            closed = scenario_scores(self.reward_model, scenes).reshape(b, s)
        else:
            reference = None if source is None else source.repeat_scenes(s).time_slice(*window)
            closed = agent_scores(self.reward_model, scenes, reference).reshape(b, s, a)
        w = cfg.continuation_weight
        return w * closed + (1 - w) * open_loop

    def _rollout(self, epoch: int) -> Rollout:
        contexts, logged = self._contexts(epoch)
        gen = derived_generator(self.config.seed, epoch, "sample")
        out = self._sample(contexts, gen)
        trace = out.trace.detach()
        b = contexts.num_scenes
        passing = None
        if self.config.credit == "agent":
            source, window = None, slice(max(0, contexts.current_index - self.config.reward_history_steps),
                                         contexts.current_index + 1 + self.reward_steps)
            if getattr(self.reward_model, "uses_log", False):
                # the log of the same window, not the context: a closed-loop or failure-focused context
                # continues with the model's own driving, which a comparison with the log must not see
                source = logged if self.config.log_reference == "log" else contexts
            scenario = None  # the B * S sample scenarios, built once for the reward and the passing check
            if self.config.counterfactual_credit:
                reference = None if source is None else source.time_slice(window.start, window.stop)  # (B) windows
                per_agent = self._counterfactual_agent_scores(contexts, out.futures, trace.agents, reference)
            else:
                reference = None if source is None else source.repeat_scenes(
                    self.config.samples_per_context).time_slice(window.start, window.stop)
                scenario = self.sample_scenarios(contexts, out.futures, trace.agents)
                per_agent = agent_scores(self.reward_model, scenario, reference).reshape(b, -1, contexts.num_agents)
            if self.config.continuation_steps:
                per_agent = self._mix_continuation(per_agent, contexts, out.futures, trace.agents, epoch, source)
            rewards = mean_over_sampled(per_agent, trace.agents)
            speed = self._sample_speeds(out.futures) if self.config.speed_neutral_advantages else None
            returns = self._selection_returns(contexts, out, per_agent) if self.config.selection_credit else per_agent
            sampled = trace.agents[:, None, :].expand_as(returns)
            adv = self._normalize(returns, dim=1, covariate=speed, mask=sampled) * sampled.to(per_agent.dtype)
            ranked = per_agent
            if self.config.passing_anchor_coef > 0:
                if scenario is None:
                    scenario = self.sample_scenarios(contexts, out.futures, trace.agents)
                passing = self._passing_agents(scenario, trace.agents, self.config.samples_per_context)
                adv = adv * (~passing)[:, None, :].to(adv.dtype)
        else:
            scenario = self.sample_scenarios(contexts, out.futures, trace.agents)
            rewards = scenario_scores(self.reward_model, scenario).reshape(b, -1)
            if self.config.continuation_steps:
                rewards = self._mix_continuation(rewards, contexts, out.futures, trace.agents, epoch, None)
            speed = None
            if self.config.speed_neutral_advantages:
                speed = mean_over_sampled(self._sample_speeds(out.futures), trace.agents)
            returns = self._selection_returns(contexts, out, rewards) if self.config.selection_credit else rewards
            adv = self._normalize(returns, dim=1, covariate=speed)
            ranked = rewards[:, :, None].expand(-1, -1, contexts.num_agents)
        winners = None
        if self.config.winner_coef > 0:
            winners = self.winner_scenarios(contexts, out.futures, trace.agents, ranked)
        imitation = None
        if self.config.imitation_contexts == "log" and self.config.imitation_coef > 0:
            gen = derived_generator(self.config.seed, epoch, "imitation_log")
            imitation = self.context_sampler.log_contexts(b, gen)[1]
        anchor = None
        if self.config.anchor_coef > 0:
            gen = derived_generator(self.config.seed, epoch, "anchor")
            anchor_contexts = self.context_sampler.log_contexts(b, gen)[0]
            anchor = (anchor_contexts, self._sample(anchor_contexts, gen, self.config.anchor_samples).trace.detach())
        return Rollout(contexts, logged, trace, rewards, adv, out.log_prob.detach(), winners, imitation, anchor,
                       passing)

    def _passing_agents(self, scenario: ScenarioTensor, agents: torch.Tensor, samples: int) -> torch.Tensor:
        """``(B, A)`` bool: sampled ``agents (B, A)`` none of whose ``samples`` in the ``B * S`` sample scenarios
        (:meth:`sample_scenarios`, context-major) has a failure step (of ``failure_kinds``: collision with any
        agent, centre off the drivable area), nor with ``passing_margins`` a near-failure one (a corner off the
        road, a near miss)."""
        kinds = self.config.failure_kinds
        check = FailureReward(collision="collision" in kinds, offroad="offroad" in kinds,
                              margins=self.config.passing_margins)
        failing = check.agent_scores(scenario).reshape(agents.shape[0], samples, agents.shape[1]) < 0  # (B, S, A)
        return agents & ~failing.any(1)

    def _selection_returns(self, contexts: ScenarioTensor, out: Any, rewards: torch.Tensor) -> torch.Tensor:
        """Best-of-K returns (:func:`best_of_k_returns`) of ``rewards`` ``(B, S, A)`` (agent credit) or ``(B, S)``
        (scene credit: scores averaged over the sampled agents) under the adapter's selection scores."""
        ranked = self.model.selection_scores(contexts, out, self.guidance)
        if ranked is None:
            raise TrafficRLHFError(f"{type(self.model).__name__}.selection_scores returned None for these contexts; "
                                   "selection_credit needs its scores on every sample.")
        scores, k = ranked
        scores = scores.detach().to(rewards.dtype)
        if rewards.dim() == 2:
            scores = mean_over_sampled(scores, out.trace.agents)
        return best_of_k_returns(rewards, scores, k, dim=1)

    def _sample_speeds(self, futures: torch.Tensor) -> torch.Tensor:
        """``(B, S, A)`` mean speed (m/s) of each sample ``futures (B, S, A, H, 4)`` over the scored steps."""
        return futures[..., : min(futures.shape[-2], self.reward_steps), 2].detach().mean(-1).to(torch.float32)

    def _normalize(self, rewards: torch.Tensor, dim: int, covariate: torch.Tensor | None = None,
                   mask: torch.Tensor | None = None) -> torch.Tensor:
        """``(r - mean) / (std + eps)`` over the samples of each context (and agent), clipped. With
        ``advantage_scale='batch'`` the divisor is instead the root mean square of every centred reward where
        ``mask`` (bool, the shape of ``rewards``; None: everywhere) is True.

        With ``covariate`` (same shape as ``rewards``, e.g. the samples' speeds), ``r - mean`` is replaced by the
        residual of the least-squares line of ``r`` on the covariate within each group; the divisor stays the
        std of ``r``, so a group whose rewards the covariate explains gets advantages near 0 (not inflated
        noise)."""
        centred = rewards - rewards.mean(dim, keepdim=True)
        scale = rewards.std(dim, unbiased=False, keepdim=True) if self.config.advantage_scale == "group" else None
        if covariate is not None:
            x = covariate.to(rewards.dtype)
            x = x - x.mean(dim, keepdim=True)
            spread = (x * x).sum(dim, keepdim=True)
            slope = torch.where(spread > 1e-6, (x * centred).sum(dim, keepdim=True) / spread.clamp_min(1e-6),
                                torch.zeros_like(spread))
            centred = centred - slope * x
        if scale is None:  # "batch": one root mean square over the sampled entries
            kept = centred if mask is None else centred[mask]
            scale = kept.pow(2).mean().sqrt() if kept.numel() else centred.new_zeros(())
        clip = self.config.advantage_clip
        return (centred / (scale + self.config.advantage_eps)).clamp(-clip, clip)

    # ------------------------------------------------------------------ optimization
    def learning_rate(self, epoch: int) -> float:
        """The learning rate of epoch ``epoch`` (0-based) under ``config.lr_schedule``."""
        cfg = self.config
        if cfg.lr_schedule == "linear":
            return cfg.learning_rate * (1.0 - epoch / cfg.epochs)
        return cfg.learning_rate

    # ------------------------------------------------------------------ logging
    def _configure_logger(self) -> Any:
        from stable_baselines3.common.logger import configure

        formats = list(self.config.log_formats)
        if "tensorboard" in formats:
            try:
                import tensorboard  # noqa: F401
            except ImportError:
                formats.remove("tensorboard")
        if self.config.output_dir is None:
            # SB3's configure(None, ...) makes a fresh SB3-<date> folder in the temp dir on every call, even for
            # stdout alone: without an output folder, build the logger itself and write nothing to disk.
            from stable_baselines3.common.logger import HumanOutputFormat, Logger

            return Logger(None, [HumanOutputFormat(sys.stdout)] if "stdout" in formats else [])
        return configure(os.path.join(self.config.output_dir, "logs"), formats)

    # ------------------------------------------------------------------ main loop
    def train(self, callback: Callable[[int, dict[str, float]], bool | None] | None = None) -> list[dict[str, float]]:
        """Run the remaining epochs; returns the history. ``callback(epoch, stats)`` after each epoch may return
        False to stop (the state is checkpointed first when ``output_dir`` is set)."""
        cfg = self.config
        if cfg.resume:
            found = self.list_checkpoints()
            if found:
                self.load_checkpoint(found[-1])
        self.logger = self._configure_logger()
        flags = {id(p): p.requires_grad for p in self.model.module.parameters()}
        chosen = {id(p) for p in self.trainable}
        for p in self.model.module.parameters():
            p.requires_grad_(id(p) in chosen)
        bar = None
        if cfg.progress_bar:
            from tqdm.auto import tqdm

            bar = tqdm(total=cfg.epochs, initial=self.start_epoch, desc=f"align {self.model.name}", unit="epoch")
        try:
            for epoch in range(self.start_epoch, cfg.epochs):
                start = time.perf_counter()
                for group in self.optimizer.param_groups:
                    group["lr"] = self.learning_rate(epoch)
                rollout = self._rollout(epoch)
                stats = {"epoch": float(epoch + 1),
                         "reward_mean": float(rollout.rewards.mean()),
                         "reward_std": float(rollout.rewards.std(1, unbiased=False).mean()),
                         "reward_min": float(rollout.rewards.min()),
                         "reward_max": float(rollout.rewards.max())}
                if rollout.passing is not None:  # share of the sampled agents that no sample of fails
                    sampled = rollout.trace.agents.sum().clamp_min(1)
                    stats["passing_share"] = float(rollout.passing.sum() / sampled)
                stats.update(self._optimize(epoch, rollout))
                stats["time_s"] = time.perf_counter() - start
                if self.held_out is not None and self.held_out.due(epoch + 1):
                    stats.update(self.held_out.evaluate())
                    self.held_out.update_best(epoch + 1, stats["eval_failure_rate"])
                self.history.append(stats)
                self._log(stats)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(reward=f"{stats['reward_mean']:.3f}", kl=f"{stats['approx_kl']:.2g}")
                done = epoch + 1
                if cfg.output_dir is not None and (done % cfg.save_every == 0 or done == cfg.epochs):
                    self.save_checkpoint(done)
                if callback is not None and callback(epoch, stats) is False:
                    if cfg.output_dir is not None and done % cfg.save_every != 0:
                        self.save_checkpoint(done)
                    break
        finally:
            if bar is not None:
                bar.close()
            for p in self.model.module.parameters():
                p.requires_grad_(flags[id(p)])
            if self.logger is not None:
                self.logger.close()
        finished = len(self.history) == cfg.epochs
        best_epoch = None
        if finished and cfg.keep_best and self.held_out is not None:
            best_epoch = self.held_out.restore_best()
        if cfg.output_dir is not None and finished:
            self.model.save_pretrained(cfg.output_dir)
            with open(os.path.join(cfg.output_dir, "align_history.json"), "w", encoding="utf-8") as handle:
                json.dump({"config": cfg.model_dump(mode="json"), "groups": list(self.group_names),
                           "best_epoch": best_epoch, "history": self.history}, handle, indent=1)
        return self.history

    def _log(self, stats: dict[str, float]) -> None:
        rollout_keys = ("reward_mean", "reward_std", "reward_min", "reward_max", "passing_share")
        for key, value in stats.items():
            if key == "epoch" or (isinstance(value, float) and math.isnan(value)):
                continue
            prefix = "rollout" if key in rollout_keys else ("time" if key == "time_s" else "train")
            if key.startswith("eval_"):
                prefix, key = "eval", key[5:]
            self.logger.record(f"{prefix}/{key}", value)
        self.logger.dump(step=int(stats["epoch"]))
