"""The reward model's scene-context inputs: causal, and they move with what an annotator sees."""

from __future__ import annotations

import torch

from trafficrlhf_sdk.feedback.records import ContextRecord
from trafficrlhf_sdk.reward.features import FeatureSpec, compute_step_inputs, stride_of
from trafficrlhf_sdk.reward.scene_context import EVENTS, NUM_SCENE_CONTEXT_FEATURES, scene_context_features
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.testing.feedback import tiny_context


def _batch(variants: list[str]) -> ScenarioTensor:
    scenario, candidates, valid, logged, logged_valid = tiny_context(variants)
    record = ContextRecord(id=1, campaign_id=1, ordinal=0, source="tiny", split="test", scene_id="tiny-0000",
                           seed=0, start_index=scenario.current_index, scenario=scenario, candidates=candidates,
                           candidate_valid=valid, logged=logged, logged_valid=logged_valid)
    return ScenarioTensor.concat([record.candidate_scenario(k) for k in range(len(variants))])


def _features(batch: ScenarioTensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    steps = torch.arange(batch.current_index + 5, batch.num_steps, 5)
    item = batch.valid[:, :, steps]
    scene, agent, slot = item.nonzero(as_tuple=True)
    step = steps[slot]
    return scene_context_features(batch, scene, agent, step, 5), scene, agent, step


def column(name: str, since_now: bool = True) -> int:
    return 2 * EVENTS.index(name) + int(since_now)


def test_shape_and_the_feature_spec_count() -> None:
    batch = _batch(["faithful", "collision"])
    spec = FeatureSpec(scene_context=True)
    inputs = compute_step_inputs(batch, spec)
    assert inputs.features.shape[1] == spec.num_features
    assert spec.num_features - FeatureSpec().num_features == NUM_SCENE_CONTEXT_FEATURES
    assert torch.isfinite(inputs.features).all()


def test_causal_an_item_never_reads_a_later_step() -> None:
    batch = _batch(["faithful"])
    features, _, _, step = _features(batch)
    cut = batch.current_index + 12
    changed = batch.states.clone()
    changed[:, :, cut + 1:, :2] += torch.randn(changed[:, :, cut + 1:, :2].shape) * 5
    later, _, _, _ = _features(batch.replace_unchecked(states=changed))
    early = step <= cut
    assert early.any() and torch.equal(features[early], later[early])
    assert not torch.equal(features[~early], later[~early])


def test_a_crash_stays_visible_and_weaving_counts_reversals() -> None:
    batch = _batch(["faithful", "collision", "weave"])
    features, scene, agent, _ = _features(batch)
    crashed = features[:, 2 * len(EVENTS)]  # collided at any step since now
    assert crashed[scene == 0].eq(0).all()
    crash_items = crashed[(scene == 1) & (agent == 1)]
    assert crash_items[-1] == 1 and torch.all(crash_items[1:] >= crash_items[:-1])  # once crashed, always crashed
    weave = features[:, -3]
    assert weave[(scene == 2) & (agent == 1)].max() > 0 and weave[scene == 0].eq(0).all()
    assert features[:, column("collision")][scene == 1].max() > 0


def test_the_reward_model_inputs_cover_the_scored_steps() -> None:
    batch = _batch(["faithful"])
    spec = FeatureSpec(scene_context=True)
    inputs = compute_step_inputs(batch, spec)
    assert stride_of(batch, spec.step_dt) == 5 and len(inputs) == int(batch.valid[:, :, inputs.step.unique()].sum())
