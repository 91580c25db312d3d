"""The feedback store: schema, WAL, transactions, tokens, assignments, labels, skips; campaign generation."""

from __future__ import annotations

import os
import sqlite3
import threading

import pytest
import torch

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.feedback import (
    AuthenticationError,
    DuplicateSubmissionError,
    FeedbackStore,
    InvalidChoiceError,
    ItemStateError,
    UnknownCampaignError,
    UnknownItemError,
)
from trafficrlhf_sdk.feedback.campaign import (
    CampaignConfig,
    campaign_policy,
    create_campaign,
    crop_map,
    extend_campaign,
)
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign, tiny_context


@pytest.fixture()
def store(tmp_path):  # type: ignore[no-untyped-def]
    s = FeedbackStore(tmp_path / "fb.db")
    yield s
    s.close()


def _count(store: FeedbackStore, table: str) -> int:
    return sqlite3.connect(store.path).execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]


def test_schema_wal_and_round_trip(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=2)
    assert store._conn().execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert store._conn().execute("PRAGMA user_version").fetchone()[0] == 2
    keys = store.context_keys(campaign)
    assert [k["ordinal"] for k in keys] == [0, 1]
    record = store.load_context(keys[1]["id"], campaign)
    scenario, cands, _, logged, _ = tiny_context(["offroad", "collision", "stall", "weave", "faithful"], 1)
    assert torch.equal(record.candidates, cands) and torch.equal(record.logged, logged)
    assert torch.equal(record.scenario.states, scenario.states) and record.scenario.map is not None
    assert record.candidate_scenario(None).num_steps == scenario.num_steps
    with pytest.raises(UnknownItemError):
        store.load_context(999, campaign)
    with pytest.raises(UnknownCampaignError, match="campaigns there: \\['tiny'\\]"):
        store.campaign("nope")
    with pytest.raises(DuplicateSubmissionError, match="--extend"):
        make_tiny_campaign(store)


def test_tokens_are_hashed_and_checked(store: FeedbackStore) -> None:
    annotator, token = store.add_annotator("alice")
    assert len(token) >= 32
    wal = store.path + "-wal"
    raw = open(store.path, "rb").read() + (open(wal, "rb").read() if os.path.exists(wal) else b"")
    assert token.encode() not in raw
    assert store.authenticate(token) == annotator
    for bad in (None, "", "x" * 32, token + "x"):
        with pytest.raises(AuthenticationError):
            store.authenticate(bad)
    fresh = store.new_token("alice")
    with pytest.raises(AuthenticationError):
        store.authenticate(token)
    assert store.authenticate(fresh).name == "alice"
    with pytest.raises(DuplicateSubmissionError):
        store.add_annotator("alice")


def test_assignment_resume_permutation_and_labels(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=3)
    alice, _ = store.add_annotator("alice")
    first = store.next_item(alice, campaign)
    assert first is not None and sorted(first.permutation) == list(range(5))
    assert store.next_item(alice, campaign) == first  # resume: same item, same order, nothing new assigned
    label = store.submit_label(alice, campaign, first.context_id, 2, time_on_item_ms=1500)
    assert label.candidate == first.permutation[1] and label.slot == 2 and label.source == "human"
    with pytest.raises(DuplicateSubmissionError, match="nothing was written"):
        store.submit_label(alice, campaign, first.context_id, 3)
    assert _count(store, "labels") == 1
    revised = store.submit_label(alice, campaign, first.context_id, 0, revise=True)
    assert revised.none_realistic and revised.revision == 1 and _count(store, "label_history") == 1
    second = store.next_item(alice, campaign)
    assert second is not None and second.context_id != first.context_id and second.position == 2
    store.skip(alice, campaign, second.context_id, "can't tell")
    with pytest.raises(DuplicateSubmissionError):
        store.skip(alice, campaign, second.context_id, "again")
    store.submit_label(alice, campaign, second.context_id, 1)  # a label replaces the skip
    assert _count(store, "skips") == 0
    assert [a.status for a in store.history(alice, campaign)] == ["labeled", "labeled"]
    assert store.progress(alice, campaign) == {"labeled": 2, "skipped": 0, "done": 2, "total": 3}


def test_bad_writes_raise_and_write_nothing(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=2)
    alice, _ = store.add_annotator("alice")
    item = store.next_item(alice, campaign)
    assert item is not None
    other = next(k["id"] for k in store.context_keys(campaign) if k["id"] != item.context_id)
    for choice in (-2, 6, True, "1", 1.0):
        with pytest.raises(InvalidChoiceError, match="from 0"):
            store.submit_label(alice, campaign, item.context_id, choice)  # type: ignore[arg-type]
    with pytest.raises(ItemStateError, match="never opened"):
        store.submit_label(alice, campaign, other, 1)
    with pytest.raises(UnknownItemError):
        store.submit_label(alice, campaign, 12345, 1)
    with pytest.raises(InvalidChoiceError):
        store.skip(alice, campaign, item.context_id, "  ")
    with pytest.raises(ItemStateError):
        store.submit_label(alice, campaign, item.context_id, 1, revise=True)
    assert _count(store, "labels") == 0 and _count(store, "skips") == 0


def test_transaction_rolls_back_everything(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=1)
    with pytest.raises(RuntimeError):
        with store.transaction() as tx:
            tx.execute("INSERT INTO annotators (name, token_sha256, created_at) VALUES ('x', 'h', 'now')")
            raise RuntimeError("crash in the middle of a write")
    assert _count(store, "annotators") == 0
    scenario, cands, valid, logged, logged_valid = tiny_context(["faithful"] * 5, 7)
    with pytest.raises(InvalidChoiceError, match="shapes do not fit"):
        store.add_context(campaign, "tiny", "test", "bad", 0, scenario, cands, valid[:, :, :5], logged, logged_valid,
                          "t")
    # a failure after the context row is inserted (while writing the logged future) must undo that row too
    from trafficrlhf_sdk.feedback import store as store_module

    real = store_module.encode_future
    calls = {"n": 0}

    def failing(states, valid):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] > 5:
            raise OSError("disk full")
        return real(states, valid)

    store_module.encode_future = failing  # type: ignore[assignment]
    try:
        with pytest.raises(OSError):
            store.add_context(campaign, "tiny", "test", "broken", 0, scenario, cands, valid, logged, logged_valid, "t")
    finally:
        store_module.encode_future = real  # type: ignore[assignment]
    assert _count(store, "contexts") == 1 and _count(store, "candidates") == 6


def test_labels_per_item_spreads_items(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=4, labels_per_item=1)
    a, _ = store.add_annotator("a")
    b, _ = store.add_annotator("b")
    seen = {}
    for who in (a, b, a, b):
        item = store.next_item(who, campaign)
        assert item is not None
        store.submit_label(who, campaign, item.context_id, 1)
        seen.setdefault(who.name, []).append(item.context_id)
    assert not set(seen["a"]) & set(seen["b"])
    assert store.next_item(a, campaign) is None and store.progress(a, campaign)["total"] == 2


def test_concurrent_writers_lose_nothing(store: FeedbackStore) -> None:
    campaign = make_tiny_campaign(store, num_contexts=6)
    annotators = [store.add_annotator(f"w{i}")[0] for i in range(6)]
    errors: list[BaseException] = []

    def work(who) -> None:  # type: ignore[no-untyped-def]
        try:
            while (item := store.next_item(who, campaign)) is not None:
                store.submit_label(who, campaign, item.context_id, 1 + item.context_id % 5)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(who,)) for who in annotators]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors
    assert len(store.labels(campaign)) == 36 and store.counts(campaign)["annotators"] == 6


def test_crop_map_keeps_lookups() -> None:
    scenario = tiny_context(["faithful"], 0)[0]
    xy = scenario.xy[0, :, :, :].reshape(-1, 2)
    cropped = crop_map(scenario.map, xy, 5.0)  # type: ignore[arg-type]
    assert cropped.sizes[0, 1] <= scenario.map.sizes[0, 1]  # type: ignore[union-attr]
    probe = xy[None] + torch.tensor([0.0, 1.3])
    assert torch.equal(cropped.lookup(probe), scenario.map.lookup(probe))  # type: ignore[union-attr]


def test_campaign_policy_rejects_guidance_it_cannot_use() -> None:
    with pytest.raises(TrafficRLHFError, match="does not accept guidance"):
        campaign_policy("constant_velocity", "no_collision", 0)
    assert campaign_policy("noisy_log", None, 3).seed == 3


@pytest.mark.data
def test_create_and_extend_campaign_on_real_data(tmp_path, nuscenes_source) -> None:  # type: ignore[no-untyped-def]
    config = CampaignConfig(name="real", model="noisy_log", num_contexts=2, num_candidates=3, candidate_seconds=2.0,
                            root=nuscenes_source.root, model_options={"position_noise_m": 2.0})
    store = FeedbackStore(tmp_path / "real.db")
    report = create_campaign(store, config)
    assert len(report.added) == 2
    record = store.load_context(report.added[0])
    assert record.candidates.shape[0] == 3 and record.candidates.shape[2] == 20
    assert record.scenario.current_index == 30 and record.controlled.any()
    assert not torch.equal(record.candidates[0], record.candidates[1])  # N different futures
    campaign = report.campaign
    assert campaign.config["provenance"]["model_plugin"] == "trafficrlhf_sdk.default_plugins.policies"
    assert campaign.sdk_version and campaign.seed == 0 and campaign.model == "noisy_log"
    before = sqlite3.connect(store.path).execute("SELECT id, scenario FROM contexts").fetchall()
    extended = extend_campaign(store, "real", num_contexts=3)
    assert len(extended.added) == 1 and len(extended.skipped) == 2
    after = sqlite3.connect(store.path).execute("SELECT id, scenario FROM contexts").fetchall()
    assert after[:2] == before  # existing contexts untouched
    again = create_campaign(FeedbackStore(tmp_path / "again.db"), config)  # same seed: same candidates
    assert torch.equal(FeedbackStore(tmp_path / "again.db").load_context(again.added[0]).candidates, record.candidates)


@pytest.mark.data
def test_closed_loop_contexts_start_from_the_models_own_driving(tmp_path, nuscenes_source) -> None:  # type: ignore[no-untyped-def]
    """Constant velocity leaves the road: its context is cut one second before its first failure, the history is
    its own driving up to the cut (the log after it) and as long as a logged context's; a policy that never fails
    is cut at a random step of its drive, with the log as history."""
    from trafficrlhf_sdk.feedback.campaign import _open_source, closed_loop_context
    from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_per_step
    from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

    config = CampaignConfig(name="cl", model="constant_velocity", contexts="closed_loop", candidate_seconds=2.0,
                            drive_seconds=6.0, root=nuscenes_source.root)
    source = _open_source(config)
    cut_before_failure = 0
    for scene_id in source.scene_ids("val")[:6]:
        scene = source.load_scene("val", scene_id)
        start = scene.current_index
        context = closed_loop_context(campaign_policy("constant_velocity", None, 0), scene, 6.0, 2.0, seed=1)
        cut = scene.num_steps - context.num_steps + start
        assert context.current_index == start and start <= cut <= start + 60
        driven = simulate(campaign_policy("constant_velocity", None, 0), scene, SimulationConfig(duration_s=6.0))
        sim = driven.simulated
        failed = (collisions_per_step(sim) | offroad_per_step(sim))[0] & sim.valid[0] & driven.controlled[0][:, None]
        failed[:, : start + 1] = False
        mine = context.valid[0, :, : start + 1]
        assert torch.equal(context.states[0, :, : start + 1][mine], sim.states[0, :, cut - start: cut + 1][mine])
        if failed.any():
            first = int(torch.arange(sim.num_steps)[failed.any(0)].min())
            assert cut == max(start, first - 10)
            cut_before_failure += 1
        replay = closed_loop_context(campaign_policy("log_replay", None, 0), scene, 6.0, 2.0, seed=1)
        cut = scene.num_steps - replay.num_steps + start
        same = replay.valid[0, :, : start + 1]
        assert torch.allclose(replay.states[0, :, : start + 1][same], scene.states[0, :, cut - start: cut + 1][same])
    assert cut_before_failure >= 3
    store = FeedbackStore(tmp_path / "cl.db")
    report = create_campaign(store, config.model_copy(update={"num_contexts": 2, "num_candidates": 2}))
    assert len(report.added) == 2 and store.load_context(report.added[0]).candidates.shape[2] == 20
    with pytest.raises(ValueError, match="closed_loop"):
        CampaignConfig(name="x", model="a", contexts="closed_loop", num_candidates=2, candidate_models=["a", "b"])
