"""Gold items: items with a known answer, mixed into a campaign to check and qualify annotators.

:func:`add_gold_items` turns regular items into gold ones: the logged future of the scene is one candidate (the
right answer) and the others are the same log with one controlled vehicle visibly broken, so a careful
annotator cannot miss which is realistic:

- ``offroad``: the vehicle drifts sideways, 12 m by the end of the window;
- ``freeze``: it stops dead at the first future step and stays there;
- ``zigzag``: it swerves ±3 m across its path, a full swing every 3 s;
- ``overspeed``: it keeps speeding up, to 3 times the logged speed at the end.

The broken vehicle is the controlled vehicle that moves the most in the log (a parked car would hide a
``freeze``). Gold items share the campaign's candidate count, are never capped by ``labels_per_item``, and
are left out of the preference export and of agreement figures; their answers give each annotator's gold
accuracy and qualification (:meth:`FeedbackStore.quality`).
"""

from __future__ import annotations

import random

import torch

from trafficrlhf_sdk.feedback.errors import InvalidChoiceError
from trafficrlhf_sdk.feedback.records import ContextRecord
from trafficrlhf_sdk.feedback.store import Campaign, FeedbackStore

__all__ = ["BREAKS", "add_gold_items", "broken_future", "gold_candidates"]

BREAKS = ("offroad", "freeze", "zigzag", "overspeed")
GOLD_SUFFIX = "#gold"


def broken_future(states: torch.Tensor, valid: torch.Tensor, agent: int, kind: str, dt: float) -> torch.Tensor:
    """A copy of the future ``states (A, H, 4)`` (x, y, speed, yaw) with agent ``agent`` broken as ``kind``."""
    out = states.clone()
    track = states[agent].double()
    ok = valid[agent]
    h = track.shape[0]
    t = torch.arange(h, dtype=torch.float64) * dt
    span = max(float(t[-1]), dt)
    yaw = track[:, 3]
    normal = torch.stack([-torch.sin(yaw), torch.cos(yaw)], -1)
    xy = track[:, :2]
    first = xy[int(ok.nonzero()[0]) if ok.any() else 0]
    if kind == "offroad":
        xy = xy + normal * (12.0 * (t / span) ** 1.5)[:, None]
    elif kind == "freeze":
        xy = first.expand_as(xy).clone()
        out[agent, :, 2] = 0.0
    elif kind == "zigzag":
        xy = xy + normal * (3.0 * torch.sin(2 * torch.pi * t / 3.0))[:, None]
    elif kind == "overspeed":
        xy = first + (1.0 + 2.0 * t / span)[:, None] * (xy - first)
        out[agent, :, 2] = states[agent, :, 2] * (1.0 + 4.0 * t / span).to(out.dtype)
    else:
        raise InvalidChoiceError(f"unknown break {kind!r}; pick one of {BREAKS}.")
    out[agent, :, :2] = xy.to(out.dtype)
    return out


def gold_candidates(record: ContextRecord, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, int, list[str]]:
    """``(candidates (N, A, H, 4), valid (N, A, H), answer, kinds)`` for a gold version of ``record``: the logged
    future at index ``answer`` and N - 1 broken copies (``kinds[k]`` names candidate k; ``"logged"`` the answer)."""
    n = record.num_candidates
    valid = record.logged_valid
    moved = (record.logged[:, -1, :2] - record.logged[:, 0, :2]).norm(dim=-1)
    moved = torch.where(record.controlled & valid[:, 0] & valid[:, -1], moved, torch.full_like(moved, -1.0))
    if float(moved.max()) < 0:
        raise InvalidChoiceError(f"item {record.id} has no controlled agent valid over the whole future; pick "
                                 "another item for a gold one.")
    agent = int(moved.argmax())
    rng = random.Random(f"{seed}:{record.id}")
    answer = rng.randrange(n)
    kinds = [BREAKS[(k + rng.randrange(len(BREAKS))) % len(BREAKS)] for k in range(n - 1)]
    futures = [broken_future(record.logged, valid, agent, kind, record.scenario.dt) for kind in kinds]
    futures.insert(answer, record.logged.clone())
    kinds.insert(answer, "logged")
    return torch.stack(futures), valid[None].expand(n, -1, -1).clone(), answer, kinds


def add_gold_items(store: FeedbackStore, campaign: Campaign | str, count: int, seed: int = 0) -> list[int]:
    """Add ``count`` gold items to ``campaign``, built from its first regular items that have none yet; returns
    their ids. Raises :class:`InvalidChoiceError` when the campaign has too few regular items."""
    from trafficrlhf_sdk.version import __version__

    campaign = store.campaign(campaign) if isinstance(campaign, str) else campaign
    if count < 1:
        raise InvalidChoiceError(f"`count` must be at least 1; got {count!r}.")
    keys = store.context_keys(campaign)
    have = {k["scene_id"] for k in keys if k["gold_answer"] is not None}
    sources = [k for k in keys if k["gold_answer"] is None and k["scene_id"] + GOLD_SUFFIX not in have]
    if len(sources) < count:
        raise InvalidChoiceError(f"campaign {campaign.name!r} has {len(sources)} regular items without a gold copy; "
                                 f"cannot add {count} gold items. Lower `count` or extend the campaign first.")
    added = []
    for key in sources[:count]:
        record = store.load_context(key["id"], campaign)
        candidates, valid, answer, kinds = gold_candidates(record, seed)
        models = [f"gold:{kind}" for kind in kinds]
        added.append(store.add_context(campaign, record.source, record.split, record.scene_id + GOLD_SUFFIX,
                                       record.seed, record.scenario, candidates, valid, record.logged,
                                       record.logged_valid, __version__, candidate_models=models,
                                       gold_answer=answer))
    return added
