"""``PreferenceDataset``: the pairs a feedback campaign yields, for reward-model training.

A choice of candidate w among N yields N-1 pairs ``w ≻ l`` (one per other candidate l); "none realistic"
yields N pairs ``logged ≻ candidate``. The N-1 pairs of one choice share their winner, so they are not
independent: count *choices* (``num_choices``), not pairs, when judging how much data there is.

"Equally realistic" (a tie) yields no pair by default (``ties="drop"``); with ``ties="soft"`` it yields the
N(N-1)/2 pairs of its candidates, each with probability 0.5 that the first is preferred (``pair_prob``), which
the Bradley–Terry loss of :mod:`trafficrlhf_sdk.reward.losses` reads as a tie. A dataset whose pairs are all
hard keeps ``pair_prob`` None (every pair 1) and is written as format 1; soft pairs make it format 2, which
readers of format 1 refuse rather than misread. Gold items are never exported, and with a qualification
(``qualification_gold`` > 0) only the labels of annotators who passed it are.

Storage is compact: each context's scene is kept once and every future (N candidates + the logged one) once;
a pair is three indices. :meth:`PreferenceDataset.pair_scenarios` builds the (winner, loser) scenario windows
(history + future) on demand. Saved as ``preferences.safetensors`` (tensors; metadata as JSON strings in the
header) plus a readable ``metadata.json``; never pickle. The train/val split is by context, never by pair, so
no context has pairs on both sides.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from collections.abc import Sequence
from typing import Any, Literal

import torch
from safetensors.torch import save_file

from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.feedback.store import Campaign, FeedbackStore
from trafficrlhf_sdk.safetensors_files import check_safetensors_file
from trafficrlhf_sdk.scenario.io import safe_load_file
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor, scenario_from_tensors, scenario_tensors

__all__ = ["PreferenceDataset", "export_preferences", "split_contexts"]

FORMAT_VERSION = "1"  # all pairs hard
SOFT_FORMAT_VERSION = "2"  # adds `pair_prob`
TENSORS_FILE = "preferences.safetensors"
METADATA_FILE = "metadata.json"


@dataclass(frozen=True)
class PreferenceDataset:
    """Preference pairs over the futures of K contexts.

    Fields:
        contexts: the K logged scenes ``(K, A, T, 4)`` (history + logged future; ``current_index`` = the start
            of the candidates), padded to common A and T, with their maps.
        futures: float32 ``(K, N + 1, A, H, 4)``: the N candidates then, at index N, the logged future.
        future_valid: bool ``(K, N + 1, A, H)``.
        pairs: int64 ``(P, 3)``: (context, winner, loser) with winner/loser indices into ``futures`` axis 1.
        pair_annotator: int64 ``(P,)`` index into ``annotators``; ``pair_label``: int64 ``(P,)`` label id in the
            database (pairs of one choice share it).
        context_split: ``"train"`` or ``"val"`` per context.
        context_keys: per context: campaign, source, split, scene_id, context_id and ``models`` (the traffic
            model of each candidate, for cross-model studies).
        annotators: annotator names.
        metadata: campaign provenance (model, guidance, seed, SDK version) and counts.
        pair_prob: float32 ``(P,)``: probability that the pair's winner is preferred (0.5 for the pairs of a
            tie); None means 1 for every pair.
    """

    contexts: ScenarioTensor
    futures: torch.Tensor
    future_valid: torch.Tensor
    pairs: torch.Tensor
    pair_annotator: torch.Tensor
    pair_label: torch.Tensor
    context_split: tuple[str, ...]
    context_keys: tuple[dict[str, Any], ...]
    annotators: tuple[str, ...]
    metadata: dict[str, Any] = field(default_factory=dict)
    pair_prob: torch.Tensor | None = None

    def __post_init__(self) -> None:
        k = self.contexts.num_scenes
        if self.futures.dim() != 5 or self.futures.shape[0] != k or self.futures.shape[2] != self.contexts.num_agents:
            raise DataFormatError(f"`futures` must have shape ({k}, N+1, {self.contexts.num_agents}, H, 4); got "
                                  f"{tuple(self.futures.shape)}.")
        if tuple(self.future_valid.shape) != tuple(self.futures.shape[:4]):
            raise DataFormatError(f"`future_valid` must have shape {tuple(self.futures.shape[:4])}.")
        if self.pairs.dim() != 2 or self.pairs.shape[1] != 3:
            raise DataFormatError(f"`pairs` must have shape (P, 3); got {tuple(self.pairs.shape)}.")
        if len(self.pairs) and (int(self.pairs[:, 0].max()) >= k
                                or int(self.pairs[:, 1:].max()) >= self.futures.shape[1]):
            raise DataFormatError("`pairs` points past the stored contexts or futures; the dataset is inconsistent.")
        if len(self.context_split) != k or len(self.context_keys) != k:
            raise DataFormatError(f"`context_split` and `context_keys` must hold one entry per context ({k}).")
        if self.pair_prob is not None and tuple(self.pair_prob.shape) != (int(self.pairs.shape[0]),):
            raise DataFormatError(f"`pair_prob` must hold one probability per pair ({int(self.pairs.shape[0])}); got "
                                  f"shape {tuple(self.pair_prob.shape)}. Filter it together with `pairs`.")

    @property
    def labels(self) -> torch.Tensor:
        """float32 ``(P,)``: probability that each pair's winner is preferred (1, or 0.5 for tie pairs)."""
        return torch.ones(len(self)) if self.pair_prob is None else self.pair_prob.float()

    # ------------------------------------------------------------------------------------------- views
    def __len__(self) -> int:
        return int(self.pairs.shape[0])

    @property
    def num_contexts(self) -> int:
        """K."""
        return self.contexts.num_scenes

    @property
    def num_candidates(self) -> int:
        """N (the logged future is index N)."""
        return int(self.futures.shape[1]) - 1

    @property
    def num_choices(self) -> int:
        """Distinct labels behind the pairs (the number of independent judgments)."""
        return int(torch.unique(self.pair_label).numel())

    def pair_scenarios(self, index: torch.Tensor | slice | list[int] | None = None) -> tuple[ScenarioTensor,
                                                                                             ScenarioTensor]:
        """(winners, losers): scenario batches (history + the pair's future), one scene per selected pair."""
        rows = self.pairs if index is None else self.pairs[index]
        if rows.dim() == 1:
            rows = rows[None]
        scenes = self.contexts[rows[:, 0]]

        def build(which: torch.Tensor) -> ScenarioTensor:
            return scenes.with_future(self.futures[rows[:, 0], which], self.future_valid[rows[:, 0], which])

        return build(rows[:, 1]), build(rows[:, 2])

    def subset(self, split: str) -> PreferenceDataset:
        """The contexts of ``split`` (``"train"`` or ``"val"``) and their pairs."""
        if split not in ("train", "val"):
            raise ValueError(f"`split` must be 'train' or 'val'; got {split!r}.")
        keep = [i for i, s in enumerate(self.context_split) if s == split]
        remap = torch.full((self.num_contexts,), -1, dtype=torch.long)
        remap[keep] = torch.arange(len(keep))
        mask = remap[self.pairs[:, 0]] >= 0
        pairs = self.pairs[mask].clone()
        pairs[:, 0] = remap[pairs[:, 0]]
        if not keep:
            raise ValueError(f"the dataset has no {split!r} context; export with a different `val_fraction`.")
        return PreferenceDataset(self.contexts[keep], self.futures[keep], self.future_valid[keep], pairs,
                                 self.pair_annotator[mask], self.pair_label[mask], tuple(split for _ in keep),
                                 tuple(self.context_keys[i] for i in keep), self.annotators, dict(self.metadata),
                                 None if self.pair_prob is None else self.pair_prob[mask])

    @staticmethod
    def concat(datasets: Sequence[PreferenceDataset]) -> PreferenceDataset:
        """One dataset from several (e.g. the campaigns of successive RLHF rounds), contexts stacked in order.

        Agents and future steps are padded with invalid entries; every dataset must have the same N. Pair
        context indices are shifted, annotators merged by name; label ids are kept (unique within one database).
        Each context keeps the train/val split it was exported with. Campaigns that start their candidates after
        different lengths of history (``history_seconds``) are aligned at that start: the longer histories are cut
        to the shortest one.
        """
        if not datasets:
            raise ValueError("`datasets` is empty; pass at least one PreferenceDataset.")
        sizes = {d.num_candidates for d in datasets}
        if len(sizes) > 1:
            raise DataFormatError(f"cannot concatenate datasets with different candidate counts N {sorted(sizes)}; "
                                  "train on campaigns with the same --candidates.")
        if len(datasets) == 1:
            return datasets[0]
        shortest = min(d.contexts.current_index for d in datasets)
        contexts = ScenarioTensor.concat([d.contexts.time_slice(d.contexts.current_index - shortest)
                                          for d in datasets])
        a, h = contexts.num_agents, max(int(d.futures.shape[3]) for d in datasets)
        annotators = tuple(sorted({name for d in datasets for name in d.annotators}))
        futures, valid, pairs, who = [], [], [], []
        offset = 0
        for d in datasets:
            pad = (0, 0, 0, h - d.futures.shape[3], 0, a - d.futures.shape[2])
            futures.append(torch.nn.functional.pad(d.futures, pad))
            valid.append(torch.nn.functional.pad(d.future_valid, pad[2:]))
            pairs.append(d.pairs + torch.tensor([offset, 0, 0]))
            remap = torch.tensor([annotators.index(name) for name in d.annotators], dtype=torch.long)
            who.append(remap[d.pair_annotator] if len(d.annotators) else d.pair_annotator)
            offset += d.num_contexts
        metadata = {"concatenated": [d.metadata for d in datasets],
                    "campaign": "+".join(str(d.metadata.get("campaign", "?")) for d in datasets)}
        soft = any(d.pair_prob is not None for d in datasets)
        return PreferenceDataset(contexts, torch.cat(futures), torch.cat(valid), torch.cat(pairs), torch.cat(who),
                                 torch.cat([d.pair_label for d in datasets]),
                                 tuple(s for d in datasets for s in d.context_split),
                                 tuple(k for d in datasets for k in d.context_keys), annotators, metadata,
                                 torch.cat([d.labels for d in datasets]) if soft else None)

    # ----------------------------------------------------------------------------------------------- io
    def save(self, directory: str | os.PathLike[str]) -> str:
        """Write ``preferences.safetensors`` and ``metadata.json`` into ``directory``; returns the directory."""
        directory = os.fspath(directory)
        os.makedirs(directory, exist_ok=True)
        tensors, scene_meta = scenario_tensors(self.contexts)
        tensors = {f"context.{k}": v for k, v in tensors.items()}
        tensors.update({"futures": self.futures.contiguous(), "future_valid": self.future_valid.contiguous(),
                        "pairs": self.pairs.contiguous(), "pair_annotator": self.pair_annotator.contiguous(),
                        "pair_label": self.pair_label.contiguous()})
        version = FORMAT_VERSION
        if self.pair_prob is not None:
            tensors["pair_prob"] = self.pair_prob.float().contiguous()
            version = SOFT_FORMAT_VERSION
        header = {f"context.{k}": v for k, v in scene_meta.items()}
        header.update({"format": "pt", "trafficrlhf_preferences": version,
                       "context_split": json.dumps(list(self.context_split)),
                       "context_keys": json.dumps(list(self.context_keys)),
                       "annotators": json.dumps(list(self.annotators)), "metadata": json.dumps(self.metadata)})
        save_file(tensors, os.path.join(directory, TENSORS_FILE), metadata=header)
        readable = {**self.metadata, "format_version": version, "num_pairs": len(self),
                    "num_soft_pairs": 0 if self.pair_prob is None else int((self.pair_prob != 1).sum()),
                    "num_choices": self.num_choices, "num_contexts": self.num_contexts,
                    "num_candidates": self.num_candidates, "annotators": list(self.annotators),
                    "contexts": [{**key, "subset": s} for key, s in zip(self.context_keys, self.context_split)],
                    "pair_semantics": "pairs[i] = (context, winner, loser); future index N is the logged future; "
                                      "pair_prob[i] (format 2) = P(winner preferred), 0.5 for a tie",
                    "files": {"tensors": TENSORS_FILE}}
        with open(os.path.join(directory, METADATA_FILE), "w", encoding="utf-8") as handle:
            json.dump(readable, handle, indent=2)
        return directory

    @staticmethod
    def load(directory: str | os.PathLike[str]) -> PreferenceDataset:
        """Read a dataset written by :meth:`save`."""
        path = os.path.join(os.fspath(directory), TENSORS_FILE)
        if os.path.isfile(path):  # a missing file gets safe_load_file's error
            check_safetensors_file(path, "preference dataset")
        tensors, header = safe_load_file(path)
        if header.get("trafficrlhf_preferences") not in (FORMAT_VERSION, SOFT_FORMAT_VERSION):
            raise DataFormatError(f"{path!r} is not a TrafficRLHF preference dataset (format "
                                  f"{header.get('trafficrlhf_preferences')!r}, expected {FORMAT_VERSION!r} or "
                                  f"{SOFT_FORMAT_VERSION!r}).")
        scene_tensors = {k[len("context."):]: v for k, v in tensors.items() if k.startswith("context.")}
        scene_meta = {k[len("context."):]: v for k, v in header.items() if k.startswith("context.")}
        try:
            contexts = scenario_from_tensors(scene_tensors, scene_meta, repr(path))
            return PreferenceDataset(
                contexts, tensors["futures"], tensors["future_valid"], tensors["pairs"], tensors["pair_annotator"],
                tensors["pair_label"], tuple(json.loads(header["context_split"])),
                tuple(json.loads(header["context_keys"])), tuple(json.loads(header["annotators"])),
                json.loads(header["metadata"]), tensors.get("pair_prob"),
            )
        except (KeyError, json.JSONDecodeError) as exc:
            raise DataFormatError(f"{path!r} lacks part of a preference dataset ({exc!r}); re-export it.") from exc


def split_contexts(keys: list[str], val_fraction: float, seed: int = 0) -> list[str]:
    """``"train"``/``"val"`` per context key: the ``round(val_fraction * K)`` keys with the smallest seeded hash
    go to val (at least one when ``val_fraction > 0`` and K >= 2). Stable when contexts are added."""
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"`val_fraction` must be in [0, 1); got {val_fraction!r}.")
    n_val = round(val_fraction * len(keys))
    if val_fraction > 0 and len(keys) >= 2:
        n_val = min(max(n_val, 1), len(keys) - 1)
    ranked = sorted(range(len(keys)), key=lambda i: hashlib.sha256(f"{seed}:{keys[i]}".encode()).digest())
    val = set(ranked[:n_val])
    return ["val" if i in val else "train" for i in range(len(keys))]


def export_preferences(store: FeedbackStore, campaign: Campaign | str, val_fraction: float = 0.2,
                       seed: int = 0, sources: tuple[str, ...] = ("human", "synthetic"),
                       ties: Literal["drop", "soft"] = "drop", qualified_only: bool = True) -> PreferenceDataset:
    """Turn the labels of ``campaign`` (from annotators of the given ``sources``) into a dataset.

    Only labeled regular contexts are included; skips yield nothing, gold items are left out. ``ties``: "drop"
    (a tie yields no pair; its context is kept only if other labels give it pairs) or "soft" (0.5 pairs between
    all its candidates). ``qualified_only``: when the campaign asks for a qualification, leave out the labels
    of annotators who have not passed it.
    """
    if ties not in ("drop", "soft"):
        raise ValueError(f"`ties` must be 'drop' or 'soft'; got {ties!r}.")
    campaign = store.campaign(campaign) if isinstance(campaign, str) else campaign
    labels = [label for label in store.labels(campaign) if label.source in sources]
    excluded: list[str] = []
    if qualified_only and campaign.settings.qualification_gold > 0:
        status = {a.id: store.quality(a, campaign)["status"] for a in store.annotators()}
        excluded = sorted({a.name for a in store.annotators() if status[a.id] != "passed"})
        labels = [label for label in labels if status.get(label.annotator_id) == "passed"]
    num_ties = sum(label.tie for label in labels)
    if ties == "drop":
        labels = [label for label in labels if not label.tie]
    if not labels:
        raise DataFormatError(f"campaign {campaign.name!r} has no labels from {list(sources)} to export yet (ties "
                              f"{ties!r}: {num_ties} ties; unqualified annotators left out: {excluded}); label it "
                              "first, or export ties as 'soft'.")
    names = {a.id: a.name for a in store.annotators()}
    context_ids = sorted({label.context_id for label in labels})
    records = [store.load_context(cid, campaign) for cid in context_ids]
    position = {cid: i for i, cid in enumerate(context_ids)}
    annotators = sorted({names[label.annotator_id] for label in labels})
    n = campaign.num_candidates
    rows, who, label_ids, prob = [], [], [], []
    for label in labels:
        c = position[label.context_id]
        if label.tie:
            found = [(c, i, j) for i in range(n) for j in range(i + 1, n)]
            p = 0.5
        else:
            winner = n if label.candidate is None else label.candidate
            found = [(c, winner, loser) for loser in range(n) if loser != winner]
            p = 1.0
        rows.extend(found)
        who.extend([annotators.index(names[label.annotator_id])] * len(found))
        label_ids.extend([label.id] * len(found))
        prob.extend([p] * len(found))
    contexts = ScenarioTensor.concat([r.scenario for r in records])
    a, h = contexts.num_agents, max(r.candidates.shape[2] for r in records)
    futures = torch.zeros(len(records), n + 1, a, h, 4)
    valid = torch.zeros(len(records), n + 1, a, h, dtype=torch.bool)
    for i, r in enumerate(records):
        ra, rh = r.candidates.shape[1], r.candidates.shape[2]
        futures[i, :n, :ra, :rh] = r.candidates
        futures[i, n, :ra, :rh] = r.logged
        valid[i, :n, :ra, :rh] = r.candidate_valid
        valid[i, n, :ra, :rh] = r.logged_valid
    keys = [{"campaign": campaign.name, "source": r.source, "split": r.split, "scene_id": r.scene_id,
             "context_id": r.id, "models": [m or campaign.model for m in r.candidate_models]} for r in records]
    split = split_contexts([f"{k['source']}/{k['split']}/{k['scene_id']}" for k in keys], val_fraction, seed)
    metadata = {"campaign": campaign.name, "model": campaign.model, "guidance": campaign.guidance,
                "campaign_seed": campaign.seed, "sdk_version": campaign.sdk_version, "split_seed": seed,
                "val_fraction": val_fraction, "label_sources": list(sources),
                "candidate_seconds": campaign.config.get("candidate_seconds"),
                "num_labels": len(labels), "num_none_realistic": sum(label.none_realistic for label in labels),
                "num_ties": num_ties, "ties": ties, "candidate_models": list(campaign.models),
                "unqualified_left_out": excluded}
    soft = any(p != 1.0 for p in prob)
    return PreferenceDataset(contexts, futures, valid, torch.tensor(rows, dtype=torch.long).reshape(-1, 3),
                             torch.tensor(who, dtype=torch.long), torch.tensor(label_ids, dtype=torch.long),
                             tuple(split), tuple(keys), tuple(annotators), metadata,
                             torch.tensor(prob, dtype=torch.float32) if soft else None)
