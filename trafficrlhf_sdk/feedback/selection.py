"""Active selection: serve first the items where reward models disagree most.

The store serves regular items by ``priority`` (highest first; :meth:`FeedbackStore.set_priorities`). This
module computes priorities from an ensemble of reward scorers, or from any ranking of item ids you bring.

Disagreement of one item: each scorer gives the N candidates rewards, standardized within the item (mean 0,
std 1, so scorers of different scales compare); the score is the mean over candidates of the standard
deviation across scorers. Items the scorers rank the same way score near 0.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from trafficrlhf_sdk.feedback.store import Campaign, FeedbackStore
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["candidate_disagreement", "priorities_from_ranking", "rank_by_disagreement"]

Scorer = Callable[[ScenarioTensor], torch.Tensor]


def candidate_disagreement(rewards: torch.Tensor) -> float:
    """Disagreement of S scorers over N candidates from ``rewards (S, N)`` (see the module docstring)."""
    if rewards.dim() != 2 or rewards.shape[0] < 2 or rewards.shape[1] < 2:
        raise ValueError(f"`rewards` must have shape (S >= 2 scorers, N >= 2 candidates); got {tuple(rewards.shape)}.")
    r = rewards.double()
    z = (r - r.mean(1, keepdim=True)) / r.std(1, keepdim=True).clamp_min(1e-9)
    return float(z.std(0).mean())


def rank_by_disagreement(store: FeedbackStore, campaign: Campaign | str, scorers: Sequence[Scorer],
                         only_unlabeled: bool = True, apply: bool = True) -> dict[int, float]:
    """Disagreement of ``scorers`` (each maps a scenario batch, one candidate per scene, to rewards ``(N,)``,
    e.g. ``RewardModel.score``) on every regular item of ``campaign``; with ``apply`` the scores become the
    items' priorities. ``only_unlabeled``: skip items that already have labels."""
    campaign = store.campaign(campaign) if isinstance(campaign, str) else campaign
    if len(scorers) < 2:
        raise ValueError(f"`scorers` needs at least two reward scorers to disagree; got {len(scorers)}.")
    labeled = {label.context_id for label in store.labels(campaign)} if only_unlabeled else set()
    scores: dict[int, float] = {}
    for key in store.context_keys(campaign):
        if key["gold_answer"] is not None or key["id"] in labeled:
            continue
        record = store.load_context(key["id"], campaign)
        batch = ScenarioTensor.concat([record.candidate_scenario(k) for k in range(record.num_candidates)])
        with torch.no_grad():
            rewards = torch.stack([torch.as_tensor(score(batch)).reshape(-1).float() for score in scorers])
        scores[key["id"]] = candidate_disagreement(rewards)
    if apply and scores:
        store.set_priorities(campaign, scores)
    return scores


def priorities_from_ranking(context_ids: Sequence[int]) -> dict[int, float]:
    """Priorities that serve ``context_ids`` in the given order (first = highest), for ``set_priorities``."""
    if len(set(context_ids)) != len(context_ids):
        raise ValueError("`context_ids` holds repeats; give each item once, most wanted first.")
    n = len(context_ids)
    return {int(c): float(n - i) for i, c in enumerate(context_ids)}
