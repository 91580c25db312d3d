"""Automatic contrast pairs and reward-model probes (trafficrlhf_sdk.reward.contrast)."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.reward.contrast import (
    CONTRAST_ANNOTATOR,
    PERTURBATIONS,
    contrast_dataset,
    perturb_future,
    probe_reward_model,
)
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.testing.feedback import tiny_context


def _scenes(n: int = 3) -> ScenarioTensor:
    return ScenarioTensor.concat([tiny_context(["faithful"], i)[0] for i in range(n)])


def _future_speed(scenario: ScenarioTensor) -> torch.Tensor:
    now = scenario.current_index
    xy = scenario.xy[:, :, now:]
    return (torch.diff(xy, dim=2).norm(dim=-1) / scenario.dt).mean(-1)  # (B, A) from positions


@pytest.mark.parametrize("kind", PERTURBATIONS)
def test_perturbations_change_only_the_future_of_moving_controlled_agents(kind: str) -> None:
    scenes = _scenes()
    scenes = scenes.replace_unchecked(controlled=torch.tensor([[True, True, False]] * 3))
    moved, changed = perturb_future(scenes, kind, 0.5)
    now = scenes.current_index
    assert torch.equal(moved.states[:, :, : now + 1], scenes.states[:, :, : now + 1])
    assert torch.equal(moved.states[:, 2], scenes.states[:, 2])  # not controlled: the log
    assert not changed[:, 2].any()
    if kind != "tailgate":  # the tiny road's cars drive in separate lanes: nobody has a lead
        assert changed[:, :2].all()
        assert not torch.allclose(moved.states[:, :2, now + 1:], scenes.states[:, :2, now + 1:])
    else:
        assert not changed.any() and torch.equal(moved.states, scenes.states)


def test_retimed_futures_follow_the_logged_path_at_another_pace() -> None:
    scenes = _scenes()
    base = _future_speed(scenes)
    faster = _future_speed(perturb_future(scenes, "faster", 0.5)[0])
    slower = _future_speed(perturb_future(scenes, "slower", 0.5)[0])
    assert torch.allclose(faster / base, torch.full_like(base, 1.5), rtol=0.02)
    assert torch.allclose(slower / base, torch.full_like(base, 0.75), rtol=0.02)
    moved = perturb_future(scenes, "off_lane", 0.5)[0]
    shift = (moved.xy - scenes.xy).norm(dim=-1)
    assert float(shift.max()) == pytest.approx(2.0, abs=1e-3)


def test_a_stall_brakes_along_the_logged_path_and_stays_stopped() -> None:
    scenes = _scenes()
    now, dt = scenes.current_index, scenes.dt
    moved, changed = perturb_future(scenes, "stall", 0.5)  # braking from 1 s to 2.5 s
    assert changed.all()
    step = lambda s: torch.diff(s.xy[:, :, now:], dim=2).norm(dim=-1) / dt  # noqa: E731  (B, A, H) m/s
    before, after = step(scenes), step(moved)
    assert torch.allclose(after[..., :10], before[..., :10], rtol=1e-4)  # the log's pace for the first second
    stopped = round(2.5 / dt)
    assert float(after[..., stopped:].abs().max()) < 1e-4  # stopped from 2.5 s on
    assert torch.all(after[..., 11:stopped] < before[..., 11:stopped])  # braking in between
    # it stays on the logged path: every position is one the log passes through
    path = scenes.xy[:, :, now:]
    nearest = (moved.xy[:, :, now:, None] - path[:, :, None]).norm(dim=-1).amin(-1)
    assert float(nearest.max()) < float(before.max()) * dt


def test_tailgating_closes_the_gap_to_the_lead() -> None:
    from trafficrlhf_sdk.metrics.geometry import following_gaps

    scenes = _scenes(1)
    states = scenes.states.clone()
    states[0, 0, :, 1] = states[0, 2, :, 1]  # car 0 drives in car 2's lane, 10 m behind it
    states[0, 0, :, 0] = states[0, 2, :, 0] - 15.0
    states[0, 0, :, 2] = states[0, 2, :, 2]
    scenes = scenes.replace_unchecked(states=states)
    moved, changed = perturb_future(scenes, "tailgate", 0.5)
    assert changed[0, 0] and not changed[0, 2]
    gap = lambda s: following_gaps(s.xy, s.yaw, s.states[..., 2], s.extent, s.valid)[0, 0]  # noqa: E731
    end = scenes.current_index + 20
    assert float(gap(moved)[end]) < 2.0 < float(gap(scenes)[end])


def test_bad_perturbations_get_clear_errors() -> None:
    with pytest.raises(TrafficRLHFError, match="unknown perturbation 'sideways'"):
        perturb_future(_scenes(1), "sideways")
    with pytest.raises(TrafficRLHFError, match="strength"):
        perturb_future(_scenes(1), "faster", 0.0)


class _PaysForSpeed:
    """A broken reward: the faster the agents drive, the better."""

    def score(self, scenario: ScenarioTensor) -> torch.Tensor:
        return _future_speed(scenario).mean(-1)


class _LikesTheLog:
    """A reward that knows the log: minus the distance to it."""

    def __init__(self, log: ScenarioTensor) -> None:
        self.log = log

    def score(self, scenario: ScenarioTensor) -> torch.Tensor:
        return -(scenario.xy - self.log.xy).norm(dim=-1).mean((1, 2))


def test_probes_catch_a_reward_that_pays_for_speed_and_pass_one_that_knows_the_log() -> None:
    scenes = _scenes()
    broken = probe_reward_model(_PaysForSpeed(), scenes, ("faster", "slower", "off_lane"))
    assert broken["faster"]["pass_rate"] == 0.0 and broken["slower"]["pass_rate"] == 1.0
    assert broken["faster"]["scenes"] == 3 and broken["faster"]["mean_gap"] < 0
    good = probe_reward_model(_LikesTheLog(scenes), scenes, ("faster", "slower", "jerky", "off_lane"))
    assert all(entry["pass_rate"] == 1.0 for entry in good.values())
    assert probe_reward_model(_LikesTheLog(scenes), scenes, ("tailgate",))["tailgate"]["scenes"] == 0


def test_contrast_dataset_prefers_the_log_and_trains_a_reward_model() -> None:
    from trafficrlhf_sdk.reward import RewardConfig, RewardTrainer
    from trafficrlhf_sdk.feedback import PreferenceDataset

    scenes = _scenes(4)
    data = contrast_dataset(scenes, ("faster", "off_lane"))
    assert data.annotators == (CONTRAST_ANNOTATOR,) and len(data) == 8
    assert (data.pairs[:, 1] == 2).all()  # the log (last slot) always wins
    assert torch.equal(data.futures[:, 2], scenes.states[:, :, scenes.current_index + 1:])
    human = PreferenceDataset(contexts=data.contexts, futures=data.futures, future_valid=data.future_valid,
                              pairs=data.pairs[::2], pair_annotator=torch.zeros(4, dtype=torch.long),
                              pair_label=torch.arange(4), context_split=("train", "train", "train", "val"),
                              context_keys=data.context_keys, annotators=("person",))
    config = RewardConfig(max_epochs=2, batch_size=2, progress=False,
                          architecture_config={"hidden_sizes": [16, 8], "crop_size": 8})
    trainer = RewardTrainer(config, train_dataset=human, contrast_dataset=data)
    assert trainer.dataset_info["contrast_pairs"] == 8 and trainer.dataset_info["train_pairs"] == 3
    result = trainer.train()
    assert result.model is not None and "val_accuracy" in result.metrics


def test_judged_contrast_items_prefer_what_each_annotator_picks_not_the_log() -> None:
    """With annotators, a contrast item is labelled like a campaign item: the pick (here noise-free: the most
    realistic option by the annotator's own judgment) is preferred to every other option, the log included."""
    from trafficrlhf_sdk.feedback.judgment import judge_scenarios
    from trafficrlhf_sdk.feedback.synthetic import SyntheticAnnotatorConfig

    scenes = _scenes(4)
    kinds = ("faster", "jerky", "off_lane")
    strict = SyntheticAnnotatorConfig(beta=None, epsilon=0.0, none_threshold=0.0)
    lenient = SyntheticAnnotatorConfig(beta=None, epsilon=0.0, none_threshold=0.0, weight_accel=0.0,
                                       weight_jerk=0.0, weight_stop_go=0.0, weight_pace=0.0, weight_lane=0.0)
    data = contrast_dataset(scenes, kinds, annotators={"strict": strict, "lenient": lenient})
    assert data.annotators == ("strict", "lenient") and data.metadata["judged_by"] == ["strict", "lenient"]
    options = [perturb_future(scenes, kind)[0] for kind in kinds] + [scenes]
    for n, config in enumerate((strict, lenient)):
        realism = torch.stack([judge_scenarios(o, o.controlled, config.judgment()).realism for o in options], 1)
        for c in range(scenes.num_scenes):
            mine = data.pairs[(data.pair_annotator == n) & (data.pairs[:, 0] == c)]
            assert len(mine) == len(options) - 1 and len(set(mine[:, 1].tolist())) == 1  # one pick per item
            pick = int(mine[0, 1])
            assert realism[c, pick] == realism[c].max()
            assert sorted(mine[:, 2].tolist()) == [j for j in range(len(options)) if j != pick]
    assert len(set(data.pair_label.tolist())) == 2 * scenes.num_scenes  # one label per item and annotator
    # the strict judge sees the stop-and-go of `jerky`, so the log beats it; the lenient one cannot
    jerky_beaten = data.pairs[:, 2] == kinds.index("jerky")
    assert (data.pairs[jerky_beaten & (data.pair_annotator == 0), 1] == len(kinds)).all()
    again = contrast_dataset(scenes, kinds, annotators={"strict": strict, "lenient": lenient})
    assert torch.equal(again.pairs, data.pairs)


def test_tie_pairs_reach_the_loss_as_soft_labels_and_survive_filtering() -> None:
    from dataclasses import replace

    from trafficrlhf_sdk.reward.data import build_pair_data, filter_pairs

    data = contrast_dataset(_scenes(2), ("faster", "slower"))
    soft = replace(data, pair_prob=torch.tensor([1.0, 0.5, 0.5, 1.0]))
    pairs = build_pair_data(lambda scenario: _Inputs(scenario.num_scenes), soft)
    assert pairs.labels.tolist() == [1.0, 0.5, 0.5, 1.0]
    kept = filter_pairs(soft, mask=torch.tensor([True, True, False, True]))
    assert kept.pair_prob is not None and kept.pair_prob.tolist() == [1.0, 0.5, 1.0]


class _Inputs:
    """Stand-in prepared inputs: one row per future."""

    def __init__(self, n: int) -> None:
        self.n = n

    @staticmethod
    def concat(parts):  # type: ignore[no-untyped-def]
        return _Inputs(sum(p.n for p in parts))


def test_conservative_ensembles_read_the_worst_member_or_a_lower_confidence_bound() -> None:
    from trafficrlhf_sdk.reward import RewardEnsemble

    torch.manual_seed(0)
    ensemble = RewardEnsemble({"member_architecture": "ctg_mlp", "num_members": 3,
                               "member_config": {"hidden_sizes": [8], "crop_size": 8}})
    scenes = _scenes(2)
    with torch.no_grad():
        members = ensemble.member_scores(scenes)
        assert torch.allclose(ensemble.score(scenes), members.mean(0))
        assert torch.allclose(ensemble.conservative("worst").score(scenes), members.min(0).values)
        lcb = ensemble.conservative("lcb", 2.0).score(scenes)
        assert torch.allclose(lcb, members.mean(0) - 2.0 * members.std(0))
    with pytest.raises(ValueError, match="aggregation"):
        ensemble.conservative("median")


class _Broken:
    """A reward broken in one way: it pays for driving faster, slower, jerkier, sideways off the path the agent
    was on, closer to its lead, swerving, or standing still."""

    def __init__(self, kind: str) -> None:
        self.kind = kind

    def score(self, scenario: ScenarioTensor) -> torch.Tensor:
        from trafficrlhf_sdk.metrics.geometry import following_gaps

        now = scenario.current_index
        if self.kind in ("faster", "slower"):
            speed = _future_speed(scenario).mean(-1)
            return speed if self.kind == "faster" else -speed
        if self.kind == "jerky":
            speed = torch.diff(scenario.xy[:, :, now:], dim=2).norm(dim=-1) / scenario.dt
            return torch.diff(speed, n=2, dim=2).abs().mean((1, 2))
        if self.kind == "weave":  # pays for sideways speed changing sign
            rel = scenario.xy[:, :, now:] - scenario.xy[:, :, now, None]
            yaw = scenario.yaw[:, :, now, None]
            side = -torch.sin(yaw) * rel[..., 0] + torch.cos(yaw) * rel[..., 1]
            return torch.diff(side, n=2, dim=2).abs().mean((1, 2))
        if self.kind == "stall":  # pays for standing still
            speed = torch.diff(scenario.xy[:, :, now:], dim=2).norm(dim=-1) / scenario.dt
            return (speed < 0.5).float().mean((1, 2))
        if self.kind == "off_lane":  # lateral offset from the line the agent was heading along at "now"
            yaw = scenario.yaw[:, :, now, None]
            rel = scenario.xy[:, :, now:] - scenario.xy[:, :, now, None]
            return (-torch.sin(yaw) * rel[..., 0] + torch.cos(yaw) * rel[..., 1]).abs().mean((1, 2))
        gaps = following_gaps(scenario.xy, scenario.yaw, scenario.states[..., 2], scenario.extent, scenario.valid)
        return -torch.nan_to_num(gaps[:, :, now:], nan=0.0, posinf=0.0).mean((1, 2))


@pytest.mark.parametrize("kind", PERTURBATIONS)
def test_each_probe_catches_a_reward_broken_its_way(kind: str) -> None:
    scenes = _scenes()
    if kind == "tailgate":  # car 0 follows car 2 in its lane, 15 m behind
        states = scenes.states.clone()
        states[:, 0, :, 1] = states[:, 2, :, 1]
        states[:, 0, :, 0] = states[:, 2, :, 0] - 15.0
        states[:, 0, :, 2] = states[:, 2, :, 2]
        scenes = scenes.replace_unchecked(states=states)
    result = probe_reward_model(_Broken(kind), scenes, (kind,))[kind]
    assert result["scenes"] >= 1 and result["pass_rate"] == 0.0, result
    assert probe_reward_model(_LikesTheLog(scenes), scenes, (kind,))[kind]["pass_rate"] == 1.0


def test_the_stand_in_judgment_takes_the_probes_like_a_reward_model() -> None:
    from trafficrlhf_sdk.reward.oracle import JudgmentReward

    scenes = _scenes()
    judge = JudgmentReward("attentive")
    assert torch.allclose(judge.score(scenes), judge.step_rewards(scenes)[:, -1])
    report = probe_reward_model(judge, scenes, ("faster", "jerky", "off_lane", "weave", "stall"))
    assert all(entry["windows"] == 3 and entry["pass_rate"] == 1.0 for entry in report.values())
