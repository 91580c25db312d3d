"""The feedback database's SQLite schema (used by :class:`~trafficrlhf_sdk.feedback.store.FeedbackStore`).

Schema (``PRAGMA user_version`` = :data:`SCHEMA_VERSION`):

- ``campaigns``: name, the generating model, guidance, seed, SDK version and the full config as JSON.
- ``contexts``: one row per item: source, split, scene id, seed, start step, and the logged scene (history and
  logged future over the candidate window, with a cropped map) as safetensors bytes.
- ``candidates``: per context the N model futures (``idx`` 0..N-1, ``kind='model'``) and the logged future
  (``idx`` -1, ``kind='logged'``, never shown as such), each as safetensors bytes of ``states (A, H, 4)`` and
  ``valid (A, H)``.
- ``annotators``: name and the SHA-256 of the token (the token itself is printed once and never stored).
- ``assignments``: which annotator was shown which item, in which position of their queue, and the shuffled
  candidate order (``permutation[k]`` = candidate index shown in slot ``k + 1``).
- ``labels``: ``UNIQUE(context, annotator)``: the slot pressed (0 = none realistic, -1 = the candidates are
  equally realistic), the candidate index it means (NULL for none and for a tie), the permutation, time on the
  item, source (``human`` or ``synthetic``).
- ``label_history``: previous values of revised labels. ``skips``: ``UNIQUE(context, annotator)`` with a reason.
- ``admins``: campaign owners' tokens (SHA-256 only), for the app's admin page.

Version 2 added: ``contexts.gold_answer`` (the known answer of a gold item: a candidate index, NULL for a
regular item), ``contexts.priority`` (higher is served first, e.g. reward-model disagreement) and
``contexts.labels_n`` (its number of labels, kept with every insert, so the queue is an index scan),
``candidates.model`` (the traffic model behind each candidate), ``assignments.lease_expires_at`` (unix seconds:
until then the open item is reserved for its annotator) and ``assignments.released`` (1 when an expired lease
was given up because others filled the item), the ``admins`` table, and ties (``slot`` -1) in ``labels`` and
``label_history``. :func:`migrate` upgrades a version 1 file in place, in one transaction.
"""

from collections.abc import Callable

__all__ = ["SCHEMA_SQL", "SCHEMA_VERSION", "migrate"]

SCHEMA_VERSION = 2

SCHEMA_SQL = """
CREATE TABLE IF NOT EXISTS campaigns (
    id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, created_at TEXT NOT NULL,
    model TEXT NOT NULL, guidance TEXT, seed INTEGER NOT NULL,
    num_candidates INTEGER NOT NULL CHECK (num_candidates >= 2),
    sdk_version TEXT NOT NULL, config_json TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS contexts (
    id INTEGER PRIMARY KEY, campaign_id INTEGER NOT NULL REFERENCES campaigns(id), ordinal INTEGER NOT NULL,
    source TEXT NOT NULL, split TEXT NOT NULL, scene_id TEXT NOT NULL, seed INTEGER NOT NULL,
    start_index INTEGER NOT NULL, created_at TEXT NOT NULL, sdk_version TEXT NOT NULL, scenario BLOB NOT NULL,
    gold_answer INTEGER, priority REAL NOT NULL DEFAULT 0, labels_n INTEGER NOT NULL DEFAULT 0,
    UNIQUE (campaign_id, source, split, scene_id), UNIQUE (campaign_id, ordinal)
);
CREATE TABLE IF NOT EXISTS candidates (
    id INTEGER PRIMARY KEY, context_id INTEGER NOT NULL REFERENCES contexts(id), idx INTEGER NOT NULL,
    kind TEXT NOT NULL CHECK (kind IN ('model', 'logged')), tensors BLOB NOT NULL, model TEXT,
    UNIQUE (context_id, idx)
);
CREATE TABLE IF NOT EXISTS annotators (
    id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, token_sha256 TEXT NOT NULL UNIQUE,
    created_at TEXT NOT NULL, active INTEGER NOT NULL DEFAULT 1
);
CREATE TABLE IF NOT EXISTS assignments (
    id INTEGER PRIMARY KEY, annotator_id INTEGER NOT NULL REFERENCES annotators(id),
    context_id INTEGER NOT NULL REFERENCES contexts(id), campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
    position INTEGER NOT NULL, permutation TEXT NOT NULL, assigned_at TEXT NOT NULL,
    lease_expires_at REAL, released INTEGER NOT NULL DEFAULT 0,
    UNIQUE (annotator_id, context_id), UNIQUE (annotator_id, campaign_id, position)
);
CREATE TABLE IF NOT EXISTS labels (
    id INTEGER PRIMARY KEY, context_id INTEGER NOT NULL REFERENCES contexts(id),
    annotator_id INTEGER NOT NULL REFERENCES annotators(id), campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
    slot INTEGER NOT NULL CHECK (slot >= -1), candidate INTEGER, permutation TEXT NOT NULL,
    time_on_item_ms INTEGER, source TEXT NOT NULL, created_at TEXT NOT NULL, revision INTEGER NOT NULL DEFAULT 0,
    UNIQUE (context_id, annotator_id)
);
CREATE TABLE IF NOT EXISTS label_history (
    id INTEGER PRIMARY KEY, label_id INTEGER NOT NULL REFERENCES labels(id), slot INTEGER NOT NULL,
    candidate INTEGER, time_on_item_ms INTEGER, created_at TEXT NOT NULL, replaced_at TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS skips (
    id INTEGER PRIMARY KEY, context_id INTEGER NOT NULL REFERENCES contexts(id),
    annotator_id INTEGER NOT NULL REFERENCES annotators(id), campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
    reason TEXT NOT NULL, created_at TEXT NOT NULL, UNIQUE (context_id, annotator_id)
);
CREATE TABLE IF NOT EXISTS admins (
    id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, token_sha256 TEXT NOT NULL UNIQUE, created_at TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS labels_by_campaign ON labels (campaign_id, context_id);
CREATE INDEX IF NOT EXISTS contexts_by_campaign ON contexts (campaign_id, ordinal);
CREATE INDEX IF NOT EXISTS assignments_by_context ON assignments (context_id);
CREATE INDEX IF NOT EXISTS contexts_queue ON contexts (campaign_id, priority DESC, labels_n, id)
    WHERE gold_answer IS NULL;
CREATE INDEX IF NOT EXISTS contexts_gold ON contexts (campaign_id, id) WHERE gold_answer IS NOT NULL;
"""

_V1_TO_V2 = """
ALTER TABLE contexts ADD COLUMN gold_answer INTEGER;
ALTER TABLE contexts ADD COLUMN priority REAL NOT NULL DEFAULT 0;
ALTER TABLE contexts ADD COLUMN labels_n INTEGER NOT NULL DEFAULT 0;
UPDATE contexts SET labels_n = (SELECT COUNT(*) FROM labels l WHERE l.context_id = contexts.id);
ALTER TABLE candidates ADD COLUMN model TEXT;
ALTER TABLE assignments ADD COLUMN lease_expires_at REAL;
ALTER TABLE assignments ADD COLUMN released INTEGER NOT NULL DEFAULT 0;
CREATE TABLE labels_v2 (
    id INTEGER PRIMARY KEY, context_id INTEGER NOT NULL REFERENCES contexts(id),
    annotator_id INTEGER NOT NULL REFERENCES annotators(id), campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
    slot INTEGER NOT NULL CHECK (slot >= -1), candidate INTEGER, permutation TEXT NOT NULL,
    time_on_item_ms INTEGER, source TEXT NOT NULL, created_at TEXT NOT NULL, revision INTEGER NOT NULL DEFAULT 0,
    UNIQUE (context_id, annotator_id)
);
INSERT INTO labels_v2 SELECT id, context_id, annotator_id, campaign_id, slot, candidate, permutation,
    time_on_item_ms, source, created_at, revision FROM labels;
DROP INDEX IF EXISTS labels_by_campaign;
DROP TABLE labels;
ALTER TABLE labels_v2 RENAME TO labels;
UPDATE candidates SET model = (SELECT c.model FROM contexts x JOIN campaigns c ON c.id = x.campaign_id
    WHERE x.id = candidates.context_id) WHERE kind = 'model'
"""


def migrate(execute: Callable[[str], object], version: int) -> None:
    """Upgrade a database of schema ``version`` to :data:`SCHEMA_VERSION` inside the caller's transaction.

    ``execute`` runs one SQL statement; the connection must have foreign keys off (``labels`` is rebuilt), and
    the caller checks them (``PRAGMA foreign_key_check``) before committing. Version 0 is a new file (nothing
    to upgrade); the tables and indexes of the current schema are created afterwards by the caller.
    """
    if version == 1:
        for statement in _V1_TO_V2.split(";"):
            if statement.strip():
                execute(statement)

