"""Human feedback collection (stage I of TrafficRLHF).

A *campaign* holds K contexts (logged scenes), each with N candidate futures from one traffic model and the
hidden logged future (:mod:`~trafficrlhf_sdk.feedback.campaign`). People label them in the browser app (the
``trafficrlhf-annotation-web`` plugin) and a :class:`SyntheticAnnotator` can stand in for them; both go through
:class:`FeedbackStore` (one SQLite file). :func:`export_preferences` turns the labels into a
:class:`PreferenceDataset` for reward-model training.
"""

from trafficrlhf_sdk.feedback.agreement import agreement_report, campaign_agreement, fleiss_kappa
from trafficrlhf_sdk.feedback.campaign import CampaignConfig, create_campaign, extend_campaign
from trafficrlhf_sdk.feedback.errors import (
    AuthenticationError,
    DuplicateSubmissionError,
    FeedbackError,
    InvalidChoiceError,
    ItemStateError,
    UnknownCampaignError,
    UnknownItemError,
)
from trafficrlhf_sdk.feedback.preference import PreferenceDataset, export_preferences
from trafficrlhf_sdk.feedback.store import Annotator, Assignment, Campaign, ContextRecord, FeedbackStore, Label
from trafficrlhf_sdk.feedback.synthetic import (
    RealismJudgment,
    SyntheticAnnotator,
    SyntheticAnnotatorConfig,
    judge_realism,
)

__all__ = [
    "Annotator",
    "Assignment",
    "AuthenticationError",
    "Campaign",
    "CampaignConfig",
    "ContextRecord",
    "DuplicateSubmissionError",
    "FeedbackError",
    "FeedbackStore",
    "InvalidChoiceError",
    "ItemStateError",
    "Label",
    "PreferenceDataset",
    "RealismJudgment",
    "SyntheticAnnotator",
    "SyntheticAnnotatorConfig",
    "UnknownCampaignError",
    "UnknownItemError",
    "agreement_report",
    "campaign_agreement",
    "create_campaign",
    "export_preferences",
    "extend_campaign",
    "fleiss_kappa",
    "judge_realism",
]
