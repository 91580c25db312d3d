"""Errors of the feedback store. Each maps to one HTTP status in the annotation app (given in brackets)."""

from __future__ import annotations

from trafficrlhf_sdk.errors import TrafficRLHFError, UnknownComponentError

__all__ = [
    "AuthenticationError",
    "DuplicateSubmissionError",
    "FeedbackError",
    "InvalidChoiceError",
    "ItemStateError",
    "UnknownCampaignError",
    "UnknownItemError",
]


class FeedbackError(TrafficRLHFError):
    """Base class of the feedback store's errors."""

    http_status = 400


class AuthenticationError(FeedbackError):
    """A missing, unknown or revoked annotator token [401]."""

    http_status = 401


class UnknownCampaignError(FeedbackError, UnknownComponentError):
    """No campaign of that name in the database [404]."""

    http_status = 404


class UnknownItemError(FeedbackError, UnknownComponentError):
    """No item (context) of that id in the campaign [404]."""

    http_status = 404


class DuplicateSubmissionError(FeedbackError):
    """The annotator already labeled this item; revise it explicitly instead [409]."""

    http_status = 409


class ItemStateError(FeedbackError):
    """The request does not fit the item's state, e.g. a label for an item never opened [409]."""

    http_status = 409


class InvalidChoiceError(FeedbackError, ValueError):
    """A choice outside 0..N, or an empty skip reason [422]."""

    http_status = 422
