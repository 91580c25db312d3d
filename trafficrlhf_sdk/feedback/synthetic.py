"""A stand-in annotator: the realism judgment of :mod:`~trafficrlhf_sdk.feedback.judgment` plus B-Pref-style
noise, labeling through the store API.

It stands in for people in tests, experiments and the main job; it is not a truth about realism. It judges only
what the annotation item shows (the map, every agent's history and the options' futures), never the logged future
of the agents it judges, so everything it decides on is visible to a reward model too. Several :data:`PROFILES`
weigh what they notice differently and make mistakes at different rates, so that their labels disagree as
people's do. A reward model can only learn what the judgment contains: a term it lacks is a blind spot that an
optimized policy will find.

**Noisy choice** (B-Pref, Lee et al. 2021, ``teacher_beta`` / ``teacher_eps_mistake`` / skip threshold):

1. if the best candidate's realism is at or below ``none_threshold``: answer "none realistic" (slot 0);
2. if every candidate's realism lies within ``tie_margin`` of the best and the campaign allows ties: answer
   "equally realistic";
3. with probability ``epsilon``: a mistake, one of the other candidates uniformly;
4. otherwise sample from ``softmax(beta * realism)`` over the candidates (``beta=None``: perfectly rational,
   the argmax).

Every draw comes from a generator seeded by (``seed``, annotator name, item id), so a labeling run is
reproducible whatever the order in which items are served.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable

import torch
from pydantic import Field

from trafficrlhf_sdk.feedback.judgment import JudgmentConfig, RealismJudgment, judge_scenarios
from trafficrlhf_sdk.feedback.records import TIE_SLOT
from trafficrlhf_sdk.feedback.store import Annotator, Campaign, ContextRecord, FeedbackStore
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["PROFILES", "SyntheticAnnotator", "SyntheticAnnotatorConfig", "annotator_generator", "judge_realism",
           "noisy_choice"]


class SyntheticAnnotatorConfig(JudgmentConfig):
    """The judgment's weights and bounds (:class:`~trafficrlhf_sdk.feedback.judgment.JudgmentConfig`) and the
    noise model."""

    beta: float | None = Field(
        20.0, gt=0, description="Rationality: inverse temperature on realism (0..1); None = always the argmax."
    )
    epsilon: float = Field(0.0, ge=0, le=1, description="Mistake rate: probability of picking another candidate.")
    none_threshold: float = Field(0.35, ge=0, le=1, description="Best realism at or below this: 'none realistic'.")
    skip_rate: float = Field(0.0, ge=0, le=1, description="Probability of skipping an item (tests the skip path).")
    seed: int = Field(0, description="Seed of every random draw.")
    tie_margin: float = Field(0.0, ge=0, le=1, description="Answer 'equally realistic' when every candidate's "
                              "realism is within this of the best (campaigns that allow ties); 0: never.")

    def judgment(self) -> JudgmentConfig:
        """The judgment's part of this configuration."""
        return JudgmentConfig(**{name: getattr(self, name) for name in JudgmentConfig.model_fields})


PROFILES: dict[str, SyntheticAnnotatorConfig] = {
    "attentive": SyntheticAnnotatorConfig(beta=40.0, epsilon=0.02, tie_margin=0.02),
    "safety": SyntheticAnnotatorConfig(beta=25.0, epsilon=0.05, weight_collision=6.0, weight_offroad=4.0,
                                       weight_tailgate=3.0, weight_accel=1.0, weight_jerk=0.5, weight_pace=1.0,
                                       tie_margin=0.03),
    "flow": SyntheticAnnotatorConfig(beta=25.0, epsilon=0.05, weight_pace=3.0, weight_stall=3.0, weight_stop_go=1.0,
                                     weight_lane=2.0, tie_margin=0.03),
    "hurried": SyntheticAnnotatorConfig(beta=10.0, epsilon=0.15, tie_margin=0.05),
}
"""Named stand-in annotators that weigh the judgment differently and err at different rates (so that their labels
disagree as people's do): ``attentive`` (few mistakes), ``safety`` (collisions, off-road and tailgating first),
``flow`` (pace, stalling, stop-and-go and lane keeping first) and ``hurried`` (noisy)."""


def judge_realism(record: ContextRecord, config: JudgmentConfig | None = None,
                  include_logged: bool = True) -> RealismJudgment:
    """Judge the N candidates of ``record`` (and, last, its logged future when ``include_logged``: an item that
    shows the log as an option) as a person watching the item would."""
    futures = [record.candidate_scenario(k) for k in range(record.num_candidates)]
    if include_logged:
        futures.append(record.candidate_scenario(None))
    batch = ScenarioTensor.concat(futures)
    return judge_scenarios(batch, record.controlled[None].expand(batch.num_scenes, -1), config)


def noisy_choice(realism: torch.Tensor, config: SyntheticAnnotatorConfig, generator: torch.Generator,
                 allow_tie: bool = False) -> int | None:
    """What an annotator with ``config``'s noise answers for an item whose options have realism ``(N,)``: the
    index chosen, None for "none realistic", or :data:`~trafficrlhf_sdk.feedback.schema.TIE_SLOT` for "equally
    realistic" (when ``allow_tie``); the steps of the module docstring, every draw from ``generator``."""
    if float(realism.max()) <= config.none_threshold:
        return None
    if allow_tie and config.tie_margin > 0 and float(realism.max() - realism.min()) <= config.tie_margin:
        return TIE_SLOT
    if config.beta is None:
        best = int(torch.argmax(realism))
    else:
        probs = torch.softmax(config.beta * realism.double(), 0)
        best = int(torch.multinomial(probs, 1, generator=generator))
    if config.epsilon > 0 and float(torch.rand((), generator=generator)) < config.epsilon:
        others = [k for k in range(len(realism)) if k != best]
        best = others[int(torch.randint(len(others), (), generator=generator))]
    return best


def annotator_generator(seed: int, name: str, item: object) -> torch.Generator:
    """The generator of annotator ``name``'s draws for ``item`` (an item id or key), seeded by all three."""
    digest = hashlib.sha256(f"{seed}:{name}:{item}".encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "big") >> 1)


class SyntheticAnnotator:
    """Labels items of a campaign like a person would, through :class:`FeedbackStore`.

    Args:
        store: the feedback database.
        name: the annotator's name (created on first use, like a person with a token).
        config: judgment and noise settings.
    """

    def __init__(self, store: FeedbackStore, name: str, config: SyntheticAnnotatorConfig | None = None) -> None:
        self.store = store
        self.config = config or SyntheticAnnotatorConfig()
        try:
            self.annotator: Annotator = store.annotator(name)
        except KeyError:
            self.annotator, _ = store.add_annotator(name)

    def _generator(self, context_id: int) -> torch.Generator:
        return annotator_generator(self.config.seed, self.annotator.name, context_id)

    def choose(self, realism: torch.Tensor, generator: torch.Generator, allow_tie: bool = False) -> int | None:
        """The candidate index chosen from realism scores ``(N,)``, None for "none realistic", or
        :data:`~trafficrlhf_sdk.feedback.schema.TIE_SLOT` for "equally realistic" (when ``allow_tie``)."""
        return noisy_choice(realism, self.config, generator, allow_tie)

    def label(self, campaign: Campaign | str, limit: int | None = None,
              on_label: Callable[[int, int | None], None] | None = None) -> dict[str, int]:
        """Label up to ``limit`` items (all that are left when None); returns counts of labels, none, ties, skips."""
        campaign = self.store.campaign(campaign) if isinstance(campaign, str) else campaign
        counts = {"labeled": 0, "none_realistic": 0, "ties": 0, "skipped": 0}
        while limit is None or counts["labeled"] + counts["skipped"] < limit:
            assignment = self.store.next_item(self.annotator, campaign)
            if assignment is None:
                break
            generator = self._generator(assignment.context_id)
            if self.config.skip_rate > 0 and float(torch.rand((), generator=generator)) < self.config.skip_rate:
                self.store.skip(self.annotator, campaign, assignment.context_id, "synthetic: random skip")
                counts["skipped"] += 1
                continue
            record = self.store.load_context(assignment.context_id, campaign)
            realism = judge_realism(record, self.config, include_logged=False).realism
            choice = self.choose(realism, generator, allow_tie=bool(getattr(campaign.settings, "allow_tie", False)))
            if choice == TIE_SLOT:
                slot = TIE_SLOT
            else:  # what a person would press
                slot = 0 if choice is None else assignment.permutation.index(choice) + 1
            self.store.submit_label(self.annotator, campaign, assignment.context_id, slot, source="synthetic")
            counts["labeled"] += 1
            counts["none_realistic"] += int(choice is None)
            counts["ties"] += int(choice == TIE_SLOT)
            if on_label is not None:
                on_label(assignment.context_id, choice)
        return counts
