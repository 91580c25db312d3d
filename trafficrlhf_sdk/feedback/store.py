"""The feedback database: one SQLite file holding campaigns, their items and every annotation.

Both the browser app and the :class:`~trafficrlhf_sdk.feedback.synthetic.SyntheticAnnotator` go through this
API, so a synthetic campaign exercises exactly the code paths people use.

Durability: the file runs in WAL mode (readers never block the writer) with ``synchronous=FULL`` by default, and
every write is one ``BEGIN IMMEDIATE`` transaction: a crash (even ``kill -9``) leaves either the whole write or
none of it, and a write that returned has reached the file. Connections are per thread, so the store can be
shared by the threads of a web server.

The tables and their columns: :mod:`trafficrlhf_sdk.feedback.schema`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import random
import secrets
import sqlite3
import threading
import time
from dataclasses import replace
from datetime import datetime, timezone
from collections.abc import Iterator
from typing import Any, Literal

import torch

from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.feedback.errors import (
    AuthenticationError,
    DuplicateSubmissionError,
    InvalidChoiceError,
    ItemStateError,
    UnknownCampaignError,
    UnknownItemError,
)
from trafficrlhf_sdk.feedback.records import (
    TIE_SLOT,
    Annotator,
    Assignment,
    Campaign,
    ContextRecord,
    Label,
    _assignment,
    _campaign,
    _label,
    decode_future,
    encode_future,
    hash_token,
)
from trafficrlhf_sdk.feedback.schema import SCHEMA_SQL, SCHEMA_VERSION, migrate
from trafficrlhf_sdk.feedback.settings import AnnotationSettings
from trafficrlhf_sdk.scenario.io import scenario_from_bytes, scenario_to_bytes
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["SCHEMA_VERSION", "TIE_SLOT", "Annotator", "Assignment", "Campaign", "ContextRecord", "FeedbackStore",
           "Label", "SQLITE_MAX_INT"]

MAX_REASON_CHARS = 500
SQLITE_MAX_INT = 2**63 - 1  # ids above this cannot be stored (nor looked up) by SQLite
Synchronous = Literal["OFF", "NORMAL", "FULL", "EXTRA"]
LabelKind = Literal["regular", "gold", "all"]


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


# -------------------------------------------------------------------------------------------------- store
class FeedbackStore:
    """Campaigns, items, annotators and labels in one SQLite file.

    Args:
        path: the database file; created with its schema when missing.
        timeout_s: how long a writer waits for the lock held by another writer before failing (s).
        synchronous: SQLite's ``synchronous`` level. ``FULL`` (default) makes each committed write survive a
            power loss; ``NORMAL`` is faster and still survives a crash of the process.
    """

    def __init__(self, path: str | os.PathLike[str], timeout_s: float = 30.0,
                 synchronous: Synchronous = "FULL") -> None:
        if synchronous not in ("OFF", "NORMAL", "FULL", "EXTRA"):
            raise ValueError(f"`synchronous` must be OFF, NORMAL, FULL or EXTRA; got {synchronous!r}.")
        self.path = os.fspath(path)
        parent = os.path.dirname(os.path.abspath(self.path))
        if not os.path.isdir(parent):
            raise FileNotFoundError(f"directory of the feedback database does not exist: {parent!r}; create it first.")
        self.timeout_s = timeout_s
        self.synchronous = synchronous
        self._local = threading.local()
        self._all: list[sqlite3.Connection] = []
        self._lock = threading.Lock()
        conn = self._conn()
        conn.execute("PRAGMA journal_mode=WAL")
        with self.transaction() as tx:
            version = tx.execute("PRAGMA user_version").fetchone()[0]
            if version not in (0, 1, SCHEMA_VERSION):
                raise DataFormatError(
                    f"{self.path!r} has feedback schema version {version}; this SDK reads versions 1 to "
                    f"{SCHEMA_VERSION}. Upgrade the SDK to open it."
                )
            migrate(tx.execute, version)
            tx.executescript_safe(SCHEMA_SQL)
            tx.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")

    # ------------------------------------------------------------------------ connections, transactions
    def _conn(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = sqlite3.connect(self.path, timeout=self.timeout_s, isolation_level=None, check_same_thread=False)
            conn.row_factory = sqlite3.Row
            conn.execute(f"PRAGMA busy_timeout = {int(self.timeout_s * 1000)}")
            conn.execute(f"PRAGMA synchronous = {self.synchronous}")
            conn.execute("PRAGMA foreign_keys = ON")
            self._local.conn = conn
            with self._lock:
                self._all.append(conn)
        return conn

    @contextlib.contextmanager
    def transaction(self) -> Iterator[_Tx]:
        """A write transaction (``BEGIN IMMEDIATE``): committed on exit, rolled back on any exception."""
        conn = self._conn()
        conn.execute("BEGIN IMMEDIATE")
        try:
            yield _Tx(conn)
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        conn.execute("COMMIT")

    @contextlib.contextmanager
    def snapshot(self) -> Iterator[sqlite3.Connection]:
        """A read transaction: every query inside sees the same state of the database."""
        conn = self._conn()
        conn.execute("BEGIN")
        try:
            yield conn
        finally:
            conn.execute("COMMIT")

    def close(self) -> None:
        """Close every connection this store opened (in any thread)."""
        with self._lock:
            for conn in self._all:
                with contextlib.suppress(sqlite3.Error):
                    conn.close()
            self._all.clear()
        self._local = threading.local()

    def __enter__(self) -> FeedbackStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------------------------------- campaigns
    def create_campaign(self, name: str, model: str, guidance: str | None, seed: int, num_candidates: int,
                        config: dict[str, Any], sdk_version: str) -> Campaign:
        """Insert a campaign; an existing name raises ``DuplicateSubmissionError`` (extend it instead)."""
        if not name or not name.strip():
            raise InvalidChoiceError("campaign `name` must be a non-empty string.")
        with self.transaction() as tx:
            try:
                tx.execute(
                    "INSERT INTO campaigns (name, created_at, model, guidance, seed, num_candidates, sdk_version, "
                    "config_json) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    (name, _now(), model, guidance, seed, num_candidates, sdk_version, json.dumps(config)),
                )
            except sqlite3.IntegrityError as exc:
                raise DuplicateSubmissionError(
                    f"campaign {name!r} already exists in {self.path!r}; pass --extend to add contexts to it."
                ) from exc
        return self.campaign(name)

    def campaign(self, name_or_id: str | int) -> Campaign:
        """The campaign called ``name_or_id`` (or with that id)."""
        column = "id" if isinstance(name_or_id, int) else "name"
        row = self._conn().execute(f"SELECT * FROM campaigns WHERE {column} = ?", (name_or_id,)).fetchone()
        if row is None:
            known = [c.name for c in self.campaigns()]
            raise UnknownCampaignError(f"no campaign {name_or_id!r} in {self.path!r}; campaigns there: {known}.")
        return _campaign(row)

    def campaigns(self) -> list[Campaign]:
        """Every campaign, oldest first."""
        return [_campaign(r) for r in self._conn().execute("SELECT * FROM campaigns ORDER BY id")]

    def update_settings(self, campaign: Campaign | str, **changes: Any) -> Campaign:
        """Change some of the campaign's :class:`AnnotationSettings` (validated; the others are kept)."""
        name = campaign if isinstance(campaign, str) else campaign.name
        with self.transaction() as tx:
            row = tx.execute("SELECT config_json FROM campaigns WHERE name = ?", (name,)).fetchone()
            if row is None:
                raise UnknownCampaignError(f"no campaign {name!r} in {self.path!r}.")
            config = json.loads(row["config_json"])
            try:
                settings = AnnotationSettings(**{**(config.get("annotation") or {}), **changes})
            except ValueError as exc:
                raise InvalidChoiceError(f"invalid settings for campaign {name!r}: {exc}") from exc
            config["annotation"] = settings.model_dump(mode="json")
            tx.execute("UPDATE campaigns SET config_json = ? WHERE name = ?", (json.dumps(config), name))
        return self.campaign(name)

    def set_priorities(self, campaign: Campaign, priorities: dict[int, float]) -> int:
        """Serve items with higher ``priorities[context_id]`` first (others keep theirs; default 0).

        This is the hook for active selection: score each context, e.g. by how much an ensemble of reward
        models disagrees on its candidates (:func:`~trafficrlhf_sdk.feedback.selection.rank_by_disagreement`),
        and pass the scores here. Returns how many items were updated; unknown ids raise ``UnknownItemError``.
        """
        with self.transaction() as tx:
            known = {r[0] for r in tx.execute("SELECT id FROM contexts WHERE campaign_id = ?", (campaign.id,))}
            missing = sorted(set(priorities) - known)
            if missing:
                raise UnknownItemError(f"no items {missing[:10]} in campaign {campaign.name!r}; nothing was changed.")
            tx.executemany("UPDATE contexts SET priority = ? WHERE id = ?",
                           [(float(v), int(k)) for k, v in priorities.items()])
        return len(priorities)

    # ----------------------------------------------------------------------------------------- contexts
    def add_context(self, campaign: Campaign, source: str, split: str, scene_id: str, seed: int,
                    scenario: ScenarioTensor, candidates: torch.Tensor, candidate_valid: torch.Tensor,
                    logged: torch.Tensor, logged_valid: torch.Tensor, sdk_version: str,
                    candidate_models: list[str] | tuple[str, ...] | None = None, gold_answer: int | None = None,
                    priority: float = 0.0) -> int:
        """Store one item (context + N candidates + logged future) in one transaction; returns its id.

        Shapes: ``scenario`` B = 1 with ``current_index`` = the start step; ``candidates (N, A, H, 4)``,
        ``candidate_valid (N, A, H)``, ``logged (A, H, 4)``, ``logged_valid (A, H)``. ``candidate_models``: the
        traffic model of each candidate (default: the campaign's model for all). ``gold_answer``: makes the item
        a gold item whose right answer is that candidate index (see :mod:`~trafficrlhf_sdk.feedback.gold`).
        """
        n = int(candidates.shape[0])
        if n != campaign.num_candidates:
            raise InvalidChoiceError(f"campaign {campaign.name!r} takes {campaign.num_candidates} candidates; got {n}.")
        models = list(candidate_models) if candidate_models is not None else [campaign.model] * n
        if len(models) != n:
            raise InvalidChoiceError(f"`candidate_models` must name one model per candidate ({n}); got {models!r}.")
        if gold_answer is not None and not 0 <= gold_answer < n:
            raise InvalidChoiceError(f"`gold_answer` must be a candidate index 0..{n - 1}; got {gold_answer!r}.")
        a = scenario.num_agents
        if (scenario.num_scenes != 1 or candidates.dim() != 4 or tuple(candidates.shape[1:2]) != (a,)
                or tuple(candidate_valid.shape) != tuple(candidates.shape[:3])
                or tuple(logged.shape) != tuple(candidates.shape[1:])
                or tuple(logged_valid.shape) != tuple(logged.shape[:2])):
            raise InvalidChoiceError(
                f"item shapes do not fit: scenario {tuple(scenario.states.shape)} (B must be 1), candidates "
                f"{tuple(candidates.shape)} / valid {tuple(candidate_valid.shape)} (expected (N, {a}, H, 4) / "
                f"(N, {a}, H)),"
                f" logged {tuple(logged.shape)} / valid {tuple(logged_valid.shape)} (expected ({a}, H, 4) / ({a}, H))."
            )
        blob = scenario_to_bytes(scenario)
        futures = [encode_future(candidates[k], candidate_valid[k]) for k in range(n)]
        with self.transaction() as tx:
            ordinal = tx.execute("SELECT COALESCE(MAX(ordinal), -1) + 1 FROM contexts WHERE campaign_id = ?",
                                 (campaign.id,)).fetchone()[0]
            try:
                cur = tx.execute(
                    "INSERT INTO contexts (campaign_id, ordinal, source, split, scene_id, seed, start_index, "
                    "created_at, sdk_version, scenario, gold_answer, priority) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, "
                    "?, ?)",
                    (campaign.id, ordinal, source, split, scene_id, seed, scenario.current_index, _now(), sdk_version,
                     blob, gold_answer, float(priority)),
                )
            except sqlite3.IntegrityError as exc:
                raise DuplicateSubmissionError(
                    f"campaign {campaign.name!r} already holds scene {source}/{split}/{scene_id}."
                ) from exc
            context_id = int(cur.lastrowid)  # type: ignore[arg-type]
            rows = [(context_id, k, "model", futures[k], models[k]) for k in range(n)]
            rows.append((context_id, -1, "logged", encode_future(logged, logged_valid), None))
            tx.executemany("INSERT INTO candidates (context_id, idx, kind, tensors, model) VALUES (?, ?, ?, ?, ?)",
                           rows)
        return context_id

    def context_keys(self, campaign: Campaign) -> list[dict[str, Any]]:
        """``id, ordinal, source, split, scene_id, seed, gold_answer, priority`` of every item of ``campaign``, by
        ordinal (``gold_answer`` is None for regular items)."""
        rows = self._conn().execute(
            "SELECT id, ordinal, source, split, scene_id, seed, gold_answer, priority FROM contexts WHERE "
            "campaign_id = ? ORDER BY ordinal", (campaign.id,))
        return [dict(r) for r in rows]

    def load_context(self, context_id: int, campaign: Campaign | None = None) -> ContextRecord:
        """The item ``context_id`` with its tensors; ``campaign`` restricts the lookup to that campaign."""
        _check_id(context_id, "item")
        with self.snapshot() as conn:
            row = conn.execute("SELECT * FROM contexts WHERE id = ?", (context_id,)).fetchone()
            if row is None or (campaign is not None and row["campaign_id"] != campaign.id):
                where = f"campaign {campaign.name!r}" if campaign is not None else repr(self.path)
                raise UnknownItemError(f"no item {context_id!r} in {where}; see `trafficrlhf feedback status`.")
            futures = conn.execute("SELECT idx, tensors, model FROM candidates WHERE context_id = ? ORDER BY idx",
                                   (context_id,)).fetchall()
        name = f"item {context_id}"
        scenario = scenario_from_bytes(row["scenario"], name)
        decoded = {r["idx"]: decode_future(r["tensors"], f"{name} candidate {r['idx']}") for r in futures}
        if -1 not in decoded or len(decoded) < 3:
            raise DataFormatError(f"{name} of {self.path!r} lacks its candidates; the database is incomplete.")
        model = [decoded[k] for k in sorted(k for k in decoded if k >= 0)]
        return ContextRecord(
            id=row["id"], campaign_id=row["campaign_id"], ordinal=row["ordinal"], source=row["source"],
            split=row["split"], scene_id=row["scene_id"], seed=row["seed"], start_index=row["start_index"],
            scenario=scenario, candidates=torch.stack([s for s, _ in model]),
            candidate_valid=torch.stack([v for _, v in model]), logged=decoded[-1][0], logged_valid=decoded[-1][1],
            candidate_models=tuple(r["model"] for r in futures if r["idx"] >= 0), gold_answer=row["gold_answer"],
            priority=float(row["priority"]),
        )

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
        """Replace annotator ``name``'s token (the old one stops working) and return the new one."""
        token = secrets.token_urlsafe(24)
        with self.transaction() as tx:
            if tx.execute("UPDATE annotators SET token_sha256 = ?, active = 1 WHERE name = ?",
                          (hash_token(token), name)).rowcount != 1:
                raise UnknownItemError(f"no annotator {name!r}; add one with `trafficrlhf feedback annotator add`.")
        return token

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

    # -------------------------------------------------------------------------------------- assignments
    def next_item(self, annotator: Annotator, campaign: Campaign) -> Assignment | None:
        """The annotator's open item (resume), else a new one; None when nothing is left for them.

        New items: those the annotator has not seen, fewest labels first (only items below the campaign's
        ``labels_per_item``, if set), in an order shuffled per annotator.
        """
        with self.transaction() as tx:
            open_row = tx.execute(
                "SELECT a.* FROM assignments a WHERE a.annotator_id = ? AND a.campaign_id = ? AND NOT EXISTS "
                "(SELECT 1 FROM labels l WHERE l.context_id = a.context_id AND l.annotator_id = a.annotator_id) "
                "AND NOT EXISTS (SELECT 1 FROM skips s WHERE s.context_id = a.context_id AND s.annotator_id = "
                "a.annotator_id) ORDER BY a.position LIMIT 1", (annotator.id, campaign.id)).fetchone()
            if open_row is not None:
                return _assignment(open_row)
            rows = tx.execute(
                "SELECT c.id, (SELECT COUNT(*) FROM labels l WHERE l.context_id = c.id) AS n FROM contexts c "
                "WHERE c.campaign_id = ? AND NOT EXISTS (SELECT 1 FROM assignments a WHERE a.context_id = c.id AND "
                "a.annotator_id = ?)", (campaign.id, annotator.id)).fetchall()
            cap = campaign.labels_per_item
            pool = [(r["n"], _shuffle_key(campaign.seed, annotator.id, r["id"]), r["id"]) for r in rows
                    if cap is None or r["n"] < cap]
            if not pool:
                return None
            context_id = min(pool)[2] if cap is not None else min(pool, key=lambda p: p[1])[2]
            return self._assign(tx, annotator, campaign, context_id)

    def open_item(self, annotator: Annotator, campaign: Campaign, context_id: int) -> Assignment:
        """The annotator's assignment of item ``context_id``, created (with its permutation) on first open."""
        with self.transaction() as tx:
            row = tx.execute("SELECT * FROM assignments WHERE annotator_id = ? AND context_id = ?",
                             (annotator.id, context_id)).fetchone()
            if row is not None:
                if row["campaign_id"] != campaign.id:
                    raise UnknownItemError(f"no item {context_id!r} in campaign {campaign.name!r}.")
                return self._with_status(tx, _assignment(row))
            exists = tx.execute("SELECT 1 FROM contexts WHERE id = ? AND campaign_id = ?",
                                (context_id, campaign.id)).fetchone()
            if exists is None:
                raise UnknownItemError(f"no item {context_id!r} in campaign {campaign.name!r}.")
            return self._assign(tx, annotator, campaign, context_id)

    def _assign(self, tx: _Tx, annotator: Annotator, campaign: Campaign, context_id: int) -> Assignment:
        position = tx.execute("SELECT COALESCE(MAX(position), 0) + 1 FROM assignments WHERE annotator_id = ? AND "
                              "campaign_id = ?", (annotator.id, campaign.id)).fetchone()[0]
        permutation = list(range(campaign.num_candidates))
        random.Random(_shuffle_key(campaign.seed, annotator.id, context_id, "perm")).shuffle(permutation)
        now = _now()
        cur = tx.execute(
            "INSERT INTO assignments (annotator_id, context_id, campaign_id, position, permutation, assigned_at) "
            "VALUES (?, ?, ?, ?, ?, ?)",
            (annotator.id, context_id, campaign.id, position, json.dumps(permutation), now))
        return Assignment(int(cur.lastrowid), annotator.id, context_id, campaign.id, position,  # type: ignore[arg-type]
                          tuple(permutation), now)

    def _with_status(self, conn: _Tx | sqlite3.Connection, assignment: Assignment) -> Assignment:
        label = conn.execute("SELECT slot FROM labels WHERE context_id = ? AND annotator_id = ?",
                             (assignment.context_id, assignment.annotator_id)).fetchone()
        if label is not None:
            return _replace(assignment, status="labeled", slot=label["slot"])
        skip = conn.execute("SELECT reason FROM skips WHERE context_id = ? AND annotator_id = ?",
                            (assignment.context_id, assignment.annotator_id)).fetchone()
        if skip is not None:
            return _replace(assignment, status="skipped", skip_reason=skip["reason"])
        return assignment

    def history(self, annotator: Annotator, campaign: Campaign) -> list[Assignment]:
        """The annotator's assignments in ``campaign`` in the order shown, each with its status."""
        with self.snapshot() as conn:
            rows = conn.execute("SELECT * FROM assignments WHERE annotator_id = ? AND campaign_id = ? ORDER BY "
                                "position", (annotator.id, campaign.id)).fetchall()
            return [self._with_status(conn, _assignment(r)) for r in rows]

    # ------------------------------------------------------------------------------------ labels, skips
    def submit_label(self, annotator: Annotator, campaign: Campaign, context_id: int, slot: int,
                     time_on_item_ms: int | None = None, source: str = "human", revise: bool = False) -> Label:
        """Record the annotator's choice for item ``context_id``: ``slot`` 1..N (as shown) or 0 (none realistic).

        The item must have been opened (its permutation fixed). A second submission raises
        :class:`DuplicateSubmissionError` and writes nothing, unless ``revise`` (the old value then goes to
        ``label_history``). A label replaces a skip of the same item.
        """
        if isinstance(slot, bool) or not isinstance(slot, int) or not 0 <= slot <= campaign.num_candidates:
            raise InvalidChoiceError(
                f"`choice` must be an integer from 0 (none realistic) to {campaign.num_candidates}; got {slot!r}."
            )
        if time_on_item_ms is not None and (not isinstance(time_on_item_ms, int) or time_on_item_ms < 0):
            raise InvalidChoiceError(f"`time_ms` must be a non-negative integer; got {time_on_item_ms!r}.")
        now = _now()
        with self.transaction() as tx:
            assignment = self._assignment_for_write(tx, annotator, campaign, context_id)
            candidate = None if slot == 0 else assignment.permutation[slot - 1]
            existing = tx.execute("SELECT * FROM labels WHERE context_id = ? AND annotator_id = ?",
                                  (context_id, annotator.id)).fetchone()
            if existing is not None:
                if not revise:
                    raise DuplicateSubmissionError(
                        f"annotator {annotator.name!r} already labeled item {context_id} (choice {existing['slot']}); "
                        "nothing was written. Revise it explicitly (PUT) to change it."
                    )
                tx.execute("INSERT INTO label_history (label_id, slot, candidate, time_on_item_ms, created_at, "
                           "replaced_at) VALUES (?, ?, ?, ?, ?, ?)", (existing["id"], existing["slot"],
                           existing["candidate"], existing["time_on_item_ms"], existing["created_at"], now))
                tx.execute("UPDATE labels SET slot = ?, candidate = ?, time_on_item_ms = ?, created_at = ?, "
                           "revision = revision + 1 WHERE id = ?", (slot, candidate, time_on_item_ms, now,
                                                                     existing["id"]))
                label_id = existing["id"]
            else:
                if revise:
                    raise ItemStateError(f"item {context_id} has no label by {annotator.name!r} to revise; POST one.")
                tx.execute("DELETE FROM skips WHERE context_id = ? AND annotator_id = ?", (context_id, annotator.id))
                cur = tx.execute(
                    "INSERT INTO labels (context_id, annotator_id, campaign_id, slot, candidate, permutation, "
                    "time_on_item_ms, source, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (context_id, annotator.id, campaign.id, slot, candidate, json.dumps(list(assignment.permutation)),
                     time_on_item_ms, source, now))
                label_id = cur.lastrowid
            row = tx.execute("SELECT * FROM labels WHERE id = ?", (label_id,)).fetchone()
        return _label(row)

    def skip(self, annotator: Annotator, campaign: Campaign, context_id: int, reason: str) -> None:
        """Skip item ``context_id`` with a ``reason`` (1-500 characters); labeled items cannot be skipped."""
        if not isinstance(reason, str) or not reason.strip() or len(reason) > MAX_REASON_CHARS:
            raise InvalidChoiceError(f"skip `reason` must be 1-{MAX_REASON_CHARS} characters; got {reason!r}.")
        with self.transaction() as tx:
            self._assignment_for_write(tx, annotator, campaign, context_id)
            if tx.execute("SELECT 1 FROM labels WHERE context_id = ? AND annotator_id = ?",
                          (context_id, annotator.id)).fetchone():
                raise DuplicateSubmissionError(f"item {context_id} is already labeled by {annotator.name!r}; "
                                               "it cannot be skipped. Revise the label instead.")
            try:
                tx.execute("INSERT INTO skips (context_id, annotator_id, campaign_id, reason, created_at) VALUES "
                           "(?, ?, ?, ?, ?)", (context_id, annotator.id, campaign.id, reason.strip(), _now()))
            except sqlite3.IntegrityError as exc:
                raise DuplicateSubmissionError(f"item {context_id} is already skipped by {annotator.name!r}.") from exc

    def _assignment_for_write(self, tx: _Tx, annotator: Annotator, campaign: Campaign, context_id: int) -> Assignment:
        if isinstance(context_id, bool) or not isinstance(context_id, int):
            raise UnknownItemError(f"item ids are integers; got {context_id!r}.")
        row = tx.execute("SELECT * FROM assignments WHERE annotator_id = ? AND context_id = ?",
                         (annotator.id, context_id)).fetchone()
        if row is None or row["campaign_id"] != campaign.id:
            known = tx.execute("SELECT 1 FROM contexts WHERE id = ? AND campaign_id = ?",
                               (context_id, campaign.id)).fetchone()
            if known is None:
                raise UnknownItemError(f"no item {context_id!r} in campaign {campaign.name!r}.")
            raise ItemStateError(f"item {context_id} was never opened by {annotator.name!r}: open it first (GET) so "
                                 "its candidate order is fixed; nothing was written.")
        return _assignment(row)

    def labels(self, campaign: Campaign) -> list[Label]:
        """Every label of ``campaign``, oldest first."""
        rows = self._conn().execute("SELECT * FROM labels WHERE campaign_id = ? ORDER BY id", (campaign.id,))
        return [_label(r) for r in rows]

    def skips(self, campaign: Campaign) -> list[dict[str, Any]]:
        """Every skip of ``campaign`` (context_id, annotator_id, reason, created_at)."""
        rows = self._conn().execute("SELECT context_id, annotator_id, reason, created_at FROM skips WHERE "
                                    "campaign_id = ? ORDER BY id", (campaign.id,))
        return [dict(r) for r in rows]

    def progress(self, annotator: Annotator, campaign: Campaign) -> dict[str, int]:
        """``labeled``, ``skipped``, ``done`` and ``total`` (items this annotator can still get, plus done)."""
        with self.snapshot() as conn:
            labeled = conn.execute("SELECT COUNT(*) FROM labels WHERE annotator_id = ? AND campaign_id = ?",
                                   (annotator.id, campaign.id)).fetchone()[0]
            skipped = conn.execute("SELECT COUNT(*) FROM skips WHERE annotator_id = ? AND campaign_id = ?",
                                   (annotator.id, campaign.id)).fetchone()[0]
            if campaign.labels_per_item is None:
                total = conn.execute("SELECT COUNT(*) FROM contexts WHERE campaign_id = ?",
                                     (campaign.id,)).fetchone()[0]
            else:
                assigned = conn.execute("SELECT COUNT(*) FROM assignments WHERE annotator_id = ? AND campaign_id = ?",
                                        (annotator.id, campaign.id)).fetchone()[0]
                available = conn.execute(
                    "SELECT COUNT(*) FROM contexts c WHERE c.campaign_id = ? AND NOT EXISTS (SELECT 1 FROM assignments"
                    " a WHERE a.context_id = c.id AND a.annotator_id = ?) AND (SELECT COUNT(*) FROM labels l WHERE "
                    "l.context_id = c.id) < ?", (campaign.id, annotator.id, campaign.labels_per_item)).fetchone()[0]
                total = assigned + available
        return {"labeled": labeled, "skipped": skipped, "done": labeled + skipped, "total": total}

    def counts(self, campaign: Campaign) -> dict[str, int]:
        """Items, labels, skips and distinct annotators of ``campaign``."""
        conn = self._conn()

        def one(sql: str) -> int:
            return conn.execute(sql, (campaign.id,)).fetchone()[0]

        return {
            "items": one("SELECT COUNT(*) FROM contexts WHERE campaign_id = ?"),
            "labels": one("SELECT COUNT(*) FROM labels WHERE campaign_id = ?"),
            "none_realistic": one("SELECT COUNT(*) FROM labels WHERE campaign_id = ? AND slot = 0"),
            "skips": one("SELECT COUNT(*) FROM skips WHERE campaign_id = ?"),
            "annotators": one("SELECT COUNT(DISTINCT annotator_id) FROM labels WHERE campaign_id = ?"),
        }


class _Tx:
    """The connection inside a write transaction (``executescript`` would commit, so it is not offered)."""

    def __init__(self, conn: sqlite3.Connection) -> None:
        self._conn = conn

    def execute(self, sql: str, params: tuple[Any, ...] = ()) -> sqlite3.Cursor:
        return self._conn.execute(sql, params)

    def executemany(self, sql: str, rows: list[tuple[Any, ...]]) -> sqlite3.Cursor:
        return self._conn.executemany(sql, rows)

    def executescript_safe(self, script: str) -> None:
        """Run ``;``-separated DDL statements one by one inside the open transaction."""
        for statement in script.split(";"):
            if statement.strip():
                self._conn.execute(statement)


# ------------------------------------------------------------------------------------------------ helpers
def _shuffle_key(*parts: object) -> int:
    return int.from_bytes(hashlib.sha256(":".join(map(str, parts)).encode()).digest()[:8], "big")


def _replace(assignment: Assignment, **changes: Any) -> Assignment:
    return replace(assignment, **changes)
