"""Preference export: N-1 pairs per choice, logged ≻ each candidate on 'none', split by context; renders."""

from __future__ import annotations

import dataclasses
import json
import os

import pytest
import torch

from trafficrlhf_sdk.cli import main
from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.feedback import FeedbackStore, PreferenceDataset, export_preferences
from trafficrlhf_sdk.feedback.preference import split_contexts
from trafficrlhf_sdk.feedback.render import save_candidate_animation, save_candidate_strip
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign


@pytest.fixture()
def labeled(tmp_path):  # type: ignore[no-untyped-def]
    """A tiny campaign of 6 items; alice answers slot 2 everywhere, bob 'none realistic' everywhere."""
    store = FeedbackStore(tmp_path / "fb.db")
    campaign = make_tiny_campaign(store, num_contexts=6)
    for name, slot in (("alice", 2), ("bob", 0)):
        who, _ = store.add_annotator(name)
        while (item := store.next_item(who, campaign)) is not None:
            store.submit_label(who, campaign, item.context_id, slot)
    yield store
    store.close()


def test_pairs_follow_the_choices(labeled: FeedbackStore) -> None:
    dataset = export_preferences(labeled, "tiny", val_fraction=0.34)
    n = dataset.num_candidates
    assert n == 5 and dataset.num_contexts == 6 and dataset.num_choices == 12
    assert len(dataset) == 6 * (n - 1) + 6 * n  # alice: N-1 pairs per choice; bob ('none'): N pairs per choice
    labels = {lab.id: lab for lab in labeled.labels(labeled.campaign("tiny"))}
    for (context, winner, loser), label_id in zip(dataset.pairs.tolist(), dataset.pair_label.tolist()):
        label = labels[label_id]
        assert dataset.context_keys[context]["context_id"] == label.context_id
        assert winner == (n if label.candidate is None else label.candidate) and loser != winner and loser < n
    winners, losers = dataset.pair_scenarios(torch.arange(3))
    assert winners.num_scenes == 3 and winners.current_index == 10 and winners.num_steps == 41
    c, w, lo = dataset.pairs[0].tolist()
    assert torch.equal(winners.states[0, :, 11:], dataset.futures[c, w])
    assert torch.equal(losers.states[0, :, 11:], dataset.futures[c, lo])
    assert torch.equal(winners.states[0, :, :11], losers.states[0, :, :11])  # same context


def test_split_is_by_context(labeled: FeedbackStore) -> None:
    dataset = export_preferences(labeled, "tiny", val_fraction=0.34, seed=1)
    train, val = dataset.subset("train"), dataset.subset("val")
    assert val.num_contexts == 2 and train.num_contexts == 4 and len(train) + len(val) == len(dataset)
    train_ids = {k["context_id"] for k in train.context_keys}
    val_ids = {k["context_id"] for k in val.context_keys}
    assert not train_ids & val_ids
    keys = [f"k{i}" for i in range(10)]
    assert split_contexts(keys, 0.2) == split_contexts(keys, 0.2)
    assert split_contexts(keys, 0.2).count("val") == 2 and split_contexts(["a", "b"], 0.01).count("val") == 1
    with pytest.raises(ValueError, match="val_fraction"):
        split_contexts(keys, 1.0)


def test_save_load_round_trip(labeled: FeedbackStore, tmp_path) -> None:  # type: ignore[no-untyped-def]
    dataset = export_preferences(labeled, "tiny")
    out = dataset.save(tmp_path / "prefs")
    assert sorted(os.listdir(out)) == ["metadata.json", "preferences.safetensors"]
    meta = json.load(open(os.path.join(out, "metadata.json")))
    assert meta["num_pairs"] == len(dataset) and meta["campaign"] == "tiny" and meta["num_none_realistic"] == 6
    loaded = PreferenceDataset.load(out)
    for name in ("futures", "future_valid", "pairs", "pair_annotator", "pair_label"):
        assert torch.equal(getattr(loaded, name), getattr(dataset, name))
    assert torch.equal(loaded.contexts.states, dataset.contexts.states) and loaded.contexts.map is not None
    assert loaded.context_split == dataset.context_split and loaded.annotators == ("alice", "bob")
    with open(os.path.join(out, "preferences.safetensors"), "r+b") as handle:
        handle.truncate(200)
    with pytest.raises(DataFormatError):
        PreferenceDataset.load(out)


def test_export_needs_labels(tmp_path) -> None:  # type: ignore[no-untyped-def]
    store = FeedbackStore(tmp_path / "empty.db")
    make_tiny_campaign(store, num_contexts=1)
    with pytest.raises(DataFormatError, match="no labels"):
        export_preferences(store, "tiny")


def test_cli_export_render_status(labeled: FeedbackStore, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    db = labeled.path
    for args in (["export", "--out", str(tmp_path / "cli_prefs"), "--val-fraction", "0.5"],
                 ["render", "--out", str(tmp_path / "strip.png"), "--with-log"],
                 ["status"]):
        with pytest.raises(SystemExit) as exit_info:
            main(["feedback", args[0], "--db", db, *(["--campaign", "tiny"] if args[0] != "status" else []), *args[1:]])
        assert exit_info.value.code == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert "54 pairs from 12 choices over 6 contexts (3 train / 3 val)" in out
    assert "Fleiss' kappa" in out and "12 labels (6 none, 0 ties) by 2 annotators" in out
    assert open(tmp_path / "strip.png", "rb").read(8) == b"\x89PNG\r\n\x1a\n"


def test_animation_gif(labeled: FeedbackStore, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from PIL import Image

    campaign = labeled.campaign("tiny")
    record = labeled.load_context(labeled.context_keys(campaign)[0]["id"])
    path = save_candidate_animation(record, tmp_path / "set.gif", every=5)
    with Image.open(path) as gif:
        assert gif.n_frames == 9 and gif.info["duration"] == 500  # 1 s of history + 3 s, every 0.5 s, real time
    strip = save_candidate_strip(record, tmp_path / "set.png", include_logged=True)
    with Image.open(strip) as png:
        assert png.width > 3 * png.height  # six panels side by side
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        save_candidate_animation(record, tmp_path / "set.avi")


def test_concat_pools_campaigns(labeled: FeedbackStore) -> None:
    """Two rounds' campaigns pooled: every pair still points at the same futures, annotators merged by name."""
    second = make_tiny_campaign(labeled, num_contexts=3, name="round2")
    who, _ = labeled.add_annotator("carol")
    while (item := labeled.next_item(who, second)) is not None:
        labeled.submit_label(who, second, item.context_id, 4)
    first, other = export_preferences(labeled, "tiny", 0.34), export_preferences(labeled, "round2", 0.34)
    # shorter candidates in the second round: the pooled futures are padded with invalid steps
    other = dataclasses.replace(other, futures=other.futures[..., :-2, :], future_valid=other.future_valid[..., :-2])
    pooled = PreferenceDataset.concat([first, other])
    assert pooled.num_contexts == 9 and len(pooled) == len(first) + len(other)
    assert pooled.annotators == ("alice", "bob", "carol") and pooled.num_choices == first.num_choices + 3
    assert pooled.context_split == first.context_split + other.context_split
    for part, start, offset in ((first, 0, 0), (other, len(first), first.num_contexts)):
        for k in (0, len(part) - 1):
            w_pool, l_pool = pooled.pair_scenarios([start + k])
            w_part, l_part = part.pair_scenarios([k])
            a, t = w_part.num_agents, w_part.num_steps
            assert torch.equal(w_pool.states[:, :a, :t], w_part.states)
            assert torch.equal(l_pool.valid[:, :a, :t], l_part.valid) and not l_pool.valid[:, :, t:].any()
            assert int(pooled.pairs[start + k, 0]) == int(part.pairs[k, 0]) + offset
            name = part.annotators[int(part.pair_annotator[k])]
            assert pooled.annotators[int(pooled.pair_annotator[start + k])] == name
    assert PreferenceDataset.concat([first]) is first
    with pytest.raises(ValueError, match="empty"):
        PreferenceDataset.concat([])


def test_concat_aligns_campaigns_with_different_histories_at_the_candidates_start(labeled: FeedbackStore) -> None:
    """A campaign whose candidates start after a shorter history pools with a shorter one: its histories are cut to
    the shortest, and every pair's futures and recent history are unchanged."""
    first = export_preferences(labeled, "tiny", 0.34)
    shorter = dataclasses.replace(first, contexts=first.contexts.time_slice(1))  # one step less of history
    short_now, long_now = shorter.contexts.current_index, first.contexts.current_index
    pooled = PreferenceDataset.concat([first, shorter])
    assert pooled.contexts.current_index == short_now == long_now - 1
    for part, start in ((first, 0), (shorter, len(first))):
        w_pool, _ = pooled.pair_scenarios([start])
        w_part, _ = part.pair_scenarios([0])
        cut = part.contexts.current_index - short_now
        torch.testing.assert_close(w_pool.states[:, : w_part.num_agents, : w_part.num_steps - cut],
                                   w_part.states[:, :, cut:])
