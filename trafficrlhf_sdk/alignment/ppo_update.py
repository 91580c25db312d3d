"""The PPO update of an :class:`~trafficrlhf_sdk.alignment.AlignTrainer`: minibatches over contexts, the clipped
surrogate on the sampled agents' log-probabilities (per denoising step for diffusion models), the expected
advantage over a mixture policy's choices (``choice_coef``), the model's own imitation loss, the optional KL
penalty to the frozen reference, gradient clipping and the early stop on a target KL. Also the record of one
epoch's rollout that the update consumes, and the small tensor helpers both share.

Shapes: contexts ``B``, samples ``S``, agents ``A``, per-step log-probability entries ``K`` (diffusion models);
``log_prob`` is ``(B, S, A)`` or ``(B, S, A, K)``; advantages ``(B, S)`` (scene credit) or ``(B, S, A)``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import torch

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.alignment.config import MAX_GRAD_NORM
from trafficrlhf_sdk.models.adapter import PolicyTrace, TrafficModelAdapter
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["PPOUpdate", "SampledEpoch", "derived_generator", "derived_seed", "mean_over_sampled"]

MAX_LOG_RATIO = 20.0  # |log pi_ref - log pi| kept below this inside exp() (KL term)


@dataclass
class SampledEpoch:
    """One epoch's sampled contexts, their traces, rewards and advantages (what the PPO passes optimize on)."""

    contexts: ScenarioTensor
    logged: ScenarioTensor  # the same windows of the log (imitation loss)
    trace: PolicyTrace
    rewards: torch.Tensor  # (B, S) scene rewards; with credit="agent" the mean over the sampled agents
    advantages: torch.Tensor  # (B, S), or (B, S, A) with credit="agent"
    sample_log_prob: torch.Tensor  # as returned by adapter.sample
    passing: torch.Tensor | None = None  # (B, A) sampled agents none of whose samples fails (passing_anchor_coef)
    choice_advantages: torch.Tensor | None = None  # (B, C, A) advantages of every discrete choice (choice_coef)


def derived_seed(*parts: Any) -> int:
    """A 62-bit seed that is a pure function of ``parts``."""
    return int(hashlib.sha256(repr(parts).encode()).hexdigest()[:15], 16)


def derived_generator(*parts: Any) -> torch.Generator:
    """A generator seeded with :func:`derived_seed` of ``parts`` (one independent stream per purpose)."""
    return torch.Generator().manual_seed(derived_seed(*parts))


def _select_trace(trace: PolicyTrace, index: torch.Tensor) -> PolicyTrace:
    return PolicyTrace({k: v[index] for k, v in trace.tensors.items()}, trace.agents[index], trace.now,
                       dict(trace.info))


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    mask = mask.to(values.dtype)
    return (values * mask).sum() / mask.sum().clamp_min(1)


def _entry_mask(log_prob: torch.Tensor, agents: torch.Tensor) -> torch.Tensor:
    """bool mask shaped like ``log_prob (B, S, A[, K])`` of the sampled agents."""
    mask = agents[:, None, :].expand(log_prob.shape[:3])
    if log_prob.dim() == 4:
        mask = mask[..., None].expand(log_prob.shape)
    return mask


def mean_over_sampled(values: torch.Tensor, agents: torch.Tensor) -> torch.Tensor:
    """``(B, S)`` mean of per-agent ``values (B, S, A)`` over each context's sampled ``agents (B, A)``."""
    picked = agents[:, None, :].to(values.dtype)
    return (values * picked).sum(-1) / picked.sum(-1).clamp_min(1)


def _broadcast(adv: torch.Tensor, log_prob: torch.Tensor) -> torch.Tensor:
    """Per-(context, sample) advantages ``(B, S)`` or per-(context, sample, agent) ``(B, S, A)`` broadcast to
    ``log_prob``'s shape."""
    if adv.dim() == 2:
        adv = adv[:, :, None]
    if log_prob.dim() == 4:
        adv = adv[..., None]
    return adv.to(log_prob.dtype).expand(log_prob.shape)


class PPOUpdate:
    """The PPO update mixed into :class:`~trafficrlhf_sdk.alignment.AlignTrainer`, whose ``model``, ``reference``
    (frozen starting adapter or None), ``optimizer``, ``trainable`` (parameters it steps) and ``config`` it
    reads."""

    def _minibatches(self, epoch: int, ppo_epoch: int, n: int) -> list[torch.Tensor]:
        perm = torch.randperm(n, generator=derived_generator(self.config.seed, epoch, "order", ppo_epoch))
        size = self.config.minibatch_contexts
        return [perm[i:i + size] for i in range(0, n, size)]

    def _steps(self, log_prob: torch.Tensor) -> torch.Tensor:
        """``log_prob`` cut to the first ``denoising_steps`` per-step entries (unchanged for ``(B, S, A)``)."""
        n = self.config.denoising_steps
        return log_prob[..., :n] if n is not None and log_prob.dim() == 4 else log_prob

    @torch.no_grad()
    def _log_probs(self, model: TrafficModelAdapter, contexts: ScenarioTensor, trace: PolicyTrace,
                   batches: list[torch.Tensor]) -> torch.Tensor:
        """``model``'s log-probabilities of ``trace`` (cut to ``denoising_steps``), computed minibatch by minibatch."""
        result: torch.Tensor | None = None
        for idx in batches:
            lp = self._steps(model.log_prob(contexts[idx], _select_trace(trace, idx)).detach())
            if result is None:
                result = torch.zeros(contexts.num_scenes, *lp.shape[1:], dtype=lp.dtype)
            result[idx] = lp
        assert result is not None
        return result

    def _optimize(self, epoch: int, rollout: SampledEpoch) -> dict[str, float]:
        cfg = self.config
        n = rollout.contexts.num_scenes
        first = self._minibatches(epoch, 0, n)
        old = self._log_probs(self.model, rollout.contexts, rollout.trace, first)
        ref = None
        passing = rollout.passing if cfg.passing_anchor_coef > 0 else None
        if self.reference is not None and (cfg.kl_coef > 0 or passing is not None):
            ref = self._log_probs(self.reference, rollout.contexts, rollout.trace, first)
        stats: dict[str, list[float]] = {k: [] for k in ("loss", "imitation_loss", "surrogate", "approx_kl",
                                                         "clip_fraction", "kl_ref", "grad_norm", "passing_kl",
                                                         "choice_objective")}
        first_dev = float("nan")
        stopped = 0.0
        updates = skipped = 0
        for p in range(cfg.ppo_epochs):
            batches = first if p == 0 else self._minibatches(epoch, p, n)
            for j, idx in enumerate(batches):
                ctx, trace = rollout.contexts[idx], _select_trace(rollout.trace, idx)
                new = self._steps(self.model.log_prob(ctx, trace))
                if not new.requires_grad:
                    raise TrafficRLHFError(
                        f"{type(self.model).__name__}.log_prob() returned a tensor without gradient, so the PPO "
                        "surrogate cannot train the policy (only the imitation loss would); compute it from the "
                        "module's parameters, outside torch.no_grad() (check_adapter reports this).")
                mask = _entry_mask(new, trace.agents)
                logr = new - old[idx]
                ratio = torch.exp(logr)
                adv = _broadcast(rollout.advantages[idx], new)
                clipped = torch.clamp(ratio, 1 - cfg.clip_range, 1 + cfg.clip_range)
                surrogate = _masked_mean(torch.minimum(ratio * adv, clipped * adv), mask)
                loss = -cfg.alpha * surrogate
                if rollout.choice_advantages is not None:
                    # the exact expected advantage over each agent's choices: its gradient moves the choice
                    # probabilities of every agent by every choice's advantage, with no sampled-choice variance
                    choice_prob = self.model.choice_log_prob(ctx).exp()
                    if not choice_prob.requires_grad:
                        raise TrafficRLHFError(
                            f"choice_coef is {cfg.choice_coef} but no trained parameter group "
                            f"{list(self.group_names)} moves {type(self.model).__name__}'s choice probabilities; "
                            "add a group that does (for TrafficGen: 'road', 'decoder' or 'encoder') or set "
                            "choice_coef = 0.")
                    expected = (choice_prob * rollout.choice_advantages[idx]).sum(1)  # (b, A)
                    choice_objective = _masked_mean(expected, trace.agents)
                    loss = loss - cfg.alpha * cfg.choice_coef * choice_objective
                    stats["choice_objective"].append(float(choice_objective.detach()))
                if cfg.imitation_coef > 0:
                    torch.manual_seed(derived_seed(cfg.seed, epoch, "imitation", p, j))
                    imitation = self.model.imitation_loss(rollout.logged[idx])
                    loss = loss + cfg.imitation_coef * imitation
                    stats["imitation_loss"].append(float(imitation.detach()))
                if ref is not None:
                    closed = self.model.transition_kl(ctx, trace, self.reference)
                    if closed is not None:  # exact per-step KL (diffusion models): finite, 0 at the start
                        per_entry = self._steps(closed)
                    else:
                        # k3 estimator of KL(new || ref); the log-ratio is clamped because a density can fall far
                        # below the reference's on one sample (TrafficGen's mixture) and exp() would overflow
                        d = (ref[idx] - new).clamp(-MAX_LOG_RATIO, MAX_LOG_RATIO)
                        per_entry = torch.exp(d) - 1 - d
                    if cfg.kl_coef > 0:
                        kl_ref = _masked_mean(per_entry, mask)
                        loss = loss + cfg.kl_coef * kl_ref
                        stats["kl_ref"].append(float(kl_ref.detach()))
                    if passing is not None:
                        passing_kl = _masked_mean(per_entry, _entry_mask(new, passing[idx]))
                        loss = loss + cfg.passing_anchor_coef * passing_kl
                        stats["passing_kl"].append(float(passing_kl.detach()))
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                grads = [p.grad for p in self.trainable if p.grad is not None]
                if not torch.isfinite(loss) or not all(torch.isfinite(g).all() for g in grads):
                    skipped += 1  # one bad minibatch must not turn every weight into NaN
                    self.optimizer.zero_grad(set_to_none=True)
                    continue
                norm = torch.nn.utils.clip_grad_norm_(self.trainable, MAX_GRAD_NORM)
                stats["grad_norm"].append(float(norm))
                self.optimizer.step()
                updates += 1
                with torch.no_grad():
                    approx_kl = float(_masked_mean((ratio - 1) - logr, mask))
                    clip_fraction = float(_masked_mean(((ratio - 1).abs() > cfg.clip_range).float(), mask))
                    if p == 0 and j == 0:
                        first_dev = float(((ratio - 1).abs() * mask).max()) if mask.any() else 0.0
                stats["loss"].append(float(loss.detach()))
                stats["surrogate"].append(float(surrogate.detach()))
                stats["approx_kl"].append(approx_kl)
                stats["clip_fraction"].append(clip_fraction)
                if cfg.target_kl is not None and approx_kl > 1.5 * cfg.target_kl:
                    stopped = 1.0
                    break
            if stopped:
                break
        result = {k: (sum(v) / len(v) if v else float("nan")) for k, v in stats.items()}
        result.update(first_ratio_max_dev=first_dev, early_stop=stopped, updates=float(updates),
                      skipped_updates=float(skipped))
        mask = _entry_mask(old, rollout.trace.agents)
        sampled = self._steps(rollout.sample_log_prob)
        gap = ((old - sampled).abs() * mask).max() if mask.any() else torch.zeros(())
        result["sample_log_prob_gap"] = float(gap)
        return result
