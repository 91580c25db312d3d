"""Inter-annotator agreement over items labeled by several annotators.

Categories are what an answer *means*, not the slot pressed (slots are shuffled per annotator): the candidate
index, "none realistic", or "equally realistic" (a tie). Only items with at least two labels count; gold items
never do (they measure accuracy, not agreement).

- **Pairwise agreement** P̄: per item, the share of ordered annotator pairs that gave the same answer,
  ``P_i = sum_j n_ij (n_ij - 1) / (n_i (n_i - 1))``, averaged over items.
- **Fleiss' kappa** ``(P̄ - P_e) / (1 - P_e)`` with ``P_e = sum_j p_j^2`` and ``p_j`` the share of all labels in
  category j. Items may have different numbers of raters (the usual generalization: each item's ``P_i`` uses
  its own ``n_i``). Undefined (None) when every label falls in one category (``P_e = 1``).
- Per annotator: items shared with others and agreement with the majority of the *other* annotators
  (ties count as disagreement); per annotator pair: shared items and raw agreement.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from itertools import combinations
from collections.abc import Iterable
from typing import Any

__all__ = ["agreement_report", "annotator_agreement", "campaign_agreement", "fleiss_kappa"]

NONE = "none"
TIE = "tie"


def fleiss_kappa(item_counts: Iterable[Counter[Any]]) -> tuple[float | None, float | None, int]:
    """``(kappa, pairwise_agreement, items)`` from per-item category counts (items with < 2 labels dropped)."""
    items = [c for c in item_counts if sum(c.values()) >= 2]
    if not items:
        return None, None, 0
    totals: Counter[Any] = Counter()
    p_items = []
    for counts in items:
        n = sum(counts.values())
        p_items.append(sum(k * (k - 1) for k in counts.values()) / (n * (n - 1)))
        totals.update(counts)
    p_bar = sum(p_items) / len(p_items)
    grand = sum(totals.values())
    p_e = sum((v / grand) ** 2 for v in totals.values())
    kappa = None if p_e >= 1.0 - 1e-12 else (p_bar - p_e) / (1.0 - p_e)
    return kappa, p_bar, len(items)


def agreement_report(labels: Iterable[tuple[int, str, int | str | None]]) -> dict[str, Any]:
    """Agreement statistics from ``(item, annotator, answer)`` triples (one per item and annotator); the answer
    is a candidate index, None ("none realistic") or ``"tie"``.

    Returns a JSON-ready dict: ``items_multi`` (items with >= 2 labels), ``fleiss_kappa``,
    ``pairwise_agreement``, ``annotators`` (per annotator: labels, shared, agree_with_majority) and ``pairs``
    (per annotator pair: shared, agreement).
    """
    by_item: dict[int, dict[str, Any]] = defaultdict(dict)
    for item, annotator, candidate in labels:
        by_item[item][annotator] = NONE if candidate is None else TIE if candidate == TIE else int(candidate)
    kappa, p_bar, n_items = fleiss_kappa(Counter(answers.values()) for answers in by_item.values())
    per: dict[str, dict[str, int]] = defaultdict(lambda: {"labels": 0, "shared": 0, "agree": 0})
    pairs: dict[tuple[str, str], list[int]] = defaultdict(lambda: [0, 0])
    for answers in by_item.values():
        for annotator, answer in answers.items():
            per[annotator]["labels"] += 1
            others = Counter(a for who, a in answers.items() if who != annotator)
            if not others:
                continue
            per[annotator]["shared"] += 1
            ranked = others.most_common(2)
            unique_majority = len(ranked) == 1 or ranked[0][1] > ranked[1][1]
            per[annotator]["agree"] += int(unique_majority and ranked[0][0] == answer)
        for a, b in combinations(sorted(answers), 2):
            pairs[(a, b)][0] += 1
            pairs[(a, b)][1] += int(answers[a] == answers[b])
    return {
        "items": len(by_item),
        "items_multi": n_items,
        "fleiss_kappa": kappa,
        "pairwise_agreement": p_bar,
        "annotators": [
            {"annotator": name, "labels": s["labels"], "shared": s["shared"],
             "agree_with_majority": s["agree"] / s["shared"] if s["shared"] else None}
            for name, s in sorted(per.items())
        ],
        "pairs": [{"a": a, "b": b, "shared": n, "agreement": agree / n}
                  for (a, b), (n, agree) in sorted(pairs.items())],
    }


def campaign_agreement(store: Any, campaign: Any) -> dict[str, Any]:
    """:func:`agreement_report` over the labels of ``campaign`` in ``store`` (a ``FeedbackStore``)."""
    names = {a.id: a.name for a in store.annotators()}
    return agreement_report((label.context_id, names[label.annotator_id], TIE if label.tie else label.candidate)
                            for label in store.labels(campaign))


def annotator_agreement(store: Any, campaign: Any, annotator: str) -> dict[str, Any]:
    """Only ``annotator``'s own figures (what an annotator may see): items shared with others and agreement with
    their majority, without anybody else's name or counts."""
    report = campaign_agreement(store, campaign)
    own = next((a for a in report["annotators"] if a["annotator"] == annotator),
               {"annotator": annotator, "labels": 0, "shared": 0, "agree_with_majority": None})
    return {"annotator": own}
