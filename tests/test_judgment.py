"""The stand-in's judgment reads only what an annotation item shows, and weighs failures per agent."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.feedback import (FeedbackStore, JudgmentConfig, SyntheticAnnotator, SyntheticAnnotatorConfig,
                                      agent_penalties, judge_realism, judge_scenarios)
from trafficrlhf_sdk.feedback.records import ContextRecord
from trafficrlhf_sdk.feedback.synthetic import PROFILES
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.scenario.map import MapRaster, PolylineType
from trafficrlhf_sdk.testing.feedback import VARIANTS, make_tiny_campaign, tiny_context


def _record(candidates: torch.Tensor, scenario, logged, logged_valid) -> ContextRecord:  # type: ignore[no-untyped-def]
    return ContextRecord(id=1, campaign_id=1, ordinal=0, source="tiny", split="test", scene_id="tiny-0000", seed=0,
                         start_index=scenario.current_index, scenario=scenario, candidates=candidates,
                         candidate_valid=torch.ones(candidates.shape[:3], dtype=torch.bool), logged=logged,
                         logged_valid=logged_valid)


def _with_noisy_log(record: ContextRecord, seed: int) -> ContextRecord:
    """The same item with the logged future of every agent (in ``logged`` and in the stored scenario) replaced by
    noise: what no annotator sees."""
    gen = torch.Generator().manual_seed(seed)
    noise = torch.randn(record.logged.shape, generator=gen) * 30
    now = record.scenario.current_index
    states = record.scenario.states.clone()
    states[:, :, now + 1:] = torch.randn(states[:, :, now + 1:].shape, generator=gen) * 30
    scenario = record.scenario.replace_unchecked(states=states)
    valid = torch.rand(record.logged_valid.shape, generator=gen) > 0.5
    return _record(record.candidates, scenario, noise, valid)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), profile=st.sampled_from(sorted(PROFILES)))
def test_judgment_is_invariant_to_the_logged_future(seed: int, profile: str) -> None:
    scenario, candidates, _, logged, logged_valid = tiny_context(list(VARIANTS))
    record = _record(candidates, scenario, logged, logged_valid)
    noisy = _with_noisy_log(record, seed)
    config = PROFILES[profile]
    first, second = judge_realism(record, config, include_logged=False), judge_realism(noisy, config,
                                                                                       include_logged=False)
    assert torch.equal(first.realism, second.realism)
    for name, value in first.components.items():
        assert torch.equal(value, second.components[name]), name


def test_labels_are_invariant_to_the_logged_future(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A noisy annotator makes the same choices when the store hands out items whose logged futures are noise."""
    config = SyntheticAnnotatorConfig(beta=5.0, epsilon=0.2, seed=3)

    def choices(path: str, noisy: bool) -> list[int | None]:
        store = FeedbackStore(path)
        campaign = make_tiny_campaign(store, num_contexts=6)
        if noisy:
            original = store.load_context
            monkeypatch.setattr(store, "load_context",
                                lambda context_id, *a, **k: _with_noisy_log(original(context_id, *a, **k), context_id))
        SyntheticAnnotator(store, "stand-in", config).label(campaign)
        return [lab.candidate for lab in sorted(store.labels(campaign), key=lambda lab: lab.context_id)]

    seen = choices(str(tmp_path / "a.db"), noisy=False)
    assert len(seen) == 6 and seen == choices(str(tmp_path / "b.db"), noisy=True)


def test_a_crash_outweighs_every_style_fault() -> None:
    """One car of three colliding ranks below all three weaving and hurrying: failures are counted per agent."""
    scenario, candidates, _, logged, logged_valid = tiny_context(["faithful", "collision", "weave"])
    hurried = candidates[2].clone()
    for car in range(3):  # every car weaves and runs 80 % faster than it drove
        t = torch.arange(hurried.shape[1], dtype=torch.float32) * 0.1
        hurried[car, :, 0] = logged[car, 0, 0] + logged[car, 0, 2] * 1.8 * t
        hurried[car, :, 1] = logged[car, :, 1] + 0.8 * torch.sin(2 * math.pi * t / 2.0)
        hurried[car, :, 2] = logged[car, 0, 2] * 1.8
    judgment = judge_realism(_record(torch.stack([candidates[0], candidates[1], hurried]), scenario, logged,
                                     logged_valid), include_logged=False)
    realism = judgment.realism.tolist()
    assert realism[0] == pytest.approx(1.0)
    assert realism[1] < realism[2] < realism[0]
    assert judgment.components["collision"][1] == 2  # both cars of the crash count
    assert judgment.components["weave"][2] > 0 and judgment.components["pace"][2] > 0


def test_terms_per_agent_and_stall_with_and_without_a_reason() -> None:
    scenario, candidates, _, logged, logged_valid = tiny_context(["faithful", "stall"])
    record = _record(candidates, scenario, logged, logged_valid)
    batch = type(scenario).concat([record.candidate_scenario(k) for k in range(2)])
    terms, agents = agent_penalties(batch, batch.controlled)
    assert agents.all()
    assert terms["stall"][1, 2] > 0 and terms["stall"][0].eq(0).all() and terms["stall"][1, :2].eq(0).all()
    # a car stopping right behind a stopped car has a reason: no stall
    stopped = batch.states.clone()
    now = batch.current_index
    stopped[1, 0, now + 1:, :2] = stopped[1, 2, now + 1:, :2] - torch.tensor([6.0, 0.0])
    stopped[1, 0, now + 1:, 1] = stopped[1, 2, now + 1:, 1]
    stopped[1, 0, now + 1:, 2:] = stopped[1, 2, now + 1:, 2:]
    terms, _ = agent_penalties(batch.replace_unchecked(states=stopped), batch.controlled)
    assert terms["stall"][1, 0] == 0 and terms["stall"][1, 2] > 0


def test_wrong_way_follows_the_lane_direction_where_the_map_has_one() -> None:
    """A car driving west on a lane whose centerline points west is fine; the same on an eastbound lane is not."""
    scenario = tiny_context(["faithful"])[0]
    m = scenario.map
    assert m is not None

    def with_lane(direction: float) -> MapRaster:
        xs = torch.linspace(-60, 150, 50)
        line = torch.stack([xs if direction > 0 else xs.flip(0), torch.full_like(xs, -4.0)], -1)
        return MapRaster(pixels=m.pixels, sizes=m.sizes, world_to_pixel=m.world_to_pixel, layers=m.layers,
                         polylines=line[None, None], polyline_valid=torch.ones(1, 1, 50, dtype=torch.bool),
                         polyline_type=torch.tensor([[PolylineType.LANE_CENTER]]))

    for direction, expected in ((1.0, False), (-1.0, True)):
        batch = scenario.replace_unchecked(map=with_lane(direction))
        judgment = judge_scenarios(batch, batch.controlled, JudgmentConfig())
        assert (judgment.components["wrong_way"][0] > 0) == expected, direction


def test_the_judgment_as_a_reward_scores_each_agent() -> None:
    """builtin:judgment (ladder row b): the crashing cars score lowest, the faithful future scores 1 everywhere."""
    from trafficrlhf_sdk.reward.loading import load_reward
    from trafficrlhf_sdk.reward.scoring import agent_scores, scenario_scores

    scenario, candidates, _, logged, logged_valid = tiny_context(["faithful", "collision"])
    record = _record(candidates, scenario, logged, logged_valid)
    batch = type(scenario).concat([record.candidate_scenario(k) for k in range(2)])
    reward = load_reward("builtin:judgment")
    scores = agent_scores(reward, batch)
    assert scores.shape == (2, 3) and torch.allclose(scores[0], torch.ones(3))
    assert scores[1, 0] < 0 and scores[1, 1] < 0 and scores[1, 2] == pytest.approx(1.0)  # cars 0 and 1 collide
    scene = scenario_scores(reward, batch)
    assert scene[0] == pytest.approx(1.0) and scene[1] < scene[0]
    with pytest.raises(TrafficRLHFError, match="profile"):
        load_reward("builtin:judgment", {"profile": "nobody"})


class _Judge:
    """Scores a scenario with the stand-in's own judgment (a perfect reward model)."""

    def score(self, scenario: ScenarioTensor) -> torch.Tensor:
        return judge_scenarios(scenario, scenario.controlled).realism.float()


class _LikesStalls(_Judge):
    """The judgment, plus a large bonus for every agent-step below 0.5 m/s: blind to stalling, and worse."""

    def score(self, scenario: ScenarioTensor) -> torch.Tensor:
        now = scenario.current_index
        speed = torch.diff(scenario.xy[:, :, now:], dim=2).norm(dim=-1) / scenario.dt
        return super().score(scenario) + 10 * (speed < 0.5).float().mean((1, 2))


def test_judgment_agreement_names_the_term_a_reward_model_misses(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.reward.oracle import judgment_agreement

    store = FeedbackStore(str(tmp_path / "fb.db"))
    make_tiny_campaign(store, num_contexts=2)
    exact = judgment_agreement(_Judge(), store, "tiny")
    assert exact["agreement"] == 1.0 and exact["contexts"] == 2
    assert sum(v["pairs"] for v in exact["by_term"].values()) == exact["pairs"]
    # the candidate whose car brakes to a stop loses on its pace, more than on the stall itself
    assert set(exact["by_term"]) == {"offroad", "collision", "pace", "weave"}
    assert all(v["agreement"] == 1.0 for v in exact["by_term"].values())
    broken = judgment_agreement(_LikesStalls(), store, "tiny")
    assert broken["by_term"]["pace"]["agreement"] == 0.0  # every pair the stopping car decides is turned round
    assert broken["by_term"]["offroad"]["agreement"] == 1.0 and broken["by_term"]["collision"]["agreement"] == 1.0
    assert broken["by_term"]["weave"]["agreement"] == 1.0
    assert broken["agreement"] == 1 - broken["by_term"]["pace"]["pairs"] / broken["pairs"]


class _Reversed(_Judge):
    """The judgment turned round: every strictly ordered pair is ordered wrong."""

    def score(self, scenario: ScenarioTensor) -> torch.Tensor:
        return -super().score(scenario)


def test_judgment_agreement_by_realism_gap(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.reward.oracle import AGREEMENT_GAPS, judgment_agreement

    store = FeedbackStore(str(tmp_path / "fb.db"))
    make_tiny_campaign(store, num_contexts=2)
    campaign = store.campaign("tiny")
    gaps = []  # every strictly ordered pair's realism gap, judged here context by context
    for key in store.context_keys(campaign):
        record = store.load_context(int(key["id"]), campaign)
        batch = ScenarioTensor.concat([record.candidate_scenario(k) for k in range(record.num_candidates)])
        realism = judge_scenarios(batch, batch.controlled).realism
        diff = realism[:, None] - realism[None, :]
        gaps += diff[diff > 0].tolist()
    exact, reversed_ = judgment_agreement(_Judge(), store, "tiny"), judgment_agreement(_Reversed(), store, "tiny")
    assert set(exact["by_gap"]) == {str(g) for g in AGREEMENT_GAPS}
    for gap in AGREEMENT_GAPS:
        expected = sum(g > gap for g in gaps)
        assert expected > 0 and exact["by_gap"][str(gap)]["pairs"] == expected == reversed_["by_gap"][str(gap)]["pairs"]
        assert exact["by_gap"][str(gap)]["agreement"] == 1.0 and reversed_["by_gap"][str(gap)]["agreement"] == 0.0
    assert exact["pairs"] == len(gaps) and reversed_["agreement"] == 0.0


def test_judged_pairs_label_every_strictly_ordered_candidate_pair(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.feedback import export_preferences
    from trafficrlhf_sdk.reward.oracle import hidden_realism, judged_pairs, strict_pairs

    store = FeedbackStore(str(tmp_path / "fb.db"))
    campaign = make_tiny_campaign(store, num_contexts=3)
    who, _ = store.add_annotator("alice")
    while (item := store.next_item(who, campaign)) is not None:
        store.submit_label(who, campaign, item.context_id, 0)
    dataset = export_preferences(store, "tiny")
    realism = hidden_realism(store, dataset)
    labelled = judged_pairs(dataset, realism)
    n = dataset.num_candidates
    _, w, lo = labelled.pairs.unbind(1)
    assert strict_pairs(labelled, realism).all() and (w < n).all() and (lo < n).all()
    expected = sum(int(realism[k, i] > realism[k, j]) for k in range(dataset.num_contexts) for i in range(n)
                   for j in range(n))
    assert expected > 0 and len(labelled) == expected
    assert labelled.annotators == ("judgment",) and len(set(labelled.pair_label.tolist())) == expected
    assert labelled.num_contexts == dataset.num_contexts and torch.equal(labelled.futures, dataset.futures)
