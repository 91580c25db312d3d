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
import re
import sqlite3
import threading
import time
from dataclasses import replace
from datetime import datetime, timezone
from collections.abc import Iterator
from typing import Any, Literal

import torch

from trafficrlhf_sdk.errors import DatabaseFileError, DataFormatError
from trafficrlhf_sdk.feedback.errors import (
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
)
from trafficrlhf_sdk.feedback.schema import SCHEMA_SQL, SCHEMA_VERSION, migrate
from trafficrlhf_sdk.feedback.settings import AnnotationSettings
from trafficrlhf_sdk.feedback.accounts import StoreAccounts
from trafficrlhf_sdk.feedback.statistics import SQLITE_MAX_INT, StoreStatistics
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor, scenario_from_bytes, scenario_to_bytes

__all__ = [
    "SCHEMA_VERSION",
    "SQLITE_MAX_INT",
    "TIE_SLOT",
    "Annotator",
    "Assignment",
    "Campaign",
    "ContextRecord",
    "FeedbackStore",
    "Label",
    "check_database_file",
    "open_store",
]

MAX_REASON_CHARS = 500
Synchronous = Literal["OFF", "NORMAL", "FULL", "EXTRA"]
LabelKind = Literal["regular", "gold", "all"]


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


SQLITE_MAGIC = b"SQLite format 3\x00"
SCHEMA_TABLES = tuple(re.findall(r"CREATE TABLE IF NOT EXISTS (\w+)", SCHEMA_SQL))


def check_database_file(path: str) -> None:
    """Refuse a file at ``path`` that exists and is not an SQLite database, before SQLite touches it (an empty
    file or no file is a new database)."""
    if os.path.isdir(path):
        raise DatabaseFileError(f"`--db` {path!r} is a directory; pass the feedback database file (e.g. "
                                "feedback.db).")
    if not os.path.exists(path):
        return
    with open(path, "rb") as handle:
        head = handle.read(len(SQLITE_MAGIC))
    if head and head != SQLITE_MAGIC:
        raise DatabaseFileError(f"`--db` {path!r} is not an SQLite database (it starts with {head[:8]!r}, not "
                                "'SQLite format 3'); pass the file `trafficrlhf feedback create` made, or a new "
                                "path for `feedback create`.")


# -------------------------------------------------------------------------------------------------- store
class FeedbackStore(StoreAccounts, StoreStatistics):
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
        self._write_lock = threading.Lock()
        check_database_file(self.path)
        try:
            self._open()
        except sqlite3.DatabaseError as exc:  # damaged past its header: SQLite finds out on the first read
            self.close()
            raise DatabaseFileError(f"`--db` {self.path!r} is not a readable feedback database (SQLite says: "
                                    f"{exc}); pass the file `trafficrlhf feedback create` made, or restore it from "
                                    "a backup.") from None

    def _open(self) -> None:
        conn = self._conn()
        conn.execute("PRAGMA journal_mode=WAL")
        upgrading = conn.execute("PRAGMA user_version").fetchone()[0] == 1
        if upgrading:  # rebuilding a table needs foreign keys off (checked below); the pragma is per connection
            conn.execute("PRAGMA foreign_keys = OFF")
        with self.transaction() as tx:
            version = tx.execute("PRAGMA user_version").fetchone()[0]
            if version not in (0, 1, SCHEMA_VERSION):
                raise DataFormatError(
                    f"{self.path!r} has feedback schema version {version}; this SDK reads versions 1 to "
                    f"{SCHEMA_VERSION}. Upgrade the SDK to open it."
                )
            if version == SCHEMA_VERSION:  # a finished database: never recreate what is missing as empty
                found = {row[0] for row in tx.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
                missing = sorted(set(SCHEMA_TABLES) - found)
                if missing:
                    raise DatabaseFileError(
                        f"`--db` {self.path!r} is a damaged feedback database: table(s) {', '.join(missing)} are "
                        "missing, so its campaigns or labels would read as empty; restore the file from a backup.")
            migrate(tx.execute, version)
            tx.executescript_safe(SCHEMA_SQL)
            if version == 1 and tx.execute("PRAGMA foreign_key_check").fetchone() is not None:
                raise DataFormatError(f"{self.path!r}: upgrading schema 1 to {SCHEMA_VERSION} broke a foreign key; "
                                      "nothing was changed. Report this with the file.")
            tx.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
        if upgrading:
            conn.execute("PRAGMA foreign_keys = ON")

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
        """A write transaction (``BEGIN IMMEDIATE``): committed on exit, rolled back on any exception (including a
        failed commit, e.g. on a full disk), so a failed write leaves nothing behind."""
        conn = self._conn()
        # writers of this process queue here in turn, rather than in SQLite's busy handler, whose growing sleeps
        # let some threads wait for seconds while others write; other processes still meet SQLite's lock
        with self._write_lock:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield _Tx(conn)
                conn.execute("COMMIT")
            except BaseException:
                # SQLite may already have rolled back (e.g. "database or disk is full"): keep the original error
                if conn.in_transaction:
                    with contextlib.suppress(sqlite3.Error):
                        conn.execute("ROLLBACK")
                raise

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

    # -------------------------------------------------------------------------------------- assignments
    def next_item(self, annotator: Annotator, campaign: Campaign) -> Assignment | None:
        """The annotator's open item (resume), else a new one; None when nothing is left for them.

        Order of service: with ``qualification_gold`` N > 0, the first N items are gold items; an annotator who
        fails them gets nothing more (see :meth:`quality`). Afterwards gold items come at ``gold_rate``, the
        rest are regular items the annotator has not seen: highest ``priority`` first, then (with
        ``labels_per_item``) fewest labels, in an order shuffled per annotator. With ``labels_per_item`` an item
        is offered only while its labels plus the unexpired leases of others on it stay below the cap; opening
        an item leases it for ``lease_seconds``. An open item whose lease expired while others filled it is
        released (it will not come back) and the next one is served.
        """
        settings = campaign.settings
        with self.transaction() as tx:
            now = time.time()  # after the write lock is ours: a wait for it must not shorten the lease
            while True:
                open_row = tx.execute(
                    "SELECT a.* FROM assignments a WHERE a.annotator_id = ? AND a.campaign_id = ? AND a.released = 0 "
                    "AND NOT EXISTS (SELECT 1 FROM labels l WHERE l.context_id = a.context_id AND l.annotator_id = "
                    "a.annotator_id) AND NOT EXISTS (SELECT 1 FROM skips s WHERE s.context_id = a.context_id AND "
                    "s.annotator_id = a.annotator_id) ORDER BY a.position LIMIT 1",
                    (annotator.id, campaign.id)).fetchone()
                if open_row is None:
                    break
                if self._keep_lease(tx, campaign, open_row, now):
                    return _assignment(open_row)
            quality = self._quality(tx, annotator, campaign)
            gold = self._due_gold(tx, annotator, campaign, settings, quality)
            if gold == "stop":
                return None
            if gold is not None:
                return self._assign(tx, annotator, campaign, int(gold), now)
            context_id = self._pick_regular(tx, annotator, campaign, now)
            if context_id is None:
                return None
            return self._assign(tx, annotator, campaign, context_id, now)

    def _keep_lease(self, tx: _Tx, campaign: Campaign, row: sqlite3.Row, now: float) -> bool:
        """Renew the lease of an open assignment; False (and released) when it expired and others filled it."""
        cap = campaign.labels_per_item
        gold = tx.execute("SELECT gold_answer FROM contexts WHERE id = ?", (row["context_id"],)).fetchone()[0]
        if cap is not None and gold is None and (row["lease_expires_at"] is None or row["lease_expires_at"] <= now):
            if self._taken(tx, row["context_id"], row["annotator_id"], now) >= cap:
                tx.execute("UPDATE assignments SET released = 1, lease_expires_at = NULL WHERE id = ?", (row["id"],))
                return False
        tx.execute("UPDATE assignments SET lease_expires_at = ? WHERE id = ?",
                   (now + campaign.settings.lease_seconds, row["id"]))
        return True

    @staticmethod
    def _taken(tx: _Tx | sqlite3.Connection, context_id: int, annotator_id: int, now: float) -> int:
        """Labels of item ``context_id`` by others plus unexpired leases of others on it."""
        return int(tx.execute(
            "SELECT (SELECT COUNT(*) FROM labels WHERE context_id = ? AND annotator_id != ?) + (SELECT COUNT(*) FROM "
            "assignments WHERE context_id = ? AND annotator_id != ? AND released = 0 AND lease_expires_at > ?)",
            (context_id, annotator_id, context_id, annotator_id, now)).fetchone()[0])

    @staticmethod
    def _pick_regular(tx: _Tx, annotator: Annotator, campaign: Campaign, now: float) -> int | None:
        cap = campaign.labels_per_item
        mine = "NOT EXISTS (SELECT 1 FROM assignments a WHERE a.annotator_id = ? AND a.context_id = c.id)"
        if cap is None:  # everybody labels everything: an order shuffled per annotator
            salt = _shuffle_key(campaign.seed, annotator.id) % 4294967311
            row = tx.execute(
                f"SELECT c.id FROM contexts c WHERE c.campaign_id = ? AND c.gold_answer IS NULL AND {mine} "
                "ORDER BY c.priority DESC, (c.id * 2654435761 + ?) % 4294967311 LIMIT 1",
                (campaign.id, annotator.id, salt)).fetchone()
        else:  # the queue index, in order: the first item with room left (labels plus others' live leases)
            row = tx.execute(
                f"SELECT c.id FROM contexts c INDEXED BY contexts_queue WHERE c.campaign_id = ? AND c.gold_answer "
                f"IS NULL AND c.labels_n < ? AND {mine} AND c.labels_n + (SELECT COUNT(*) FROM assignments s WHERE "
                "s.context_id = c.id AND s.released = 0 AND s.lease_expires_at > ?) < ? "
                "ORDER BY c.priority DESC, c.labels_n, c.id LIMIT 1",
                (campaign.id, cap, annotator.id, now, cap)).fetchone()
        return None if row is None else int(row[0])

    def _due_gold(self, tx: _Tx, annotator: Annotator, campaign: Campaign, settings: AnnotationSettings,
                  quality: dict[str, Any]) -> int | str | None:
        """A gold item to serve now, ``"stop"`` when the annotator failed (or cannot finish) qualification, or
        None for a regular item."""
        if quality["status"] == "none" and settings.gold_rate <= 0:
            return None
        unseen = tx.execute(
            "SELECT c.id FROM contexts c INDEXED BY contexts_gold WHERE c.campaign_id = ? AND c.gold_answer IS NOT "
            "NULL AND NOT EXISTS "
            "(SELECT 1 FROM assignments a WHERE a.annotator_id = ? AND a.context_id = c.id) ORDER BY "
            "(c.id * 2654435761 + ?) % 4294967311 LIMIT 1",
            (campaign.id, annotator.id, _shuffle_key(campaign.seed, annotator.id, "gold") % 4294967311)).fetchone()
        if quality["status"] == "failed":
            return "stop"
        if quality["status"] == "pending":
            return "stop" if unseen is None else int(unseen[0])
        if unseen is None or settings.gold_rate <= 0:
            return None
        served = tx.execute(
            "SELECT COUNT(*), COALESCE(SUM(c.gold_answer IS NOT NULL), 0) FROM assignments a JOIN contexts c ON c.id = "
            "a.context_id WHERE a.annotator_id = ? AND a.campaign_id = ?", (annotator.id, campaign.id)).fetchone()
        after = int(served[0]) - settings.qualification_gold
        gold_after = int(served[1]) - settings.qualification_gold
        jitter = (_shuffle_key(campaign.seed, annotator.id, "gold-phase") % 1000) / 1000.0
        return int(unseen[0]) if int(settings.gold_rate * (after + 1) + jitter) > gold_after else None

    def open_item(self, annotator: Annotator, campaign: Campaign, context_id: int) -> Assignment:
        """The annotator's assignment of item ``context_id``, created (with its permutation) on first open.

        With ``labels_per_item``, opening a new regular item that is full (labels plus others' leases) raises
        :class:`ItemStateError`; so does opening a gold item before qualification is over or a regular one
        before it is passed.
        """
        _check_id(context_id, "item")
        with self.transaction() as tx:
            now = time.time()
            row = tx.execute("SELECT * FROM assignments WHERE annotator_id = ? AND context_id = ?",
                             (annotator.id, context_id)).fetchone()
            if row is not None:
                if row["campaign_id"] != campaign.id:
                    raise UnknownItemError(f"no item {context_id!r} in campaign {campaign.name!r}.")
                assignment = self._with_status(tx, _assignment(row))
                if assignment.status == "open" and not row["released"]:
                    self._keep_lease(tx, campaign, row, now)
                return assignment
            ctx = tx.execute("SELECT gold_answer FROM contexts WHERE id = ? AND campaign_id = ?",
                             (context_id, campaign.id)).fetchone()
            if ctx is None:
                raise UnknownItemError(f"no item {context_id!r} in campaign {campaign.name!r}.")
            status = self._quality(tx, annotator, campaign)["status"]
            if status in ("pending", "failed") and ctx["gold_answer"] is None:
                raise ItemStateError(f"annotator {annotator.name!r} is not qualified for campaign {campaign.name!r} "
                                     f"(qualification {status}); take the next item instead.")
            cap = campaign.labels_per_item
            if cap is not None and ctx["gold_answer"] is None and self._taken(tx, context_id, annotator.id, now) >= cap:
                raise ItemStateError(f"item {context_id} already has its {cap} annotator(s) (labels_per_item); "
                                     "nothing was assigned. Take the next item instead.")
            return self._assign(tx, annotator, campaign, context_id, now)

    def _assign(self, tx: _Tx, annotator: Annotator, campaign: Campaign, context_id: int, now: float) -> Assignment:
        position = tx.execute("SELECT COALESCE(MAX(position), 0) + 1 FROM assignments WHERE annotator_id = ? AND "
                              "campaign_id = ?", (annotator.id, campaign.id)).fetchone()[0]
        permutation = list(range(campaign.num_candidates))
        random.Random(_shuffle_key(campaign.seed, annotator.id, context_id, "perm")).shuffle(permutation)
        stamp = _now()
        cur = tx.execute(
            "INSERT INTO assignments (annotator_id, context_id, campaign_id, position, permutation, assigned_at, "
            "lease_expires_at) VALUES (?, ?, ?, ?, ?, ?, ?)",
            (annotator.id, context_id, campaign.id, position, json.dumps(permutation), stamp,
             now + campaign.settings.lease_seconds))
        return Assignment(int(cur.lastrowid), annotator.id, context_id, campaign.id, position,  # type: ignore[arg-type]
                          tuple(permutation), stamp)

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

    def is_gold(self, context_id: int) -> bool:
        """True when item ``context_id`` is a gold item."""
        _check_id(context_id, "item")
        row = self._conn().execute("SELECT gold_answer FROM contexts WHERE id = ?", (context_id,)).fetchone()
        return row is not None and row[0] is not None

    # ------------------------------------------------------------------------------------ labels, skips
    def submit_label(self, annotator: Annotator, campaign: Campaign, context_id: int, slot: int,
                     time_on_item_ms: int | None = None, source: str = "human", revise: bool = False,
                     min_view_s: float | None = None) -> Label:
        """Record the annotator's choice for item ``context_id``: ``slot`` 1..N (as shown), 0 (none realistic)
        or :data:`TIE_SLOT` (-1, equally realistic, when the campaign allows ties).

        The item must have been opened (its permutation fixed). A second submission raises
        :class:`DuplicateSubmissionError` and writes nothing, unless ``revise`` (the old value then goes to
        ``label_history``). A label replaces a skip of the same item. With ``labels_per_item``, a first label on
        a regular item that already has its labels from others is refused (:class:`ItemStateError`) and the
        annotator's assignment is released. ``min_view_s``: refuse (``ItemStateError``) a first label sent
        sooner than this after the item was first served (the app's playback requirement).
        """
        low = TIE_SLOT if campaign.settings.allow_tie else 0
        if isinstance(slot, bool) or not isinstance(slot, int) or not low <= slot <= campaign.num_candidates:
            tie = ", or -1 ('tie') for equally realistic" if campaign.settings.allow_tie else ""
            raise InvalidChoiceError(
                f"`choice` must be an integer from 0 (none realistic) to {campaign.num_candidates}{tie}; got "
                f"{slot!r}."
            )
        if time_on_item_ms is not None and (isinstance(time_on_item_ms, bool) or not isinstance(time_on_item_ms, int)
                                            or not 0 <= time_on_item_ms <= SQLITE_MAX_INT):
            raise InvalidChoiceError(f"`time_ms` must be a non-negative integer below 2^63; got {time_on_item_ms!r}.")
        now = _now()
        full = None
        with self.transaction() as tx:
            assignment = self._assignment_for_write(tx, annotator, campaign, context_id)
            candidate = None if slot <= 0 else assignment.permutation[slot - 1]
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
                if min_view_s is not None and min_view_s > 0:
                    shown = datetime.fromisoformat(assignment.assigned_at).timestamp()
                    waited = time.time() - shown
                    if waited < min_view_s:
                        raise ItemStateError(
                            f"item {context_id} was served {waited:.1f} s ago; watch the future play through once "
                            f"(at least {min_view_s:.1f} s) before choosing. Nothing was written.")
                cap = campaign.labels_per_item
                gold = tx.execute("SELECT gold_answer FROM contexts WHERE id = ?", (context_id,)).fetchone()[0]
                others = tx.execute("SELECT COUNT(*) FROM labels WHERE context_id = ? AND annotator_id != ?",
                                    (context_id, annotator.id)).fetchone()[0]
                if cap is not None and gold is None and others >= cap:
                    tx.execute("UPDATE assignments SET released = 1, lease_expires_at = NULL WHERE id = ?",
                               (assignment.id,))
                    full = (cap, others)
                    label_id = None
                else:
                    tx.execute("DELETE FROM skips WHERE context_id = ? AND annotator_id = ?",
                               (context_id, annotator.id))
                    cur = tx.execute(
                        "INSERT INTO labels (context_id, annotator_id, campaign_id, slot, candidate, permutation, "
                        "time_on_item_ms, source, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        (context_id, annotator.id, campaign.id, slot, candidate,
                         json.dumps(list(assignment.permutation)), time_on_item_ms, source, now))
                    label_id = cur.lastrowid
                    tx.execute("UPDATE contexts SET labels_n = labels_n + 1 WHERE id = ?", (context_id,))
                    tx.execute("UPDATE assignments SET lease_expires_at = NULL WHERE id = ?", (assignment.id,))
            row = None if label_id is None else tx.execute("SELECT * FROM labels WHERE id = ?", (label_id,)).fetchone()
        if full is not None:
            raise ItemStateError(f"item {context_id} already has {full[1]} label(s) from others (labels_per_item "
                                 f"{full[0]}; your lease on it had expired); nothing was written. Take the next item.")
        return _label(row)

    def skip(self, annotator: Annotator, campaign: Campaign, context_id: int, reason: str) -> None:
        """Skip item ``context_id`` with a ``reason`` (1-500 characters); labeled items cannot be skipped."""
        if not isinstance(reason, str) or not reason.strip() or len(reason) > MAX_REASON_CHARS:
            raise InvalidChoiceError(f"skip `reason` must be 1-{MAX_REASON_CHARS} characters; got {reason!r}.")
        with self.transaction() as tx:
            assignment = self._assignment_for_write(tx, annotator, campaign, context_id)
            if tx.execute("SELECT 1 FROM labels WHERE context_id = ? AND annotator_id = ?",
                          (context_id, annotator.id)).fetchone():
                raise DuplicateSubmissionError(f"item {context_id} is already labeled by {annotator.name!r}; "
                                               "it cannot be skipped. Revise the label instead.")
            try:
                tx.execute("INSERT INTO skips (context_id, annotator_id, campaign_id, reason, created_at) VALUES "
                           "(?, ?, ?, ?, ?)", (context_id, annotator.id, campaign.id, reason.strip(), _now()))
            except sqlite3.IntegrityError as exc:
                raise DuplicateSubmissionError(f"item {context_id} is already skipped by {annotator.name!r}.") from exc
            tx.execute("UPDATE assignments SET lease_expires_at = NULL WHERE id = ?", (assignment.id,))

    def _assignment_for_write(self, tx: _Tx, annotator: Annotator, campaign: Campaign, context_id: int) -> Assignment:
        _check_id(context_id, "item")
        row = tx.execute("SELECT * FROM assignments WHERE annotator_id = ? AND context_id = ?",
                         (annotator.id, context_id)).fetchone()
        if row is None or row["campaign_id"] != campaign.id:
            known = tx.execute("SELECT 1 FROM contexts WHERE id = ? AND campaign_id = ?",
                               (context_id, campaign.id)).fetchone()
            if known is None:
                raise UnknownItemError(f"no item {context_id!r} in campaign {campaign.name!r}.")
            raise ItemStateError(f"item {context_id} was never opened by {annotator.name!r}: open it first (GET) so "
                                 "its candidate order is fixed; nothing was written.")
        if row["released"]:
            raise ItemStateError(f"item {context_id} was released from {annotator.name!r} (the lease expired and "
                                 "others labeled it); nothing was written. Take the next item.")
        return _assignment(row)

    def labels(self, campaign: Campaign, kind: LabelKind = "regular") -> list[Label]:
        """The labels of ``campaign`` (``kind``: regular items, gold items or all), oldest first."""
        where = {"regular": " AND c.gold_answer IS NULL", "gold": " AND c.gold_answer IS NOT NULL", "all": ""}
        if kind not in where:
            raise ValueError(f"`kind` must be 'regular', 'gold' or 'all'; got {kind!r}.")
        rows = self._conn().execute("SELECT l.* FROM labels l JOIN contexts c ON c.id = l.context_id WHERE "
                                    f"l.campaign_id = ?{where[kind]} ORDER BY l.id", (campaign.id,))
        return [_label(r) for r in rows]

    def skips(self, campaign: Campaign) -> list[dict[str, Any]]:
        """Every skip of ``campaign`` (context_id, annotator_id, reason, created_at)."""
        rows = self._conn().execute("SELECT context_id, annotator_id, reason, created_at FROM skips WHERE "
                                    "campaign_id = ? ORDER BY id", (campaign.id,))
        return [dict(r) for r in rows]


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


def _check_id(value: object, what: str) -> None:
    """Refuse ids that are not integers in SQLite's range (an item id ``2**63`` would overflow the driver)."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= SQLITE_MAX_INT:
        raise UnknownItemError(f"{what} ids are integers from 0 to 2^63 - 1; got {value!r}.")


@contextlib.contextmanager
def open_store(path: str | os.PathLike[str], must_exist: bool = False) -> Iterator[FeedbackStore]:
    """The feedback database at ``path`` for one command: a failure inside the block leaves nothing behind.

    When the block raises and the database did not exist before, the store is closed and the file removed (with
    SQLite's ``-wal``/``-shm`` files), so a mistyped option never leaves an empty database. ``must_exist``
    refuses a missing database, naming the command that creates one."""
    from trafficrlhf_sdk.errors import DataNotFoundError

    path = os.fspath(path)
    existed = os.path.exists(path)
    if must_exist and not existed:
        raise DataNotFoundError(f"feedback database {path!r} does not exist; create it with `trafficrlhf feedback "
                                "create --db ...`.")
    store = FeedbackStore(path)
    try:
        yield store
    except BaseException:
        if not existed:
            store.close()
            for leftover in (path, f"{path}-wal", f"{path}-shm", f"{path}-journal"):
                with contextlib.suppress(FileNotFoundError):
                    os.remove(leftover)
        raise
