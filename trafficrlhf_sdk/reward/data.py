"""Preference pairs prepared for a reward model: every distinct future featurized once, pairs as indices.

A choice among N candidates yields N-1 pairs that share the winner, so scoring pairs one by one would score
the winner N-1 times. :class:`PairData` keeps each future of a context once (``inputs``, in the model's
prepared form) and the pairs as (winner, loser) indices into it, grouped by context so that batches, the
train/val split and bootstrap draws are by context, never by pair.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from collections.abc import Callable, Sequence
from typing import Any

import torch

from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.feedback.preference import PreferenceDataset, split_contexts
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["PairData", "build_pair_data", "filter_pairs", "split_by_context"]


@dataclass(frozen=True)
class PairData:
    """Pairs over featurized futures.

    Fields:
        inputs: the model's prepared inputs of F futures (scene f = future f).
        winner, loser: int64 ``(P,)`` future indices; labels: float32 ``(P,)`` probability that the winner is
            preferred (1 for a choice, 0.5 for a tie).
        pair_context: int64 ``(P,)`` and future_context: int64 ``(F,)``: the context of each pair and future.
        context_keys: one dict per context (campaign, scene, ...); split: "train"/"val" per context.
    """

    inputs: Any
    winner: torch.Tensor
    loser: torch.Tensor
    labels: torch.Tensor
    pair_context: torch.Tensor
    future_context: torch.Tensor
    context_keys: tuple[dict[str, Any], ...]
    split: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.winner.shape[0])

    @property
    def num_contexts(self) -> int:
        """K (contexts without pairs included)."""
        return len(self.context_keys)

    def contexts_with_pairs(self) -> torch.Tensor:
        """Indices of the contexts that have at least one pair."""
        return torch.unique(self.pair_context)

    def batch(self, contexts: torch.Tensor | Sequence[int]) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(inputs of the contexts' futures, winner and loser positions in them, labels) for ``contexts``.

        Repeated contexts (bootstrap draws) are repeated with all their futures and pairs.
        """
        futures, winners, losers, labels = [], [], [], []
        offset = 0
        by_context_f, by_context_p = self._index()
        for c in torch.as_tensor(contexts, dtype=torch.long).tolist():
            fut, prs = by_context_f[c], by_context_p[c]
            position = torch.full((int(self.future_context.shape[0]),), -1, dtype=torch.long)
            position[fut] = torch.arange(len(fut)) + offset
            futures.append(fut)
            winners.append(position[self.winner[prs]])
            losers.append(position[self.loser[prs]])
            labels.append(self.labels[prs])
            offset += len(fut)
        if not futures:
            raise ValueError("`contexts` is empty.")
        return (self.inputs.select(torch.cat(futures)), torch.cat(winners), torch.cat(losers), torch.cat(labels))

    def _index(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        cache = self.__dict__.get("_cache")
        if cache is None:
            k = self.num_contexts
            f_order = torch.argsort(self.future_context, stable=True)
            p_order = torch.argsort(self.pair_context, stable=True)
            f_counts = torch.bincount(self.future_context, minlength=k).tolist()
            p_counts = torch.bincount(self.pair_context, minlength=k).tolist()
            cache = (list(torch.split(f_order, f_counts)), list(torch.split(p_order, p_counts)))
            object.__setattr__(self, "_cache", cache)
        return cache

    def subset(self, contexts: torch.Tensor | Sequence[int]) -> PairData:
        """The given contexts (no repeats) with their futures and pairs, renumbered in the given order."""
        contexts = torch.as_tensor(contexts, dtype=torch.long)
        if len(torch.unique(contexts)) != len(contexts):
            raise ValueError("`contexts` holds repeats; use `batch` for bootstrap draws.")
        inputs, winner, loser, labels = self.batch(contexts)
        remap = torch.full((self.num_contexts,), -1, dtype=torch.long)
        remap[contexts] = torch.arange(len(contexts))
        by_context_f, by_context_p = self._index()
        future_context = torch.cat([torch.full((len(by_context_f[c]),), i) for i, c in enumerate(contexts.tolist())])
        pair_context = torch.cat([torch.full((len(by_context_p[c]),), i) for i, c in enumerate(contexts.tolist())])
        return PairData(inputs, winner, loser, labels, pair_context, future_context,
                        tuple(self.context_keys[c] for c in contexts.tolist()),
                        tuple(self.split[c] for c in contexts.tolist()))

    def split_subset(self, split: str) -> PairData:
        """The contexts whose split is ``split`` ("train" or "val")."""
        return self.subset([i for i, s in enumerate(self.split) if s == split])

    def with_labels(self, labels: torch.Tensor) -> PairData:
        """The same pairs with other labels ``(P,)``."""
        if labels.shape != self.labels.shape:
            raise ValueError(f"`labels` must have shape {tuple(self.labels.shape)}; got {tuple(labels.shape)}.")
        return replace(self, labels=labels.float())


def filter_pairs(dataset: PreferenceDataset, annotators: Sequence[str] | None = None,
                 mask: torch.Tensor | None = None) -> PreferenceDataset:
    """The dataset with only the pairs of ``annotators`` (names) and where ``mask (P,)`` is True."""
    keep = torch.ones(len(dataset), dtype=torch.bool) if mask is None else mask.bool().clone()
    if annotators:
        unknown = [a for a in annotators if a not in dataset.annotators]
        if unknown:
            raise DataFormatError(f"annotators {unknown} have no pairs in this dataset; its annotators are "
                                  f"{list(dataset.annotators)}.")
        wanted = torch.tensor([dataset.annotators.index(a) for a in annotators])
        keep &= torch.isin(dataset.pair_annotator, wanted)
    return replace(dataset, pairs=dataset.pairs[keep], pair_annotator=dataset.pair_annotator[keep],
                   pair_label=dataset.pair_label[keep],
                   pair_prob=None if dataset.pair_prob is None else dataset.pair_prob[keep])


def split_by_context(dataset: PreferenceDataset, val_fraction: float, seed: int = 0) -> tuple[str, ...]:
    """The dataset's own train/val split when it has both, else a seeded hash split of its contexts."""
    if "train" in dataset.context_split and "val" in dataset.context_split:
        return tuple(dataset.context_split)
    if val_fraction <= 0 or dataset.num_contexts < 2:
        return tuple("train" for _ in range(dataset.num_contexts))
    keys = [f"{k.get('source')}/{k.get('split')}/{k.get('scene_id')}/{k.get('context_id')}"
            for k in dataset.context_keys]
    return tuple(split_contexts(keys, val_fraction, seed))


def build_pair_data(prepare: Callable[[ScenarioTensor], Any], dataset: PreferenceDataset,
                    labels: torch.Tensor | None = None, split: Sequence[str] | None = None,
                    progress: bool = False) -> PairData:
    """Featurize the futures that ``dataset``'s pairs use, once each, with ``prepare`` (a model's ``prepare``).

    Args:
        prepare: scenario batch -> prepared inputs (``RewardModel.prepare``).
        dataset: a :class:`PreferenceDataset`.
        labels: ``(P,)`` probability that each pair's winner is preferred; default the dataset's own (1, or 0.5
            for the pairs of an "equally realistic" answer).
        split: "train"/"val" per context; default the dataset's ``context_split``.
        progress: show a progress bar.
    """
    if len(dataset) == 0:
        raise DataFormatError("the preference dataset has no pairs; label the campaign (or pick other annotators).")
    pairs = dataset.pairs
    k, slots = dataset.num_contexts, dataset.futures.shape[1]
    used = torch.zeros(k, slots, dtype=torch.bool)
    used[pairs[:, 0], pairs[:, 1]] = True
    used[pairs[:, 0], pairs[:, 2]] = True
    future_id = torch.full((k, slots), -1, dtype=torch.long)
    ctx, slot = used.nonzero(as_tuple=True)  # sorted by context, then slot
    future_id[ctx, slot] = torch.arange(len(ctx))
    contexts = ctx.unique().tolist()
    if progress:
        from trafficrlhf_sdk.console import progress as progress_bar

        contexts = progress_bar(contexts, desc="featurizing", unit="context", leave=False)
    parts = []
    with torch.no_grad():
        for c in contexts:
            js = slot[ctx == c]
            scene = dataset.contexts[c]
            scenes = ScenarioTensor.concat([scene] * len(js)) if len(js) > 1 else scene
            parts.append(prepare(scenes.with_future(dataset.futures[c, js][:, : scene.num_agents],
                                                    dataset.future_valid[c, js][:, : scene.num_agents])))
    inputs = type(parts[0]).concat(parts)
    return PairData(
        inputs=inputs, winner=future_id[pairs[:, 0], pairs[:, 1]], loser=future_id[pairs[:, 0], pairs[:, 2]],
        labels=dataset.labels if labels is None else labels.float(), pair_context=pairs[:, 0].clone(),
        future_context=ctx.clone(), context_keys=tuple(dataset.context_keys),
        split=tuple(split if split is not None else dataset.context_split),
    )
