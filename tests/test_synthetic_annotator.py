"""The synthetic annotator: hidden realism judgment, B-Pref-style noise, labeling through the store."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.cli import main
from trafficrlhf_sdk.feedback import FeedbackStore, SyntheticAnnotator, SyntheticAnnotatorConfig, judge_realism
from trafficrlhf_sdk.testing.feedback import VARIANTS, make_tiny_campaign


@pytest.fixture()
def store(tmp_path):  # type: ignore[no-untyped-def]
    s = FeedbackStore(tmp_path / "fb.db")
    make_tiny_campaign(s, num_contexts=5)
    yield s
    s.close()


def _variant(ordinal: int, candidate: int) -> str:
    return VARIANTS[(ordinal + candidate) % len(VARIANTS)]


def test_judgment_ranks_faults(store: FeedbackStore) -> None:
    campaign = store.campaign("tiny")
    record = store.load_context(store.context_keys(campaign)[0]["id"])  # candidates in VARIANTS order, then log
    judgment = judge_realism(record)
    realism = dict(zip([*VARIANTS, "logged"], judgment.realism.tolist()))
    assert realism["faithful"] == pytest.approx(1.0) and realism["logged"] == pytest.approx(1.0)
    assert max(realism["offroad"], realism["collision"], realism["stall"], realism["weave"]) < 0.99
    c = {k: v.tolist() for k, v in judgment.components.items()}
    assert c["offroad"][1] > 0 and c["collision"][2] > 0 and c["stall"][3] > 0 and c["accel"][4] > 0
    assert c["collision"][0] == c["offroad"][0] == c["stall"][0] == 0


def test_rational_annotator_picks_the_faithful_candidate(store: FeedbackStore) -> None:
    campaign = store.campaign("tiny")
    counts = SyntheticAnnotator(store, "oracle", SyntheticAnnotatorConfig(beta=None)).label(campaign)
    assert counts == {"labeled": 5, "none_realistic": 0, "skipped": 0}
    ordinal = {k["id"]: k["ordinal"] for k in store.context_keys(campaign)}
    for label in store.labels(campaign):
        assert label.source == "synthetic"
        assert _variant(ordinal[label.context_id], label.candidate) == "faithful"  # type: ignore[arg-type]
        assert label.permutation[label.slot - 1] == label.candidate  # went through the shuffled slots


def test_none_threshold_mistakes_and_skips(store: FeedbackStore) -> None:
    campaign = store.campaign("tiny")
    picky = SyntheticAnnotator(store, "picky", SyntheticAnnotatorConfig(none_threshold=1.0)).label(campaign)
    assert picky["none_realistic"] == 5
    SyntheticAnnotator(store, "wrong", SyntheticAnnotatorConfig(beta=None, epsilon=1.0)).label(campaign)
    ordinal = {k["id"]: k["ordinal"] for k in store.context_keys(campaign)}
    wrong = [lab for lab in store.labels(campaign) if lab.annotator_id == store.annotator("wrong").id]
    assert all(_variant(ordinal[lab.context_id], lab.candidate) != "faithful" for lab in wrong)  # type: ignore[arg-type]
    skipper = SyntheticAnnotator(store, "skipper", SyntheticAnnotatorConfig(skip_rate=1.0)).label(campaign, limit=3)
    assert skipper == {"labeled": 0, "none_realistic": 0, "skipped": 3}


def test_seeded_and_reproducible(tmp_path) -> None:  # type: ignore[no-untyped-def]
    def run(path: str, seed: int) -> list[int | None]:
        s = FeedbackStore(path)
        campaign = make_tiny_campaign(s, num_contexts=5)
        SyntheticAnnotator(s, "noisy", SyntheticAnnotatorConfig(beta=2.0, epsilon=0.3, seed=seed)).label(campaign)
        return [lab.candidate for lab in sorted(s.labels(campaign), key=lambda lab: lab.context_id)]

    first = run(str(tmp_path / "a.db"), 0)
    assert first == run(str(tmp_path / "b.db"), 0)
    assert any(run(str(tmp_path / f"s{seed}.db"), seed) != first for seed in (1, 2, 3))


def test_choose_softmax_follows_beta() -> None:
    annotator = SyntheticAnnotator.__new__(SyntheticAnnotator)
    realism = torch.tensor([0.9, 0.5, 0.5])
    generator = torch.Generator().manual_seed(0)
    annotator.config = SyntheticAnnotatorConfig(beta=50.0)
    assert all(annotator.choose(realism, generator) == 0 for _ in range(50))
    annotator.config = SyntheticAnnotatorConfig(beta=0.01)
    picks = {annotator.choose(realism, generator) for _ in range(200)}
    assert picks == {0, 1, 2}  # nearly uniform


def test_cli_label_synthetic(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    db = str(tmp_path / "fb.db")
    make_tiny_campaign(FeedbackStore(db), num_contexts=3)
    with pytest.raises(SystemExit) as exit_info:
        main(["feedback", "label", "--synthetic", "--db", db, "--campaign", "tiny", "--annotator", "s1", "--beta", "0"])
    assert exit_info.value.code == 0
    assert "s1: labeled 3 items" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        main(["feedback", "label", "--db", db, "--campaign", "tiny"])
    assert exit_info.value.code == 2
    with pytest.raises(SystemExit) as exit_info:
        main(["feedback", "status", "--db", db, "--campaign", "nope"])
    assert exit_info.value.code == 2 and "no campaign 'nope'" in capsys.readouterr().err
