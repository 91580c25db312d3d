"""Feedback store, campaign quality features: leases and the labels-per-item cap under concurrency, gold items and
qualification, ties in the export, several models per set, priorities, deactivation, id range, migration."""

from __future__ import annotations

import json
import sqlite3
import threading
import time

import pytest
import torch

from trafficrlhf_sdk.feedback import FeedbackStore, ItemStateError, UnknownItemError, export_preferences
from trafficrlhf_sdk.feedback.errors import AuthenticationError, InvalidChoiceError
from trafficrlhf_sdk.feedback.gold import BREAKS, add_gold_items, gold_candidates
from trafficrlhf_sdk.feedback.preference import PreferenceDataset
from trafficrlhf_sdk.feedback.records import TIE_SLOT
from trafficrlhf_sdk.feedback.selection import candidate_disagreement, priorities_from_ranking, rank_by_disagreement
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign, tiny_context


@pytest.fixture()
def store(tmp_path):  # type: ignore[no-untyped-def]
    s = FeedbackStore(tmp_path / "fb.db")
    yield s
    s.close()


def _answer(store: FeedbackStore, annotator, campaign, assignment, right: bool) -> None:  # type: ignore[no-untyped-def]
    """Label a gold item right (its known answer) or wrong (another candidate)."""
    answer = store.load_context(assignment.context_id, campaign).gold_answer
    assert answer is not None
    candidate = answer if right else (answer + 1) % campaign.num_candidates
    store.submit_label(annotator, campaign, assignment.context_id, assignment.permutation.index(candidate) + 1)


def test_cap_holds_under_concurrent_annotators(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=30, labels_per_item=1)
    people = [store.add_annotator(f"a{i}")[0] for i in range(8)]
    errors: list[BaseException] = []

    def work(who) -> None:  # type: ignore[no-untyped-def]
        try:
            local = FeedbackStore(store.path)
            while (item := local.next_item(who, campaign)) is not None:
                local.submit_label(who, campaign, item.context_id, 1)
            local.close()
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(p,)) for p in people]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors
    per_item = sqlite3.connect(store.path).execute(
        "SELECT context_id, COUNT(*) FROM labels GROUP BY context_id").fetchall()
    assert len(per_item) == 30 and max(n for _, n in per_item) == 1
    assert store.counts(campaign)["items_over_cap"] == 0 and store.counts(campaign)["items_complete"] == 30


def test_leases_reserve_items_and_expire(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=2, labels_per_item=1)
    campaign = store.update_settings(campaign, lease_seconds=0.3)
    alice, bob, carol = (store.add_annotator(n)[0] for n in ("alice", "bob", "carol"))
    a = store.next_item(alice, campaign)
    b = store.next_item(bob, campaign)
    assert a is not None and b is not None and a.context_id != b.context_id
    assert store.next_item(carol, campaign) is None  # both items are leased
    with pytest.raises(ItemStateError, match="labels_per_item"):
        store.open_item(carol, campaign, a.context_id)
    time.sleep(0.4)  # alice walked away: her lease expired
    c = store.next_item(carol, campaign)
    assert c is not None and c.context_id in (a.context_id, b.context_id)
    store.submit_label(carol, campaign, c.context_id, 2)
    late = alice if c.context_id == a.context_id else bob
    with pytest.raises(ItemStateError, match="lease on it had expired"):
        store.submit_label(late, campaign, c.context_id, 1)
    assert store.next_item(late, campaign) is None or store.next_item(late, campaign).context_id != c.context_id
    labels = store.labels(campaign)
    assert [(x.annotator_id, x.context_id) for x in labels] == [(carol.id, c.context_id)]


def test_deactivation_revokes_and_releases(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=1, labels_per_item=1)
    (alice, token), (bob, _) = store.add_annotator("alice"), store.add_annotator("bob")
    assert store.next_item(alice, campaign) is not None and store.next_item(bob, campaign) is None
    store.set_active("alice", False)
    with pytest.raises(AuthenticationError):
        store.authenticate(token)
    assert store.next_item(bob, campaign) is not None  # alice's lease was released at once
    fresh = store.new_token("alice")
    assert store.authenticate(fresh).name == "alice"


def test_gold_items_qualification_and_accuracy(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=8)
    gold_ids = add_gold_items(store, campaign, 4, seed=3)
    campaign = store.update_settings(campaign, qualification_gold=2, qualification_accuracy=1.0, gold_rate=0.25)
    record = store.load_context(gold_ids[0], campaign)
    assert record.gold_answer is not None and record.candidate_models[record.gold_answer] == "gold:logged"
    assert torch.equal(record.candidates[record.gold_answer], record.logged)
    assert {m.split(":")[1] for m in record.candidate_models} - {"logged"} <= set(BREAKS)
    good, bad = store.add_annotator("good")[0], store.add_annotator("bad")[0]
    for who, right in ((good, True), (bad, False)):
        for _ in range(2):  # the qualification: the first two items are gold
            item = store.next_item(who, campaign)
            assert item is not None and item.context_id in gold_ids
            with pytest.raises(ItemStateError, match="not qualified"):
                store.open_item(who, campaign, next(k["id"] for k in store.context_keys(campaign)
                                                    if k["gold_answer"] is None))
            _answer(store, who, campaign, item, right)
    assert store.quality(bad, campaign)["status"] == "failed" and store.next_item(bad, campaign) is None
    assert store.quality(good, campaign) | {"qualification_gold": 2} == {
        "gold_answered": 2, "gold_correct": 2, "gold_accuracy": 1.0, "status": "passed", "qualification_gold": 2}
    served = []
    while (item := store.next_item(good, campaign)) is not None:
        served.append(item.context_id in gold_ids)
        if served[-1]:
            _answer(store, good, campaign, item, right=False)
        else:
            store.submit_label(good, campaign, item.context_id, 1)
    assert served.count(False) == 8 and served.count(True) == 2  # the other two gold items, mixed in at 1 in 4
    assert store.quality(good, campaign)["gold_accuracy"] == 0.5
    assert store.counts(campaign)["items"] == 8 and store.counts(campaign)["gold_items"] == 4
    data = export_preferences(store, campaign, val_fraction=0.0)
    assert data.num_choices == 8 and data.annotators == ("good",)  # gold labels are never exported
    with pytest.raises(InvalidChoiceError, match="regular items without a gold copy"):
        add_gold_items(store, campaign, 5)


def test_gold_candidates_are_broken_copies_of_the_log() -> None:
    from trafficrlhf_sdk.feedback.records import ContextRecord

    scenario, cands, valid, logged, logged_valid = tiny_context(["faithful"] * 5)
    record = ContextRecord(1, 1, 0, "tiny", "test", "s", 0, 10, scenario, cands, valid, logged, logged_valid)
    futures, fut_valid, answer, kinds = gold_candidates(record, seed=0)
    assert futures.shape == cands.shape and fut_valid.shape == valid.shape and kinds[answer] == "logged"
    for k, kind in enumerate(kinds):
        moved = (futures[k] - logged)[..., :2].abs().amax()
        assert (moved == 0) if kind == "logged" else (moved > 1.0), (kind, float(moved))


def test_ties_are_stored_and_exported_as_no_pair_or_soft_pairs(store: FeedbackStore, tmp_path) -> None:  # type: ignore[no-untyped-def]
    campaign = make_tiny_campaign(store, num_contexts=3)
    alice = store.add_annotator("alice")[0]
    answers = [TIE_SLOT, 2, 0]
    for slot in answers:
        item = store.next_item(alice, campaign)
        assert item is not None
        label = store.submit_label(alice, campaign, item.context_id, slot)
        assert label.tie == (slot == TIE_SLOT) and label.none_realistic == (slot == 0)
    assert store.counts(campaign)["ties"] == 1
    dropped = export_preferences(store, campaign, val_fraction=0.0)
    assert len(dropped) == 4 + 5 and dropped.pair_prob is None and dropped.metadata["num_ties"] == 1
    soft = export_preferences(store, campaign, val_fraction=0.0, ties="soft")
    assert len(soft) == 10 + 4 + 5 and int((soft.labels == 0.5).sum()) == 10 and soft.num_choices == 3
    tie_pairs = soft.pairs[soft.labels == 0.5]
    assert {(int(w), int(lo)) for _, w, lo in tie_pairs} == {(i, j) for i in range(5) for j in range(i + 1, 5)}
    back = PreferenceDataset.load(soft.save(tmp_path / "soft"))
    assert torch.equal(back.labels, soft.labels)
    assert torch.equal(PreferenceDataset.load(dropped.save(tmp_path / "hard")).labels, torch.ones(9))
    assert len(soft.subset("train")) == len(soft) and soft.subset("train").pair_prob is not None
    with pytest.raises(InvalidChoiceError, match="-1"):
        store.submit_label(alice, campaign, item.context_id, -2)
    no_ties = store.update_settings(campaign, allow_tie=False)
    with pytest.raises(InvalidChoiceError, match="from 0"):
        store.submit_label(alice, no_ties, item.context_id, TIE_SLOT, revise=True)


def test_several_models_per_set_are_recorded(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=1)
    scenario, cands, valid, logged, logged_valid = tiny_context(["faithful", "offroad", "stall", "weave", "collision"],
                                                                scene_index=5)
    models = ["gru", "gru", "cv", "cv", "replay"]
    cid = store.add_context(campaign, "tiny", "test", "mixed", 0, scenario, cands, valid, logged, logged_valid, "t",
                            candidate_models=models)
    assert store.load_context(cid, campaign).candidate_models == tuple(models)
    with pytest.raises(InvalidChoiceError, match="one model per candidate"):
        store.add_context(campaign, "tiny", "test", "bad", 0, scenario, cands, valid, logged, logged_valid, "t",
                          candidate_models=["gru"])
    alice = store.add_annotator("alice")[0]
    while (item := store.next_item(alice, campaign)) is not None:
        store.submit_label(alice, campaign, item.context_id, 1)
    data = export_preferences(store, campaign, val_fraction=0.0)
    keys = {k["scene_id"]: k["models"] for k in data.context_keys}
    assert keys["mixed"] == models and keys["tiny-0000"] == ["tiny"] * 5


def test_priorities_steer_the_order(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=5)
    ids = [k["id"] for k in store.context_keys(campaign)]
    wanted = [ids[3], ids[0], ids[4]]
    store.set_priorities(campaign, priorities_from_ranking(wanted))
    alice = store.add_annotator("alice")[0]
    order = []
    while (item := store.next_item(alice, campaign)) is not None:
        order.append(item.context_id)
        store.submit_label(alice, campaign, item.context_id, 1)
    assert order[:3] == wanted and sorted(order) == sorted(ids)
    with pytest.raises(UnknownItemError):
        store.set_priorities(campaign, {10**9: 1.0})
    assert candidate_disagreement(torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])) == pytest.approx(0.0)
    assert candidate_disagreement(torch.tensor([[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]])) == pytest.approx(2 * 2**0.5 / 3)
    shift = lambda batch: batch.states[:, :, -1, 0]  # noqa: E731 - reward: how far the first agent got
    mean_x = lambda batch: batch.states[:, :, -1, 0].mean(1)  # noqa: E731
    scores = rank_by_disagreement(store, campaign, [lambda b: shift(b)[:, 0], lambda b: -mean_x(b)],
                                  only_unlabeled=False)
    assert set(scores) == set(ids) and all(v >= 0 for v in scores.values())


def test_ids_outside_sqlite_range_are_refused(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=1)
    alice = store.add_annotator("alice")[0]
    for bad in (2**63, 2**64, -1):
        with pytest.raises(UnknownItemError, match="2\\^63"):
            store.open_item(alice, campaign, bad)
        with pytest.raises(UnknownItemError):
            store.submit_label(alice, campaign, bad, 1)


# the schema of version 1 files, as written by earlier SDK releases
V1_SCHEMA = """
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
    UNIQUE (campaign_id, source, split, scene_id), UNIQUE (campaign_id, ordinal)
);
CREATE TABLE IF NOT EXISTS candidates (
    id INTEGER PRIMARY KEY, context_id INTEGER NOT NULL REFERENCES contexts(id), idx INTEGER NOT NULL,
    kind TEXT NOT NULL CHECK (kind IN ('model', 'logged')), tensors BLOB NOT NULL, UNIQUE (context_id, idx)
);
CREATE TABLE IF NOT EXISTS annotators (
    id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, token_sha256 TEXT NOT NULL UNIQUE,
    created_at TEXT NOT NULL, active INTEGER NOT NULL DEFAULT 1
);
CREATE TABLE IF NOT EXISTS assignments (
    id INTEGER PRIMARY KEY, annotator_id INTEGER NOT NULL REFERENCES annotators(id),
    context_id INTEGER NOT NULL REFERENCES contexts(id), campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
    position INTEGER NOT NULL, permutation TEXT NOT NULL, assigned_at TEXT NOT NULL,
    UNIQUE (annotator_id, context_id), UNIQUE (annotator_id, campaign_id, position)
);
CREATE TABLE IF NOT EXISTS labels (
    id INTEGER PRIMARY KEY, context_id INTEGER NOT NULL REFERENCES contexts(id),
    annotator_id INTEGER NOT NULL REFERENCES annotators(id), campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
    slot INTEGER NOT NULL CHECK (slot >= 0), candidate INTEGER, permutation TEXT NOT NULL,
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
CREATE INDEX IF NOT EXISTS labels_by_campaign ON labels (campaign_id, context_id);
CREATE INDEX IF NOT EXISTS contexts_by_campaign ON contexts (campaign_id, ordinal);
"""
V1_TABLES = ("campaigns", "contexts", "candidates", "annotators", "assignments", "labels", "label_history", "skips")


def test_version_1_files_are_migrated(tmp_path) -> None:  # type: ignore[no-untyped-def]
    new = FeedbackStore(tmp_path / "v2.db")
    campaign = make_tiny_campaign(new, num_contexts=2)
    alice = new.add_annotator("alice")[0]
    item = new.next_item(alice, campaign)
    new.submit_label(alice, campaign, item.context_id, 3)
    new.submit_label(alice, campaign, item.context_id, 0, revise=True)
    new.close()
    old_path = tmp_path / "v1.db"
    conn = sqlite3.connect(old_path)
    conn.executescript(V1_SCHEMA)
    conn.execute("ATTACH DATABASE ? AS v2", (str(tmp_path / "v2.db"),))
    for table in V1_TABLES:
        columns = [r[1] for r in conn.execute(f"PRAGMA main.table_info({table})")]
        listed = ", ".join(columns)
        conn.execute(f"INSERT INTO main.{table} ({listed}) SELECT {listed} FROM v2.{table}")
    conn.execute("PRAGMA user_version = 1")
    conn.commit()
    conn.close()
    store = FeedbackStore(old_path)
    assert store._conn().execute("PRAGMA user_version").fetchone()[0] == 2
    campaign = store.campaign("tiny")
    [label] = store.labels(campaign)
    assert label.slot == 0 and label.revision == 1
    assert store.load_context(item.context_id, campaign).candidate_models == ("tiny",) * 5
    assert store.next_item(alice, campaign) is not None
    nxt = store.next_item(alice, campaign)
    store.submit_label(alice, campaign, nxt.context_id, TIE_SLOT)  # the relaxed CHECK accepts ties
    assert store._conn().execute("PRAGMA foreign_key_check").fetchall() == []
    store.close()


def _cli(args: list[str], capsys) -> str:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(args)
    captured = capsys.readouterr()
    assert exit_info.value.code == 0, captured.err
    return captured.out


def test_cli_for_the_campaign_owner(store: FeedbackStore, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    campaign = make_tiny_campaign(store, num_contexts=4)
    db = ["--db", store.path]
    guide = tmp_path / "guide.md"
    guide.write_text("# Judge\n\n- realism first\n", encoding="utf-8")
    out = _cli(["feedback", "settings", *db, "--campaign", "tiny", "--guidelines", str(guide), "--gold-rate", "0.1",
                "--playback-optional", "--no-tie"], capsys)
    shown = json.loads(out)
    assert shown["gold_rate"] == 0.1 and shown["playback_required"] is False and shown["allow_tie"] is False
    assert store.campaign("tiny").settings.guidelines == guide.read_text(encoding="utf-8")
    assert "added 2 gold items" in _cli(["feedback", "gold", *db, "--campaign", "tiny", "--count", "2"], capsys)
    admin = _cli(["feedback", "admin", *db, "owner"], capsys).strip()
    assert store.authenticate_admin(admin) == "owner"
    token = _cli(["feedback", "annotator", "add", *db, "alice"], capsys).strip()
    _cli(["feedback", "annotator", "deactivate", *db, "alice"], capsys)
    with pytest.raises(AuthenticationError):
        store.authenticate(token)
    ids = [k["id"] for k in store.context_keys(campaign) if k["gold_answer"] is None]
    ranking = tmp_path / "ranking.txt"
    ranking.write_text(f"# most wanted first\n{ids[2]}\n{ids[1]}\n", encoding="utf-8")
    assert "2 items" in _cli(["feedback", "prioritize", *db, "--campaign", "tiny", "--ranking", str(ranking)], capsys)
    store.update_settings("tiny", allow_tie=True)
    bob = store.add_annotator("bob")[0]
    campaign = store.campaign("tiny")
    first = store.next_item(bob, campaign)
    assert first is not None and first.context_id == ids[2]
    store.submit_label(bob, campaign, first.context_id, TIE_SLOT)
    second = store.next_item(bob, campaign)
    store.submit_label(bob, campaign, second.context_id, 1)
    out = _cli(["feedback", "export", *db, "--campaign", "tiny", "--out", str(tmp_path / "prefs"), "--ties", "soft",
                "--val-fraction", "0"], capsys)
    assert out.startswith("14 pairs from 2 choices")
    status = _cli(["feedback", "status", *db], capsys)
    assert "4 items (+2 gold)" in status and "(0 none, 1 ties)" in status and "0 items over the cap" in status
