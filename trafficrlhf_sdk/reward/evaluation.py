"""Evaluate a reward model on the preference pairs of a campaign or an exported dataset."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import torch

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, TrafficRLHFError
from trafficrlhf_sdk.feedback.preference import PreferenceDataset, export_preferences
from trafficrlhf_sdk.feedback.store import FeedbackStore
from trafficrlhf_sdk.reward.data import build_pair_data, filter_pairs
from trafficrlhf_sdk.reward.losses import preference_metrics
from trafficrlhf_sdk.reward.model import RewardEnsemble, RewardModel
from trafficrlhf_sdk.reward.oracle import hidden_realism, strict_pairs

__all__ = ["GAP_BINS", "evaluate_model", "load_preferences", "score_futures"]

GAP_BINS = (0.0, 0.05, 0.2)  # hidden-realism gaps reported separately by evaluate_model


def load_preferences(db: str | None = None, campaign: str | Sequence[str] | None = None, data: str | None = None,
                     annotators: Sequence[str] = (), val_fraction: float = 0.0,
                     seed: int = 0) -> tuple[PreferenceDataset, FeedbackStore | None]:
    """A preference dataset from a campaign in database ``db`` or from an exported folder ``data``.

    ``campaign`` may name several campaigns of ``db`` (e.g. one per RLHF round): their datasets are
    concatenated. Only the pairs of ``annotators`` are kept when given. A campaign is exported with
    ``val_fraction`` of its contexts marked "val" (seeded hash by scene). Returns the dataset and the store (None
    for ``data``).
    """
    if (db is None) == (data is None):
        raise TrafficRLHFError("pass either a feedback database and campaign (`--db`, `--campaign`) or an exported "
                         "dataset folder (`--data`).")
    store = None
    if data is not None:
        dataset = PreferenceDataset.load(data)
    else:
        if not campaign:
            raise TrafficRLHFError("`--campaign` is required with `--db`.")
        if not os.path.isfile(db):  # type: ignore[arg-type]
            raise DataNotFoundError(f"feedback database {db!r} does not exist; create it with `trafficrlhf feedback "
                                    "create --db ...`.")
        store = FeedbackStore(db)  # type: ignore[arg-type]
        names = [campaign] if isinstance(campaign, str) else list(campaign)
        parts = []
        for name in names:  # in a pool (e.g. one campaign per RLHF round), a round of only ties adds no pairs
            try:
                parts.append(export_preferences(store, name, val_fraction=val_fraction, seed=seed))
            except DataFormatError:
                if len(names) == 1:
                    raise
        if not parts:
            raise DataFormatError(f"campaigns {names} hold no preference pairs (only ties, or no labels); label "
                                  "them first.")
        dataset = PreferenceDataset.concat(parts)
    return filter_pairs(dataset, list(annotators)), store


def score_futures(model: RewardModel, dataset: PreferenceDataset) -> tuple[torch.Tensor, torch.Tensor, Any]:
    """Rewards of the winners and losers ``(P,)`` of ``dataset``'s pairs, and the members' std for ensembles."""
    data = build_pair_data(model.prepare, dataset, split=tuple("val" for _ in range(dataset.num_contexts)))
    model.eval()
    with torch.no_grad():
        if isinstance(model, RewardEnsemble):
            per_member = torch.stack([m.score_prepared(data.inputs) for m in model.members])
            scores, spread = per_member.mean(0), per_member.std(0) if len(model.members) > 1 else None
        else:
            scores, spread = model.score_prepared(data.inputs), None
    return scores[data.winner], scores[data.loser], None if spread is None else spread


def evaluate_model(model: RewardModel, dataset: PreferenceDataset, store: FeedbackStore | None = None,
                   tie_tolerance: float | None = 0.0) -> dict[str, Any]:
    """Accuracy (share of pairs with r(S_w) > r(S_l)), margin and reward range on every pair of ``dataset``.

    With ``store`` (the campaign's database) and a ``tie_tolerance``, the pairs are also judged by the synthetic
    annotator's hidden realism: ``strict_*`` metrics count only pairs whose winner is more realistic by more than
    ``tie_tolerance`` (a noise-free annotator's real preferences; ties carry none), and ``accuracy_gap_above_g``
    those with a realism gap above each ``g`` of :data:`GAP_BINS`.
    """
    chosen, rejected, spread = score_futures(model, dataset)
    result: dict[str, Any] = {"pairs": len(chosen), "contexts": int(dataset.pairs[:, 0].unique().numel()),
                              **{k: v for k, v in preference_metrics(chosen, rejected).items() if k != "num_pairs"}}
    result["none_realistic_pairs"] = int((dataset.pairs[:, 1] == dataset.num_candidates).sum())
    if spread is not None:
        result["mean_member_std"] = float(spread.mean())
    if store is not None and tie_tolerance is not None:
        realism = hidden_realism(store, dataset)
        c, w, lo = dataset.pairs.unbind(1)
        gap = realism[c, w] - realism[c, lo]
        mask = strict_pairs(dataset, realism, tie_tolerance)
        result["tie_tolerance"] = tie_tolerance
        result["strict_pairs"] = int(mask.sum())
        strict = preference_metrics(chosen[mask], rejected[mask])
        result["strict_accuracy"] = strict["accuracy"]
        result["strict_margin"] = strict["margin"]
        for g in GAP_BINS:
            sel = gap > g
            result[f"accuracy_gap_above_{g:g}"] = preference_metrics(chosen[sel], rejected[sel])["accuracy"]
            result[f"pairs_gap_above_{g:g}"] = int(sel.sum())
    return result
