"""The synthetic annotator's hidden judgment, for scoring a reward model against a noise-free annotator.

A noise-free :class:`~trafficrlhf_sdk.feedback.SyntheticAnnotator` (``beta=None``, ``epsilon=0``) picks the
candidate of highest hidden realism. When several candidates are equally realistic (often: CTG candidates
without any collision, off-road or kinematic excess all score exactly 1) it still has to pick one, and the
pairs "pick ≻ equally good candidate" carry no preference. :func:`strict_pairs` marks the pairs whose winner
is strictly more realistic than the loser (by more than ``tolerance``), as B-Pref's "equal" teacher would.
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.feedback.preference import PreferenceDataset
from trafficrlhf_sdk.feedback.store import FeedbackStore
from trafficrlhf_sdk.feedback.synthetic import SyntheticAnnotatorConfig, judge_realism

__all__ = ["hidden_realism", "strict_pairs"]


def hidden_realism(store: FeedbackStore, dataset: PreferenceDataset,
                   config: SyntheticAnnotatorConfig | None = None) -> torch.Tensor:
    """Hidden realism ``(K, N + 1)`` of every future of every context of ``dataset`` (index N: the logged one).

    The contexts are read back from ``store`` by the ``context_id`` and ``campaign`` of ``dataset.context_keys``.
    """
    realism = torch.zeros(dataset.num_contexts, dataset.futures.shape[1], dtype=torch.float64)
    campaigns: dict[str, object] = {}
    for k, key in enumerate(dataset.context_keys):
        name = key["campaign"]
        if name not in campaigns:
            campaigns[name] = store.campaign(name)
        record = store.load_context(int(key["context_id"]), campaigns[name])  # type: ignore[arg-type]
        judged = judge_realism(record, config, include_logged=True).realism
        realism[k, : len(judged) - 1] = judged[:-1]
        realism[k, -1] = judged[-1]
    return realism


def strict_pairs(dataset: PreferenceDataset, realism: torch.Tensor, tolerance: float = 0.0) -> torch.Tensor:
    """Whether each pair's winner is more realistic than its loser by more than ``tolerance``, bool ``(P,)``."""
    c, w, lo = dataset.pairs.unbind(1)
    return (realism[c, w] - realism[c, lo]) > tolerance
