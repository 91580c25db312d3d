"""Human feedback collection (stage I of TrafficRLHF).

A *campaign* holds K contexts (logged scenes), each with N candidate futures from one traffic model and the
hidden logged future (:mod:`~trafficrlhf_sdk.feedback.campaign`). People label them in the browser app (the
``trafficrlhf-annotation-web`` plugin) and a :class:`SyntheticAnnotator` can stand in for them; both go through
:class:`FeedbackStore` (one SQLite file). :func:`export_preferences` turns the labels into a
:class:`PreferenceDataset` for reward-model training.

Campaign quality (:mod:`~trafficrlhf_sdk.feedback.settings`): guidelines, gold items with a known answer
(:mod:`~trafficrlhf_sdk.feedback.gold`) and qualification, the play-once rule, leases that keep
``labels_per_item`` under concurrency, ties, several models per candidate set, and serving items by priority
(:mod:`~trafficrlhf_sdk.feedback.selection`, e.g. by reward-model disagreement).
"""

from trafficrlhf_sdk.lazy import lazy_exports

_EXPORTS = {
    "Annotator": "store",
    "Assignment": "store",
    "AuthenticationError": "errors",
    "Campaign": "store",
    "CampaignConfig": "campaign",
    "ContextRecord": "store",
    "DuplicateSubmissionError": "errors",
    "FeedbackError": "errors",
    "FeedbackStore": "store",
    "InvalidChoiceError": "errors",
    "ItemStateError": "errors",
    "Label": "store",
    "PreferenceDataset": "preference",
    "JudgmentConfig": "judgment",
    "RealismJudgment": "judgment",
    "SyntheticAnnotator": "synthetic",
    "SyntheticAnnotatorConfig": "synthetic",
    "UnknownCampaignError": "errors",
    "UnknownItemError": "errors",
    "agreement_report": "agreement",
    "campaign_agreement": "agreement",
    "create_campaign": "campaign",
    "export_preferences": "preference",
    "extend_campaign": "campaign",
    "fleiss_kappa": "agreement",
    "judge_realism": "synthetic",
    "judge_scenarios": "judgment",
    "agent_penalties": "judgment",
    "PROFILES": "synthetic",
    "TIE_SLOT": "records",
    "AnnotationSettings": "settings",
    "add_gold_items": "gold",
    "annotator_agreement": "agreement",
    "priorities_from_ranking": "selection",
    "rank_by_disagreement": "selection",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
