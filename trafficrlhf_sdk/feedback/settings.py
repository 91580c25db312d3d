"""Per-campaign annotation settings: playback, guidelines, gold items, qualification, leases, ties.

They are stored with the campaign (``config["annotation"]`` in the database) and can be changed while the
campaign runs (``trafficrlhf feedback settings`` or the app's admin page); a campaign stored without them
gets the defaults below.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["MAX_GUIDELINES_CHARS", "AnnotationSettings"]

MAX_GUIDELINES_CHARS = 50_000


class AnnotationSettings(BaseModel):
    """How a campaign is annotated."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    playback_required: bool = Field(
        True, description="A choice is accepted only once the future has played through (the page blocks the "
                          "keys until then, and the server refuses labels sent sooner than the playback at 2x "
                          "speed would take after the item was first served).")
    guidelines: str | None = Field(
        None, max_length=MAX_GUIDELINES_CHARS,
        description="Markdown guidelines shown at sign-in (and again whenever they change) and on demand.")
    gold_rate: float = Field(
        0.0, ge=0.0, le=0.5, description="Share of the items served after qualification that are gold items "
                                         "(known answer), e.g. 0.1 for one in ten.")
    qualification_gold: int = Field(
        0, ge=0, le=100, description="N: gold items an annotator answers first; their labels count (are served "
                                     "regular items, and exported) only once they pass them.")
    qualification_accuracy: float = Field(
        0.8, ge=0.0, le=1.0, description="Share of the N qualification gold items that must be answered right.")
    lease_seconds: float = Field(
        600.0, gt=0, le=86_400, description="How long an opened item stays reserved for its annotator when the "
                                            "campaign has labels_per_item; afterwards others may take it.")
    allow_tie: bool = Field(
        True, description="Offer 'equally realistic' (key E): recorded as a tie, exported as no pair or as "
                          "soft 0.5 pairs (`export_preferences(ties=...)`).")

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> AnnotationSettings:
        """The settings stored in a campaign's config (defaults for a campaign stored without them)."""
        return cls(**(config.get("annotation") or {}))
