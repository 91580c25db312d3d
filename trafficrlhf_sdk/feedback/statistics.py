"""What a campaign owner reads from a :class:`~trafficrlhf_sdk.feedback.store.FeedbackStore`: per-annotator gold
accuracy and qualification, per-annotator statistics, an annotator's progress and a campaign's counts."""

from __future__ import annotations

import time
from typing import Any

from trafficrlhf_sdk.feedback.records import TIE_SLOT, Annotator, Campaign

__all__ = ["SQLITE_MAX_INT", "StoreStatistics"]

SQLITE_MAX_INT = 2**63 - 1  # ids above this cannot be stored (nor looked up) by SQLite


class StoreStatistics:
    """Read-only figures mixed into :class:`~trafficrlhf_sdk.feedback.store.FeedbackStore`, whose connection
    (``_conn``, ``snapshot``) and ``annotators`` they use."""

    _conn: Any
    snapshot: Any
    annotators: Any

    # ------------------------------------------------------------------------------------------ quality
    def quality(self, annotator: Annotator, campaign: Campaign) -> dict[str, Any]:
        """The annotator's gold figures in ``campaign``.

        Returns ``gold_answered``, ``gold_correct``, ``gold_accuracy`` (None before any gold answer), and
        ``status``: ``"none"`` (no qualification asked), ``"pending"`` (fewer than N gold answers),
        ``"passed"`` or ``"failed"`` (judged on the first N gold answers against ``qualification_accuracy``).
        A tie or "none realistic" on a gold item counts as wrong.
        """
        with self.snapshot() as conn:
            return self._quality(conn, annotator, campaign)

    @staticmethod
    def _quality(conn: Any, annotator: Annotator | int, campaign: Campaign) -> dict[str, Any]:
        annotator_id = annotator if isinstance(annotator, int) else annotator.id
        rows = conn.execute(
            "SELECT l.candidate IS NOT NULL AND l.candidate = c.gold_answer FROM labels l JOIN contexts c ON c.id = "
            "l.context_id WHERE l.annotator_id = ? AND l.campaign_id = ? AND c.gold_answer IS NOT NULL ORDER BY l.id",
            (annotator_id, campaign.id)).fetchall()
        right = [bool(r[0]) for r in rows]
        settings = campaign.settings
        n = settings.qualification_gold
        if n == 0:
            status = "none"
        elif len(right) < n:
            status = "pending"
        else:
            status = "passed" if sum(right[:n]) >= settings.qualification_accuracy * n - 1e-9 else "failed"
        return {"gold_answered": len(right), "gold_correct": sum(right),
                "gold_accuracy": sum(right) / len(right) if right else None, "status": status,
                "qualification_gold": n}

    def annotator_stats(self, campaign: Campaign) -> list[dict[str, Any]]:
        """Per annotator who worked on ``campaign`` (or is active): labels, skips, ties, 'none', open items,
        gold figures and qualification status, and the median time per label (ms)."""
        conn = self._conn()
        out = []
        for a in self.annotators():
            rows = conn.execute(
                "SELECT l.slot, l.time_on_item_ms FROM labels l JOIN contexts c ON c.id = l.context_id WHERE "
                "l.annotator_id = ? AND l.campaign_id = ? AND c.gold_answer IS NULL", (a.id, campaign.id)).fetchall()
            skips = conn.execute("SELECT COUNT(*) FROM skips WHERE annotator_id = ? AND campaign_id = ?",
                                 (a.id, campaign.id)).fetchone()[0]
            leases = conn.execute(
                "SELECT COUNT(*) FROM assignments WHERE annotator_id = ? AND campaign_id = ? AND released = 0 AND "
                "lease_expires_at > ?", (a.id, campaign.id, time.time())).fetchone()[0]
            times = sorted(r[1] for r in rows if r[1] is not None)
            out.append({"annotator": a.name, "active": a.active, "labels": len(rows), "skips": skips,
                        "ties": sum(r[0] == TIE_SLOT for r in rows), "none_realistic": sum(r[0] == 0 for r in rows),
                        "open_items": leases, "median_time_ms": times[len(times) // 2] if times else None,
                        **self._quality(conn, a, campaign)})
        return out

    # ----------------------------------------------------------------------------------------- progress
    def progress(self, annotator: Annotator, campaign: Campaign) -> dict[str, int]:
        """``labeled``, ``skipped``, ``done`` and ``total``: the items assigned to the annotator plus those still
        open to them (below ``labels_per_item``; items others hold right now are counted as open)."""
        with self.snapshot() as conn:
            labeled = conn.execute("SELECT COUNT(*) FROM labels WHERE annotator_id = ? AND campaign_id = ?",
                                   (annotator.id, campaign.id)).fetchone()[0]
            skipped = conn.execute("SELECT COUNT(*) FROM skips WHERE annotator_id = ? AND campaign_id = ?",
                                   (annotator.id, campaign.id)).fetchone()[0]
            assigned = conn.execute("SELECT COUNT(*) FROM assignments WHERE annotator_id = ? AND campaign_id = ? AND "
                                    "released = 0", (annotator.id, campaign.id)).fetchone()[0]
            cap = SQLITE_MAX_INT if campaign.labels_per_item is None else campaign.labels_per_item
            open_items = conn.execute("SELECT COUNT(*) FROM contexts INDEXED BY contexts_queue WHERE campaign_id = ? "
                                      "AND gold_answer IS NULL AND labels_n < ?", (campaign.id, cap)).fetchone()[0]
            seen = conn.execute("SELECT COUNT(*) FROM assignments a JOIN contexts c ON c.id = a.context_id WHERE "
                                "a.annotator_id = ? AND a.campaign_id = ? AND c.gold_answer IS NULL AND c.labels_n < ?",
                                (annotator.id, campaign.id, cap)).fetchone()[0]
        return {"labeled": labeled, "skipped": skipped, "done": labeled + skipped,
                "total": assigned + open_items - seen}

    def counts(self, campaign: Campaign) -> dict[str, int]:
        """Regular items, labels (ties and 'none realistic' among them), skips, distinct annotators, gold items,
        items that reached ``labels_per_item`` and items over it (0 unless the cap was lowered)."""
        conn = self._conn()

        def one(sql: str) -> int:
            return int(conn.execute(sql, (campaign.id,)).fetchone()[0])

        regular = ("AND context_id IN (SELECT id FROM contexts WHERE campaign_id = l.campaign_id AND gold_answer IS "
                   "NULL)")
        per_item = (f"SELECT context_id, COUNT(*) AS n FROM labels l WHERE campaign_id = ? {regular} "
                    "GROUP BY context_id")
        cap = campaign.labels_per_item
        return {
            "items": one("SELECT COUNT(*) FROM contexts WHERE campaign_id = ? AND gold_answer IS NULL"),
            "labels": one(f"SELECT COUNT(*) FROM labels l WHERE campaign_id = ? {regular}"),
            "none_realistic": one(f"SELECT COUNT(*) FROM labels l WHERE campaign_id = ? AND slot = 0 {regular}"),
            "ties": one(f"SELECT COUNT(*) FROM labels l WHERE campaign_id = ? AND slot = {TIE_SLOT} {regular}"),
            "skips": one("SELECT COUNT(*) FROM skips WHERE campaign_id = ?"),
            "annotators": one(f"SELECT COUNT(DISTINCT annotator_id) FROM labels l WHERE campaign_id = ? {regular}"),
            "gold_items": one("SELECT COUNT(*) FROM contexts WHERE campaign_id = ? AND gold_answer IS NOT NULL"),
            "items_complete": 0 if cap is None else one(f"SELECT COUNT(*) FROM ({per_item}) WHERE n >= {int(cap)}"),
            "items_over_cap": 0 if cap is None else one(f"SELECT COUNT(*) FROM ({per_item}) WHERE n > {int(cap)}"),
        }
