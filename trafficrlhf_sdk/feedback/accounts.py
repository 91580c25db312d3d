"""Who may label and who owns campaigns: annotators and admins of a
:class:`~trafficrlhf_sdk.feedback.store.FeedbackStore`, each known by a token that is shown once and stored only as
its hash."""

from __future__ import annotations

import secrets
import sqlite3
from collections.abc import Callable
from contextlib import AbstractContextManager
from datetime import datetime, timezone
from typing import Any

from trafficrlhf_sdk.feedback.errors import (
    AuthenticationError,
    DuplicateSubmissionError,
    InvalidChoiceError,
    UnknownItemError,
)
from trafficrlhf_sdk.feedback.records import Annotator, Campaign, hash_token

__all__ = ["StoreAccounts"]


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


class StoreAccounts:
    """Annotator and admin accounts, mixed into :class:`~trafficrlhf_sdk.feedback.store.FeedbackStore`, whose
    connection (``_conn``) and write transactions (``transaction``) they use."""

    _conn: Callable[[], sqlite3.Connection]
    transaction: Callable[[], AbstractContextManager[Any]]

    # --------------------------------------------------------------------------------------- annotators
    def add_annotator(self, name: str) -> tuple[Annotator, str]:
        """Create annotator ``name``; returns it and its token (shown once: only its hash is stored)."""
        if not name or not name.strip() or len(name) > 100:
            raise InvalidChoiceError(f"annotator `name` must be 1-100 characters; got {name!r}.")
        token = secrets.token_urlsafe(24)
        with self.transaction() as tx:
            try:
                tx.execute("INSERT INTO annotators (name, token_sha256, created_at) VALUES (?, ?, ?)",
                           (name, hash_token(token), _now()))
            except sqlite3.IntegrityError as exc:
                raise DuplicateSubmissionError(
                    f"annotator {name!r} already exists; use `trafficrlhf feedback annotator token {name}` for a new "
                    "token."
                ) from exc
        return self.annotator(name), token

    def new_token(self, name: str) -> str:
        """Replace annotator ``name``'s token (the old one stops working), reactivate them, return the new one."""
        token = secrets.token_urlsafe(24)
        with self.transaction() as tx:
            if tx.execute("UPDATE annotators SET token_sha256 = ?, active = 1 WHERE name = ?",
                          (hash_token(token), name)).rowcount != 1:
                raise UnknownItemError(f"no annotator {name!r}; add one with `trafficrlhf feedback annotator add`.")
        return token

    def set_active(self, name: str, active: bool) -> Annotator:
        """(De)activate annotator ``name``. A deactivated token is refused, and the annotator's open items are
        released at once, so that others can take them."""
        with self.transaction() as tx:
            row = tx.execute("SELECT id FROM annotators WHERE name = ?", (name,)).fetchone()
            if row is None:
                raise UnknownItemError(f"no annotator {name!r}; add one with `trafficrlhf feedback annotator add`.")
            tx.execute("UPDATE annotators SET active = ? WHERE id = ?", (int(bool(active)), row["id"]))
            if not active:
                tx.execute("UPDATE assignments SET released = 1, lease_expires_at = NULL WHERE annotator_id = ? AND "
                           "lease_expires_at IS NOT NULL", (row["id"],))
        return self.annotator(name)

    def reset_qualification(self, name: str, campaign: Campaign) -> dict[str, int]:
        """Let annotator ``name`` take ``campaign``'s qualification again, e.g. after missing a gold item.

        Their gold answers (with their revisions), gold skips and gold-item assignments in ``campaign`` are
        removed, so the gold items are served again from the start and the status is ``"pending"``; labels of
        regular items are kept. Returns how many ``labels``, ``skips`` and ``assignments`` were removed."""
        with self.transaction() as tx:
            row = tx.execute("SELECT id FROM annotators WHERE name = ?", (name,)).fetchone()
            if row is None:
                raise UnknownItemError(f"no annotator {name!r}; add one with `trafficrlhf feedback annotator add`.")
            gold = ("SELECT id FROM contexts WHERE campaign_id = ? AND gold_answer IS NOT NULL")
            where = f"annotator_id = ? AND campaign_id = ? AND context_id IN ({gold})"
            args = (row["id"], campaign.id, campaign.id)
            tx.execute(f"DELETE FROM label_history WHERE label_id IN (SELECT id FROM labels WHERE {where})", args)
            counts = {table: tx.execute(f"DELETE FROM {table} WHERE {where}", args).rowcount
                      for table in ("labels", "skips", "assignments")}
        return counts

    def annotator(self, name: str) -> Annotator:
        """The annotator called ``name``."""
        row = self._conn().execute("SELECT * FROM annotators WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise UnknownItemError(f"no annotator {name!r}; add one with `trafficrlhf feedback annotator add {name}`.")
        return Annotator(row["id"], row["name"], row["created_at"], bool(row["active"]))

    def annotators(self) -> list[Annotator]:
        """Every annotator."""
        return [Annotator(r["id"], r["name"], r["created_at"], bool(r["active"]))
                for r in self._conn().execute("SELECT * FROM annotators ORDER BY id")]

    def authenticate(self, token: str | None) -> Annotator:
        """The active annotator holding ``token``; anything else raises :class:`AuthenticationError`."""
        if not token:
            raise AuthenticationError("missing annotator token: send the header 'Authorization: Bearer <token>'.")
        row = self._conn().execute("SELECT * FROM annotators WHERE token_sha256 = ? AND active = 1",
                                   (hash_token(token),)).fetchone()
        if row is None:
            raise AuthenticationError("unknown or revoked annotator token; ask for a new one "
                                      "(`trafficrlhf feedback annotator token NAME`).")
        return Annotator(row["id"], row["name"], row["created_at"], True)

    # ------------------------------------------------------------------------------------------- admins
    def add_admin(self, name: str) -> str:
        """Create (or re-key) campaign owner ``name`` and return their admin token (shown once, stored hashed)."""
        if not name or not name.strip() or len(name) > 100:
            raise InvalidChoiceError(f"admin `name` must be 1-100 characters; got {name!r}.")
        token = secrets.token_urlsafe(24)
        with self.transaction() as tx:
            tx.execute("INSERT INTO admins (name, token_sha256, created_at) VALUES (?, ?, ?) ON CONFLICT(name) DO "
                       "UPDATE SET token_sha256 = excluded.token_sha256", (name, hash_token(token), _now()))
        return token

    def authenticate_admin(self, token: str | None) -> str:
        """The name of the admin holding ``token``; anything else raises :class:`AuthenticationError`."""
        if not token:
            raise AuthenticationError("missing admin token: send the header 'Authorization: Bearer <admin token>'.")
        row = self._conn().execute("SELECT name FROM admins WHERE token_sha256 = ?", (hash_token(token),)).fetchone()
        if row is None:
            raise AuthenticationError("unknown admin token; create one with `trafficrlhf feedback admin NAME`.")
        return str(row["name"])

