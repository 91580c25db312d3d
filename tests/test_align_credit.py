"""Per-agent credit, failure-focused contexts and per-agent reward scores (alignment, stage III)."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
from trafficrlhf_sdk.alignment.contexts import ContextSampler
from trafficrlhf_sdk.alignment.ppo_update import derived_generator
from trafficrlhf_sdk.reward.builtin import FailureReward
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_per_step
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import ConstantVelocityPolicy

gru = pytest.importorskip("trafficrlhf_example_gru")

FAST = dict(epochs=1, contexts_per_epoch=4, samples_per_context=3, minibatch_contexts=2, ppo_epochs=1,
            progress_bar=False)


def _model():  # type: ignore[no-untyped-def]
    torch.manual_seed(0)
    return gru.ExampleGRUAdapter()


def _kl_to_reference(trainer: AlignTrainer, model, contexts: ScenarioTensor, trace) -> float:  # type: ignore[no-untyped-def]
    """The k3 estimate of KL(model || trainer.reference) on the stored samples of ``contexts``."""
    with torch.no_grad():
        every = [torch.arange(contexts.num_scenes)]
        d = trainer._log_probs(trainer.reference, contexts, trace, every) \
            - trainer._log_probs(model, contexts, trace, every)
        return float((torch.exp(d) - 1 - d).mean())


def test_failure_reward_agent_scores_count_each_agents_failing_steps(train_scene_list: list[ScenarioTensor]) -> None:
    scene = train_scene_list[0].replace_unchecked(current_index=10)
    scores = FailureReward().agent_scores(scene)
    assert scores.shape == (1, scene.num_agents)
    bad = (collisions_per_step(scene) & scene.valid) | offroad_per_step(scene)
    agents = scene.controlled & scene.valid.any(-1)
    for a in range(scene.num_agents):
        steps = scene.valid[0, a, 11:]
        if not agents[0, a] or not steps.any():
            assert scores[0, a] == 0
            continue
        expected = -(bad[0, a, 11:] & steps).sum() / steps.sum()
        assert torch.isclose(scores[0, a], expected.float())


def test_learned_reward_agent_scores_average_to_the_scene_score(train_scene_list: list[ScenarioTensor]) -> None:
    from trafficrlhf_sdk.reward import CTGMLPRewardModel, RewardEnsemble

    torch.manual_seed(0)
    model = RewardEnsemble(members=[CTGMLPRewardModel(), CTGMLPRewardModel()])
    scene = train_scene_list[1].replace_unchecked(current_index=10).time_slice(0, 31)
    # keep the agents valid over the whole window: then "mean over steps of the mean over agents" (the scene
    # score) equals "mean over agents of the mean over steps"
    full = scene.valid.all(-1) & scene.controlled
    scene = scene.replace_unchecked(controlled=full)
    per_agent = model.agent_scores(scene)
    assert per_agent.shape == (1, scene.num_agents)
    assert torch.all(per_agent[~full] == 0)
    assert torch.isclose(per_agent[full].mean(), model(scene)[0], atol=1e-6)


def test_failure_contexts_start_shortly_before_a_failure_of_the_driving_model(
        train_scene_list: list[ScenarioTensor]) -> None:
    config = AlignConfig(failure_fraction=1.0, failure_scenes=8, contexts_per_epoch=6)
    sampler = ContextSampler(ConstantVelocityPolicy(), config, lambda: train_scene_list, None, future_steps=20)
    contexts, logged = sampler.failure_contexts(6, torch.Generator().manual_seed(0))
    assert sampler.last_failure_events > 0  # constant velocity leaves the road within 6 s in these scenes
    assert contexts.num_scenes == logged.num_scenes <= 6
    assert contexts.current_index == logged.current_index == 30
    assert contexts.controlled.any(-1).all()
    # the history up to "now" is the policy's: constant velocity keeps each controlled agent's speed
    now = contexts.current_index
    moved = (contexts.states[:, :, : now + 1] - logged.states[:, :, : now + 1]).abs().amax((-1, -2))
    assert (moved[contexts.controlled] > 0).any()
    # driving on from "now" with the same policy, every context fails within the longest lead (collision or
    # off-road of a controlled agent): the context was cut FAILURE_LEAD_STEPS before that failure
    from trafficrlhf_sdk.alignment.config import FAILURE_LEAD_STEPS
    from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

    lead = FAILURE_LEAD_STEPS[1]
    again = simulate(ConstantVelocityPolicy(), contexts, SimulationConfig(duration_s=lead * 0.1, start_index=now))
    window = again.simulated.time_slice(now + 1, now + lead + 1)
    failed = ((collisions_per_step(window) & window.valid) | offroad_per_step(window)).any(-1)
    assert (failed & again.controlled).any(-1).all()


def test_agent_credit_gives_each_sampled_agent_its_own_advantage(train_scene_list: list[ScenarioTensor]) -> None:
    model = _model()
    config = AlignConfig(alpha=1.0, credit="agent", failure_fraction=0.5, failure_scenes=4, 
                         **FAST)
    trainer = AlignTrainer(model, FailureReward(), config, scenes=train_scene_list)
    rollout = trainer._rollout(0)
    b, a = rollout.contexts.num_scenes, rollout.contexts.num_agents
    assert rollout.advantages.shape == (b, 3, a)
    assert torch.all(rollout.advantages[~rollout.trace.agents[:, None, :].expand(b, 3, a)] == 0)
    # within each (context, agent) the advantages are normalized over the samples: mean 0
    assert torch.allclose(rollout.advantages.mean(1), torch.zeros(b, a), atol=1e-5)
    history = trainer.train()
    assert history[0]["first_ratio_max_dev"] == 0.0


def test_agent_credit_needs_agent_scores(train_scene_list: list[ScenarioTensor]) -> None:
    class SceneOnly:
        def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
            return torch.zeros(scenario.num_scenes, scenario.num_steps)

    with pytest.raises(TrafficRLHFError, match="agent_scores"):
        AlignTrainer(_model(), SceneOnly(), AlignConfig(credit="agent", **FAST), scenes=train_scene_list)


def test_failure_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="failure_fraction"):
        AlignConfig(failure_fraction=1.5)
    with pytest.raises(ValueError, match="failure_scenes"):
        AlignConfig(failure_scenes=0)


def test_denoising_steps_limit_the_ppo_terms_to_the_first_chain_steps(train_scene_list: list[ScenarioTensor]) -> None:
    ctg = pytest.importorskip("trafficrlhf_ctg")
    model = ctg.CTGAdapter()
    config = AlignConfig(alpha=1.0, denoising_steps=2, kl_coef=0.1, **FAST)
    trainer = AlignTrainer(model, FailureReward(), config, scenes=train_scene_list)
    rollout = trainer._rollout(0)
    assert rollout.sample_log_prob.shape[-1] == 5  # the adapter's whole chain is traced ...
    assert trainer._steps(rollout.sample_log_prob).shape[-1] == 2  # ... the PPO terms see its first 2 steps
    history = trainer.train()
    assert history[0]["first_ratio_max_dev"] == 0.0 and history[0]["sample_log_prob_gap"] < 1e-3


def test_a_reference_model_far_away_does_not_turn_the_weights_into_nan(train_scene_list: list[ScenarioTensor]) -> None:
    model = _model()
    trainer = AlignTrainer(model, FailureReward(), AlignConfig(alpha=1.0, kl_coef=1.0, **FAST), scenes=train_scene_list)
    assert trainer.reference is not None
    with torch.no_grad():  # a reference whose densities differ from the model's by far more than exp() can hold
        for p in trainer.reference.module.parameters():
            p.mul_(50.0)
    history = trainer.train()
    assert all(torch.isfinite(p).all() for p in model.module.parameters())
    assert history[0]["updates"] + history[0]["skipped_updates"] >= 1


def test_realism_reward_penalizes_an_agent_that_stalls_against_the_log(train_scene_list: list[ScenarioTensor]) -> None:
    from trafficrlhf_sdk.reward.builtin import RealismReward

    log = train_scene_list[3].replace_unchecked(current_index=10).time_slice(0, 31)
    now = log.current_index
    moving = log.controlled & log.valid[:, :, now:].all(-1) & (log.states[:, :, now + 1:, 2].amin(-1) > 3.0)
    assert moving.any(), "the scene needs an agent driving faster than 3 m/s throughout"
    agent = int(moving[0].nonzero()[0])
    states = log.states.clone()
    states[0, agent, now + 1:, :2] = states[0, agent, now, :2]  # it stops dead at "now"
    states[0, agent, now + 1:, 2] = 0.0
    stalled = log.replace_unchecked(states=states)
    reward = RealismReward()
    baseline = reward.agent_scores(log, logged=log)
    scores = reward.agent_scores(stalled, logged=log)
    # stall share 1 and a |dv/dt| above 3 m/s^2 on the 0.5 s differences that span the stop
    assert scores[0, agent] <= baseline[0, agent] - 1.0
    others = torch.ones(log.num_agents, dtype=torch.bool)
    others[agent] = False
    assert torch.allclose(scores[0, others], baseline[0, others])
    with pytest.raises(TrafficRLHFError, match="logged"):
        reward.agent_scores(stalled)
    with pytest.raises(TrafficRLHFError, match="credit='agent'"):
        AlignTrainer(_model(), reward, AlignConfig(**FAST), scenes=train_scene_list)


def test_rewards_that_use_the_log_get_the_log_not_the_contexts_own_continuation(
        train_scene_list: list[ScenarioTensor]) -> None:
    """Failure-focused contexts continue with the driving model's own steps; the reference a ``uses_log`` reward
    compares with must be the logged future of the same window."""
    from trafficrlhf_sdk.reward.builtin import RealismReward

    seen: list[tuple[ScenarioTensor, ScenarioTensor]] = []

    class Recording(RealismReward):
        def agent_scores(self, scenario, logged=None):  # type: ignore[no-untyped-def, override]
            seen.append((scenario, logged))
            return super().agent_scores(scenario, logged=logged)

    config = AlignConfig(credit="agent", failure_fraction=1.0, failure_scenes=8, 
                         **FAST)
    trainer = AlignTrainer(_model(), Recording(), config, scenes=train_scene_list)
    contexts, logged = trainer._contexts(0)
    trainer._rollout(0)
    scenario, reference = seen[-1]
    s, now = config.samples_per_context, contexts.current_index
    start = now - scenario.current_index  # the reward window keeps reward_history_steps of history
    expected = logged[torch.arange(contexts.num_scenes).repeat_interleave(s)].time_slice(
        start, start + scenario.num_steps)
    assert torch.equal(reference.states, expected.states) and torch.equal(reference.valid, expected.valid)
    own = contexts.states[:, :, now + 1:] * contexts.valid[:, :, now + 1:, None]
    log = logged.states[:, :, now + 1:] * logged.valid[:, :, now + 1:, None]
    assert not torch.equal(own, log), "the failure-focused contexts should differ from the log after now"


def test_the_passing_anchor_zeroes_passing_agents_advantages_and_holds_them_at_the_start(
        train_scene_list: list[ScenarioTensor]) -> None:
    """``passing_anchor_coef``: an agent is *passing* when none of its samples collides or leaves the road
    (checked here with the metrics' own per-step tests); its advantages become 0 while every other agent keeps
    the advantage it has without the option; with the surrogate and imitation off, the anchor alone brings a
    drifted model back towards its start on the passing agents' samples."""
    common = dict(alpha=0.0, imitation_coef=0.0, credit="agent", failure_fraction=0.5, failure_scenes=4,
                  learning_rate=1e-3, **{**FAST, "ppo_epochs": 4})
    reward = FailureReward(margins=True)
    plain = AlignTrainer(_model(), reward, AlignConfig(**common), scenes=train_scene_list)._rollout(0)
    model = _model()
    trainer = AlignTrainer(model, reward, AlignConfig(passing_anchor_coef=1.0, **common), scenes=train_scene_list)
    assert trainer.reference is not None
    rollout = trainer._rollout(0)
    passing, agents = rollout.passing, rollout.trace.agents
    assert passing is not None and not (passing & ~agents).any()
    futures = trainer._sample(rollout.contexts, derived_generator(0, 0, "sample")).futures  # the rollout's draw
    scenario = trainer.sample_scenarios(rollout.contexts, futures, agents)
    future = slice(scenario.current_index + 1, None)
    bad = (collisions_per_step(scenario) | offroad_per_step(scenario))[:, :, future] & scenario.valid[:, :, future]
    fails = bad.any(-1).reshape(rollout.advantages.shape).any(1)  # (B, A): some sample fails
    assert torch.equal(passing, agents & ~fails)
    assert passing.any() and (agents & ~passing).any(), "the draw needs passing and failing agents"
    assert torch.all(rollout.advantages[passing[:, None, :].expand_as(rollout.advantages)] == 0)
    kept = (agents & ~passing)[:, None, :].expand_as(rollout.advantages)
    assert torch.equal(rollout.advantages[kept], plain.advantages[kept])

    with torch.no_grad():
        torch.manual_seed(1)
        for p in model.module.parameters():
            p.add_(0.05 * torch.randn_like(p))

    def passing_kl() -> float:
        every = [torch.arange(rollout.contexts.num_scenes)]
        d = trainer._log_probs(trainer.reference, rollout.contexts, rollout.trace, every) \
            - trainer._log_probs(model, rollout.contexts, rollout.trace, every)
        mask = passing[:, None, :].expand(d.shape[:3])
        mask = mask[..., None].expand(d.shape) if d.dim() == 4 else mask
        return float((torch.exp(d) - 1 - d)[mask].mean())

    before = passing_kl()
    stats = trainer._optimize(0, rollout)
    assert stats["passing_kl"] > 0 and stats["updates"] >= 1
    assert passing_kl() < before


def test_the_passing_anchor_needs_agent_credit_and_its_margins_flag_needs_the_anchor() -> None:
    with pytest.raises(ValueError, match="passing_anchor_coef"):
        AlignConfig(passing_anchor_coef=1.0, credit="scene")
    with pytest.raises(ValueError, match="passing_margins"):
        AlignConfig(passing_margins=True, credit="agent")


def test_a_reference_that_cannot_score_the_policy_or_is_unused_is_refused(
        train_scene_list: list[ScenarioTensor]) -> None:
    anchored = AlignConfig(kl_coef=1.0, **FAST)
    with pytest.raises(TrafficRLHFError, match="nothing would use it"):
        AlignTrainer(_model(), FailureReward(), AlignConfig(**FAST), scenes=train_scene_list, reference=_model())

    class OtherAdapter(gru.ExampleGRUAdapter):
        pass

    with pytest.raises(TrafficRLHFError, match="same adapter"):
        AlignTrainer(_model(), FailureReward(), anchored, scenes=train_scene_list, reference=OtherAdapter())
    smaller = _model()
    smaller.build({"hidden": 32})
    with pytest.raises(TrafficRLHFError, match="other shapes"):
        AlignTrainer(_model(), FailureReward(), anchored, scenes=train_scene_list, reference=smaller)


def test_choice_coef_needs_agent_credit_and_a_model_with_choices(train_scene_list: list[ScenarioTensor]) -> None:
    with pytest.raises(ValueError, match="choice_coef"):
        AlignConfig(choice_coef=1.0, credit="scene")
    with pytest.raises(TrafficRLHFError, match="offers no discrete choices"):
        AlignTrainer(_model(), FailureReward(), AlignConfig(choice_coef=1.0, credit="agent", **FAST),
                     scenes=train_scene_list)
