"""Row types of the feedback store and the safetensors encoding of stored futures."""

from __future__ import annotations

import hashlib
import json
import sqlite3
from dataclasses import dataclass
from typing import Any

import torch
from safetensors.torch import load, save

from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.feedback.settings import AnnotationSettings
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["TIE_SLOT", "Annotator", "Assignment", "Campaign", "ContextRecord", "Label", "decode_future",
           "encode_future", "hash_token"]

TIE_SLOT = -1  # the stored slot of "equally realistic"


def hash_token(token: str) -> str:
    """SHA-256 hex digest of a token. Tokens are 192-bit random strings, so a fast unsalted hash is safe."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class Campaign:
    """A campaign row; ``config`` is the :class:`~trafficrlhf_sdk.feedback.campaign.CampaignConfig` as a dict."""

    id: int
    name: str
    model: str
    guidance: str | None
    seed: int
    num_candidates: int
    sdk_version: str
    created_at: str
    config: dict[str, Any]

    @property
    def labels_per_item(self) -> int | None:
        """How many annotators should label each item (None: every annotator labels every item)."""
        return self.config.get("labels_per_item")

    @property
    def settings(self) -> AnnotationSettings:
        """Playback, guidelines, gold items, qualification, leases and ties of this campaign."""
        return AnnotationSettings.from_config(self.config)

    @property
    def models(self) -> tuple[str, ...]:
        """The traffic models of the candidates (several when the campaign mixes models)."""
        return tuple(self.config.get("candidate_models") or [self.model])


@dataclass(frozen=True)
class Annotator:
    """An annotator (a person or a synthetic one) identified by a token."""

    id: int
    name: str
    created_at: str
    active: bool


@dataclass(frozen=True)
class Assignment:
    """One item shown to one annotator: ``permutation[k]`` is the candidate index shown in slot ``k + 1``."""

    id: int
    annotator_id: int
    context_id: int
    campaign_id: int
    position: int
    permutation: tuple[int, ...]
    assigned_at: str
    status: str = "open"  # open | labeled | skipped
    slot: int | None = None  # the slot of the label, when labeled
    skip_reason: str | None = None


@dataclass(frozen=True)
class Label:
    """A stored label. ``slot`` 0 means "none realistic" (``candidate`` None: the logged future wins); ``slot``
    -1 means the candidates are equally realistic (a tie; ``candidate`` None)."""

    id: int
    context_id: int
    annotator_id: int
    campaign_id: int
    slot: int
    candidate: int | None
    permutation: tuple[int, ...]
    time_on_item_ms: int | None
    source: str
    created_at: str
    revision: int

    @property
    def none_realistic(self) -> bool:
        """True when the annotator declared no candidate realistic."""
        return self.slot == 0

    @property
    def tie(self) -> bool:
        """True when the annotator found the candidates equally realistic."""
        return self.slot == TIE_SLOT


@dataclass(frozen=True)
class ContextRecord:
    """One item with its tensors.

    Fields:
        scenario: the logged scene ``(1, A, T, 4)`` over history + candidate window; ``current_index`` = start.
        candidates: float32 ``(N, A, H, 4)`` model futures after the start step; ``candidate_valid`` bool
            ``(N, A, H)``; ``logged`` ``(A, H, 4)`` and ``logged_valid`` ``(A, H)``: the logged future.
        controlled: bool ``(A,)``: agents the model drove (the others replay the log in every candidate).
        candidate_models: the traffic model of each candidate (None where the database does not say).
        gold_answer: for a gold item, the index of the candidate known to be the right answer; else None.
        priority: serving priority (higher first).
    """

    id: int
    campaign_id: int
    ordinal: int
    source: str
    split: str
    scene_id: str
    seed: int
    start_index: int
    scenario: ScenarioTensor
    candidates: torch.Tensor
    candidate_valid: torch.Tensor
    logged: torch.Tensor
    logged_valid: torch.Tensor
    candidate_models: tuple[str | None, ...] = ()
    gold_answer: int | None = None
    priority: float = 0.0

    @property
    def controlled(self) -> torch.Tensor:
        """Controlled agents, bool ``(A,)``."""
        return self.scenario.controlled[0]

    @property
    def num_candidates(self) -> int:
        """N."""
        return int(self.candidates.shape[0])

    def candidate_scenario(self, index: int | None) -> ScenarioTensor:
        """History + candidate ``index``'s future (``None``: the logged future) as a ScenarioTensor (B = 1)."""
        states, valid = (self.logged, self.logged_valid) if index is None else \
            (self.candidates[index], self.candidate_valid[index])
        return self.scenario.with_future(states[None], valid[None])


def encode_future(states: torch.Tensor, valid: torch.Tensor) -> bytes:
    """The safetensors bytes of one future: ``states (A, H, 4)`` float32 and ``valid (A, H)`` bool."""
    return save({"states": states.detach().cpu().float().contiguous(),
                 "valid": valid.detach().cpu().bool().contiguous()},
                metadata={"format": "pt", "trafficrlhf_future": "1"})


def decode_future(data: bytes, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of :func:`encode_future`."""
    try:
        tensors = load(bytes(data))
        return tensors["states"], tensors["valid"]
    except Exception as exc:  # safetensors raises several types for corrupt bytes
        raise DataFormatError(f"{name}: stored future is not readable ({exc}); the database may be damaged.") from exc


def _campaign(row: sqlite3.Row) -> Campaign:
    return Campaign(row["id"], row["name"], row["model"], row["guidance"], row["seed"], row["num_candidates"],
                    row["sdk_version"], row["created_at"], json.loads(row["config_json"]))


def _assignment(row: sqlite3.Row) -> Assignment:
    return Assignment(row["id"], row["annotator_id"], row["context_id"], row["campaign_id"], row["position"],
                      tuple(json.loads(row["permutation"])), row["assigned_at"])


def _label(row: sqlite3.Row) -> Label:
    return Label(row["id"], row["context_id"], row["annotator_id"], row["campaign_id"], row["slot"], row["candidate"],
                 tuple(json.loads(row["permutation"])), row["time_on_item_ms"], row["source"], row["created_at"],
                 row["revision"])
