"""The stand-in annotator's judgment, for scoring a reward model against a noise-free annotator and as a reward.

A noise-free :class:`~trafficrlhf_sdk.feedback.SyntheticAnnotator` (``beta=None``, ``epsilon=0``) picks the
candidate of highest hidden realism. When several candidates are equally realistic (often: CTG candidates
without any collision, off-road or kinematic excess all score exactly 1) it still has to pick one, and the
pairs "pick ≻ equally good candidate" carry no preference. :func:`strict_pairs` marks the pairs whose winner
is strictly more realistic than the loser (by more than ``tolerance``), as B-Pref's "equal" teacher would.

:class:`JudgmentReward` (``builtin:judgment``) uses the judgment itself as the reward, per agent: the ceiling that
feedback from this annotator can give a fine-tuner, against which a reward model learned from its labels is
measured (the alignment ladder).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch

from trafficrlhf_sdk.feedback.preference import PreferenceDataset
from trafficrlhf_sdk.feedback.store import FeedbackStore
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.feedback.judgment import FAILURE_TERMS, STYLE_TERMS, agent_penalties
from trafficrlhf_sdk.feedback.synthetic import PROFILES, SyntheticAnnotatorConfig, judge_realism
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["AGREEMENT_GAPS", "JudgmentReward", "hidden_realism", "judged_pairs", "judgment_agreement",
           "strict_pairs"]

AGREEMENT_GAPS = (0.02, 0.05)
"""Realism gaps above which :func:`judgment_agreement` also reports agreement (``by_gap``)."""


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


def judged_pairs(dataset: PreferenceDataset, realism: torch.Tensor) -> PreferenceDataset:
    """``dataset``'s contexts labelled without noise: every pair of candidates whose ``realism`` (``(K, N + 1)``,
    from :func:`hidden_realism`) differs, the more realistic one preferred; the logged futures are left out.

    A reward model trained on these labels shows what its inputs and head can learn of the judgment; against the
    same model trained on annotators' choices it separates the loss to label noise from the loss to the inputs
    (docs/explanation/feedback-chain.md)."""
    n = dataset.futures.shape[1] - 1
    candidates = realism[:, :n]
    better = candidates[:, :, None] > candidates[:, None, :]  # (K, N, N): row beats column
    pairs = better.nonzero()  # (P, 3): context, winner, loser
    return replace(dataset, pairs=pairs, pair_annotator=torch.zeros(len(pairs), dtype=torch.long),
                   pair_label=pairs[:, 0] * (n * n) + pairs[:, 1] * n + pairs[:, 2], annotators=("judgment",),
                   pair_prob=None)


class JudgmentReward:
    """The stand-in's judgment as a reward (``builtin:judgment``), with the reward-model protocol.

    Each judged agent scores ``2 * exp(-penalty) - 1`` in (-1, 1], its penalty the judgment's weighted terms for
    that agent alone (its own failures at full weight, its own style terms); the scene's reward is the mean over
    the agents. It reads what an annotation item shows: the scenario's history up to ``current_index``, its map
    and its futures (see :mod:`~trafficrlhf_sdk.feedback.judgment`).

    Args:
        profile: the stand-in profile whose weights are used (:data:`~trafficrlhf_sdk.feedback.synthetic.PROFILES`).
    """

    def __init__(self, profile: str = "attentive") -> None:
        if profile not in PROFILES:
            raise TrafficRLHFError(f"`profile` is {profile!r}; use one of {', '.join(sorted(PROFILES))}.")
        self.config = PROFILES[profile]

    def agent_scores(self, scenario: ScenarioTensor) -> torch.Tensor:
        """``(B, A)`` per-agent rewards in (-1, 1]; 0 for agents not judged."""
        terms, agents = agent_penalties(scenario, scenario.controlled, self.config)
        penalty = sum(self.config.weight(name) * terms[name] for name in (*FAILURE_TERMS, *STYLE_TERMS))
        return torch.where(agents, 2 * torch.exp(-penalty) - 1, torch.zeros_like(penalty)).float()

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        """``(B, T)``: the scene's mean agent reward at every step after ``current_index`` (the judgment scores a
        whole window, not single steps)."""
        scores = self.agent_scores(scenario)
        agents = scenario.controlled & scenario.valid[:, :, scenario.current_index + 1:].any(-1)
        scene = (scores * agents).sum(-1) / agents.sum(-1).clamp_min(1)
        out = torch.zeros(scenario.valid.shape[0], scenario.num_steps)
        out[:, scenario.current_index + 1:] = scene[:, None]
        return out

    def score(self, scenario: ScenarioTensor) -> torch.Tensor:
        """``(B,)``: the mean reward of the judged agents (0 where none is judged)."""
        return self.step_rewards(scenario)[:, -1]


def judgment_agreement(reward: Any, store: FeedbackStore, campaign: str,
                       config: SyntheticAnnotatorConfig | None = None, tolerance: float = 0.0) -> dict[str, Any]:
    """How often ``reward`` (anything with ``score(scenario) -> (B,)``, or ``step_rewards``) orders two candidates
    of the same context as the noise-free stand-in does, over every pair of candidates of every context of
    ``campaign`` whose realism differs by more than ``tolerance`` (no labels needed). Returns ``agreement``, the
    number of ``pairs`` and ``contexts``; ``by_term``: per judgment term, the pairs that term decides (the one
    adding most to the loser's weighted penalty over the winner's) with their ``pairs`` and ``agreement``, so a
    shortfall names what the reward model does not see; and ``by_gap``: for each gap of :data:`AGREEMENT_GAPS`
    (keyed by its text), the ``pairs`` whose realism differs by more and their ``agreement``, so a shortfall on
    pairs a person would see differ is told from one on near ties."""
    from trafficrlhf_sdk.reward.scoring import scenario_scores

    judgment = (config or SyntheticAnnotatorConfig()).judgment()
    names = (*FAILURE_TERMS, *STYLE_TERMS)
    record_campaign = store.campaign(campaign)
    agree = pairs = contexts = 0
    tally = {name: [0, 0] for name in names}  # term -> [agreeing pairs, pairs]
    gaps = {threshold: [0, 0] for threshold in AGREEMENT_GAPS}  # threshold -> [agreeing pairs, pairs]
    for key in store.context_keys(record_campaign):
        record = store.load_context(int(key["id"]), record_campaign)
        judged = judge_realism(record, judgment, include_logged=False)
        batch = ScenarioTensor.concat([record.candidate_scenario(k) for k in range(record.num_candidates)])
        scores = scenario_scores(reward, batch).double()
        gap = judged.realism[:, None] - judged.realism[None, :]  # (N, N): row's realism over column's
        better = gap > tolerance  # row beats column
        if not better.any():
            continue
        contexts += 1
        pairs += int(better.sum())
        agreed = better & (scores[:, None] > scores[None, :])
        agree += int(agreed.sum())
        for threshold in AGREEMENT_GAPS:
            clear = gap > max(threshold, tolerance)
            gaps[threshold][0] += int((agreed & clear).sum())
            gaps[threshold][1] += int(clear.sum())
        weighted = torch.stack([judgment.weight(n) * judged.components[n].double() for n in names])  # (terms, N)
        decider = (weighted[:, None, :] - weighted[:, :, None]).argmax(0)  # (N, N): the loser's worst excess
        for n, name in enumerate(names):
            mine = better & (decider == n)
            tally[name][0] += int((agreed & mine).sum())
            tally[name][1] += int(mine.sum())
    by_term = {name: {"pairs": n, "agreement": ok / n} for name, (ok, n) in tally.items() if n}
    by_gap = {str(t): {"pairs": n, "agreement": ok / n if n else float("nan")} for t, (ok, n) in gaps.items()}
    return {"agreement": agree / pairs if pairs else float("nan"), "pairs": pairs, "contexts": contexts,
            "by_term": by_term, "by_gap": by_gap}
