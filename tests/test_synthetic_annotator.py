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
    assert counts == {"labeled": 5, "none_realistic": 0, "ties": 0, "skipped": 0}
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
    assert skipper == {"labeled": 0, "none_realistic": 0, "ties": 0, "skipped": 3}


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


def _record_with(candidates: torch.Tensor, scenario, logged, logged_valid):  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.feedback.records import ContextRecord

    return ContextRecord(id=1, campaign_id=1, ordinal=0, source="tiny", split="test", scene_id="tiny-0000", seed=0,
                         start_index=scenario.current_index, scenario=scenario, candidates=candidates,
                         candidate_valid=torch.ones(candidates.shape[:3], dtype=torch.bool), logged=logged,
                         logged_valid=logged_valid)


def test_judgment_notices_pace_stop_and_go_and_lane_keeping() -> None:
    """The log re-timed faster (1.5x) or slower (half speed) than the cars drove before and than their neighbours
    costs pace, an oscillating clock stop-and-go, a sideways drift lane keeping; the faithful copy costs nothing,
    and every fault ranks below it."""
    from trafficrlhf_sdk.reward.contrast import perturb_future
    from trafficrlhf_sdk.testing.feedback import tiny_context

    scenario, _, _, logged, logged_valid = tiny_context(["faithful"])
    now = scenario.current_index
    variants = {"faithful": scenario.states[0, :, now + 1:]}
    for kind, strength in (("faster", 0.5), ("slower", 1.0), ("jerky", 0.5), ("off_lane", 0.5)):
        variants[kind] = perturb_future(scenario, kind, strength)[0].states[0, :, now + 1:]
    judgment = judge_realism(_record_with(torch.stack(list(variants.values())), scenario, logged, logged_valid),
                             include_logged=False)
    realism = dict(zip(variants, judgment.realism.tolist()))
    c = {k: dict(zip(variants, v.tolist())) for k, v in judgment.components.items()}
    assert realism["faithful"] == pytest.approx(1.0)
    assert all(realism[k] < realism["faithful"] - 0.05 for k in variants if k != "faithful"), realism
    assert c["pace"]["faster"] > 0 and c["pace"]["slower"] > 0 and c["pace"]["faithful"] == 0
    assert c["stop_go"]["jerky"] > 0 and c["lane"]["off_lane"] > 0 and c["lane"]["faithful"] == 0


def test_judgment_notices_tailgating_and_driving_against_the_flow() -> None:
    from trafficrlhf_sdk.testing.feedback import tiny_context

    scenario, _, _, logged, logged_valid = tiny_context(["faithful"])
    tail = logged.clone()
    tail[0, :, 0] = logged[2, :, 0] - 6.0  # car 0 right behind car 2 ...
    tail[0, :, 1] = logged[2, :, 1]  # ... in its lane
    tail[0, :, 2] = logged[2, :, 2]
    wrong = logged.clone()
    wrong[1, :, 3] = logged[1, :, 3] + torch.pi  # car 1 drives with its nose backwards
    judgment = judge_realism(_record_with(torch.stack([logged, tail, wrong]), scenario, logged, logged_valid),
                             include_logged=False)
    assert judgment.components["tailgate"][1] > 0 and judgment.components["tailgate"][0] == 0
    assert judgment.components["wrong_way"][2] > 0 and judgment.components["wrong_way"][0] == 0


def test_profiles_disagree_and_ties_are_answered_when_allowed() -> None:
    from trafficrlhf_sdk.feedback.records import TIE_SLOT
    from trafficrlhf_sdk.feedback.synthetic import PROFILES

    assert len({(p.weight_pace, p.weight_collision, p.beta, p.epsilon) for p in PROFILES.values()}) == len(PROFILES)
    annotator = SyntheticAnnotator.__new__(SyntheticAnnotator)
    annotator.config = SyntheticAnnotatorConfig(tie_margin=0.05)
    even = torch.tensor([0.90, 0.92, 0.91])
    gen = torch.Generator().manual_seed(0)
    assert annotator.choose(even, gen, allow_tie=True) == TIE_SLOT
    assert annotator.choose(even, gen, allow_tie=False) in (0, 1, 2)
    assert annotator.choose(torch.tensor([0.5, 0.95, 0.6]), gen, allow_tie=True) != TIE_SLOT
