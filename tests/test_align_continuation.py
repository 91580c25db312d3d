"""Closed-loop continuations of sampled futures (``continuation_steps``): the reward sees what executing a sample's
first steps leads to once the model replans."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
from trafficrlhf_sdk.alignment.continuation import continuation_scenarios
from trafficrlhf_sdk.reward.builtin import FailureReward
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario import ScenarioTensor

gru = pytest.importorskip("trafficrlhf_example_gru")

FAST = dict(epochs=1, contexts_per_epoch=4, samples_per_context=3, minibatch_contexts=2, ppo_epochs=1,
            progress_bar=False, log_formats=("csv",))


def _trainer(train_scene_list: list[ScenarioTensor], **options: object) -> AlignTrainer:
    torch.manual_seed(0)
    config = AlignConfig(**{"alpha": 1.0, "credit": "agent", **FAST, **options})  # type: ignore[arg-type]
    return AlignTrainer(gru.ExampleGRUAdapter(), FailureReward(margins=True), config, scenes=train_scene_list)


def _samples(trainer: AlignTrainer) -> tuple[ScenarioTensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    contexts, _ = trainer.context_sampler.draw(torch.Generator().manual_seed(0))
    out = trainer._sample(contexts, torch.Generator().manual_seed(1))
    states, valid = trainer._future_states(contexts, out.futures, out.trace.agents)
    return contexts, states, valid, out.trace.agents


def test_a_continuation_executes_the_sample_then_the_model_drives(train_scene_list: list[ScenarioTensor]) -> None:
    trainer = _trainer(train_scene_list, continuation_steps=10)
    contexts, states, valid, agents = _samples(trainer)
    b, s, a = states.shape[:3]
    now = contexts.current_index
    scenes = continuation_scenarios(trainer.model, contexts, states, valid, agents, 5, 10, seed=3)
    assert scenes.num_scenes == b * s and scenes.current_index == now and scenes.num_steps == now + 16
    grid = scenes.states.reshape(b, s, a, -1, 4)
    # the history is the context's, for every sample
    assert torch.equal(grid[..., : now + 1, :], contexts.states[:, None, :, : now + 1].expand(b, s, a, -1, 4))
    picked = agents[:, None, :].expand(b, s, a)
    # the sampled agents execute the first 5 steps of their own sample ...
    assert torch.allclose(grid[..., now + 1: now + 6, :][picked], states[..., :5, :][picked])
    # ... then the model drives them: not the sample's own later steps
    assert not torch.allclose(grid[..., now + 6:, :][picked], states[..., 5:15, :][picked])
    # everyone else follows the context where it is valid
    other = ~picked & contexts.valid[:, None, :, now + 1: now + 16].all(-1).expand(b, s, a)
    assert other.any()
    assert torch.allclose(grid[..., now + 1:, :][other],
                          contexts.states[:, None, :, now + 1: now + 16].expand(b, s, a, -1, 4)[other])
    assert torch.equal(scenes.controlled.reshape(b, s, a), picked)
    # seeded: the same call gives the same continuations
    again = continuation_scenarios(trainer.model, contexts, states, valid, agents, 5, 10, seed=3)
    assert torch.equal(again.states, scenes.states)


def test_samples_that_execute_the_same_steps_get_the_same_continuation(
        train_scene_list: list[ScenarioTensor]) -> None:
    """Common random numbers: the samples of a context differ by their executed steps alone."""
    trainer = _trainer(train_scene_list, continuation_steps=10)
    contexts, states, valid, agents = _samples(trainer)
    now = contexts.current_index
    b, s, a = states.shape[:3]
    twins = states.clone()
    twins[:, 1, :, :5] = twins[:, 0, :, :5]  # sample 1 executes sample 0's first steps (differs after them)
    grid = continuation_scenarios(trainer.model, contexts, twins, valid, agents, 5, 10, seed=3).states
    grid = grid.reshape(b, s, a, -1, 4)[..., now + 1:, :]
    assert torch.equal(grid[:, 0], grid[:, 1])
    assert not torch.equal(grid[:, 0], grid[:, 2])
    # another seed draws other plans: the continuation is the model's stochastic driving
    other = continuation_scenarios(trainer.model, contexts, twins, valid, agents, 5, 10, seed=4).states
    assert not torch.equal(other.reshape(b, s, a, -1, 4)[..., now + 6:, :], grid[..., 5:, :])


def test_without_closed_loop_steps_the_continuation_is_the_executed_prefix(
        train_scene_list: list[ScenarioTensor]) -> None:
    trainer = _trainer(train_scene_list, continuation_steps=10)
    contexts, states, valid, agents = _samples(trainer)
    scenes = continuation_scenarios(trainer.model, contexts, states, valid, agents, 5, 0, seed=0)
    now, (b, s, a) = contexts.current_index, states.shape[:3]
    assert scenes.num_steps == now + 6
    assert torch.equal(scenes.states.reshape(b, s, a, -1, 4)[..., now + 1:, :], states[..., :5, :])
    with pytest.raises(ValueError, match="future steps"):
        continuation_scenarios(trainer.model, contexts, states[..., :8, :], valid[..., :8], agents, 5, 10, seed=0)


def test_the_reward_scores_the_continuation_window_and_mixes_it_with_the_open_loop_sample(
        train_scene_list: list[ScenarioTensor]) -> None:
    seen: list[int] = []

    class Recording(FailureReward):
        def agent_scores(self, scenario):  # type: ignore[no-untyped-def]
            seen.append(scenario.num_steps - scenario.current_index - 1)
            return super().agent_scores(scenario)

    torch.manual_seed(0)
    config = AlignConfig(alpha=1.0, credit="agent", continuation_steps=25, **FAST)  # type: ignore[arg-type]
    trainer = AlignTrainer(gru.ExampleGRUAdapter(), Recording(margins=True), config, scenes=train_scene_list)
    assert trainer.future_steps == 30  # 5 executed + 25 closed-loop steps of log kept for the other agents
    rollout = trainer._rollout(0)
    assert seen == [trainer.horizon, 30]  # the open-loop sample, then its continuation
    assert torch.isfinite(rollout.advantages).all()
    # continuation_weight mixes the two scores linearly
    contexts, _, _, agents = _samples(trainer)
    out = trainer._sample(contexts, torch.Generator().manual_seed(1))
    open_loop = torch.zeros(contexts.num_scenes, config.samples_per_context, contexts.num_agents)
    closed = trainer._mix_continuation(open_loop, contexts, out.futures, agents, 0, None)
    half = AlignTrainer(trainer.model, Recording(margins=True),
                        config.model_copy(update={"continuation_weight": 0.5}), scenes=train_scene_list)
    mixed = half._mix_continuation(open_loop + 1.0, contexts, out.futures, agents, 0, None)
    assert torch.allclose(mixed, 0.5 * closed + 0.5)
    assert (closed < 0).any()  # the margins cost something somewhere, or the mix test proves little


def test_a_run_with_continuations_trains_like_any_other(train_scene_list: list[ScenarioTensor]) -> None:
    trainer = _trainer(train_scene_list, continuation_steps=10, credit="scene")
    history = trainer.train()
    assert history[0]["first_ratio_max_dev"] == 0.0 and history[0]["updates"] > 0


def test_continuation_settings_are_checked(train_scene_list: list[ScenarioTensor]) -> None:
    with pytest.raises(ValueError, match="counterfactual_credit"):
        AlignConfig(credit="agent", counterfactual_credit=True, continuation_steps=10)
    with pytest.raises(ValueError, match="continuation_executed_steps"):
        AlignConfig(continuation_steps=10, continuation_executed_steps=30, horizon=20)
    with pytest.raises(TrafficRLHFError, match="continuation_executed_steps"):
        _trainer(train_scene_list, continuation_steps=10, continuation_executed_steps=500)


def test_guidance_swapped_restores_the_policys_own_guidance_even_on_error() -> None:
    from trafficrlhf_sdk.simulation.guidance import GuidanceSet, guidance_swapped

    class Policy:
        guidance = None

    policy, run = Policy(), GuidanceSet.parse("no_collision")
    with guidance_swapped(policy, run):
        assert policy.guidance is run
    assert policy.guidance is None
    with pytest.raises(RuntimeError), guidance_swapped(policy, run):
        raise RuntimeError("boom")
    assert policy.guidance is None
    with guidance_swapped(policy, None):  # None leaves the policy's own guidance in place
        assert policy.guidance is None
