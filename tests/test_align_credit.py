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
            progress_bar=False, log_formats=("csv",))


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
    config = AlignConfig(failure_fraction=1.0, failure_scenes=8, failure_drive_s=6.0, failure_lead_steps=(3, 8),
                         history_steps=10, contexts_per_epoch=6)
    sampler = ContextSampler(ConstantVelocityPolicy(), config, lambda: train_scene_list, None, future_steps=20)
    contexts, logged = sampler.failure_contexts(6, torch.Generator().manual_seed(0))
    assert sampler.last_failure_events > 0  # constant velocity leaves the road within 6 s in these scenes
    assert contexts.num_scenes == logged.num_scenes <= 6
    assert contexts.current_index == logged.current_index == 10
    assert contexts.controlled.any(-1).all()
    # the history up to "now" is the policy's: constant velocity keeps each controlled agent's speed
    now = contexts.current_index
    moved = (contexts.states[:, :, : now + 1] - logged.states[:, :, : now + 1]).abs().amax((-1, -2))
    assert (moved[contexts.controlled] > 0).any()
    # driving on from "now" with the same policy, every context fails within the 8-step lead (collision or
    # off-road of a controlled agent): the context was cut 3..8 steps before that failure
    from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

    again = simulate(ConstantVelocityPolicy(), contexts, SimulationConfig(duration_s=0.8, start_index=now))
    window = again.simulated.time_slice(now + 1, now + 9)
    failed = ((collisions_per_step(window) & window.valid) | offroad_per_step(window)).any(-1)
    assert (failed & again.controlled).any(-1).all()


def test_agent_credit_gives_each_sampled_agent_its_own_advantage(train_scene_list: list[ScenarioTensor]) -> None:
    model = _model()
    config = AlignConfig(alpha=1.0, credit="agent", failure_fraction=0.5, failure_scenes=4, failure_drive_s=4.0,
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
    with pytest.raises(ValueError, match="failure_lead_steps"):
        AlignConfig(failure_lead_steps=(5, 2))
    with pytest.raises(ValueError, match="exceed 1"):
        AlignConfig(failure_fraction=0.7, closed_loop_fraction=0.5)
    with pytest.raises(ValueError, match="perturb_fraction"):
        AlignConfig(failure_fraction=0.75, perturb_fraction=0.5)


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


def test_pessimistic_reward_is_the_member_mean_minus_beta_std(train_scene_list: list[ScenarioTensor]) -> None:
    from trafficrlhf_sdk.reward.builtin import PessimisticReward
    from trafficrlhf_sdk.reward import CTGMLPRewardModel, RewardEnsemble

    torch.manual_seed(1)
    ensemble = RewardEnsemble(members=[CTGMLPRewardModel(), CTGMLPRewardModel(), CTGMLPRewardModel()])
    scene = train_scene_list[2].replace_unchecked(current_index=10)
    with torch.no_grad():
        per_member = torch.stack([m.agent_scores(scene) for m in ensemble.members])
        pessimistic = PessimisticReward(ensemble, beta=2.0)
        assert torch.allclose(pessimistic.agent_scores(scene), per_member.mean(0) - 2.0 * per_member.std(0))
        assert torch.allclose(PessimisticReward(ensemble, 0.0).score(scene), ensemble(scene))
        assert (pessimistic.score(scene) <= ensemble(scene) + 1e-7).all()
    with pytest.raises(TrafficRLHFError, match="two members"):
        PessimisticReward(FailureReward(), 1.0)


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


def test_failure_refresh_reuses_one_drive_per_block_of_epochs(train_scene_list: list[ScenarioTensor]) -> None:
    config = AlignConfig(failure_fraction=1.0, failure_scenes=8, failure_drive_s=6.0, failure_lead_steps=(3, 8),
                         history_steps=10, contexts_per_epoch=4, failure_refresh_every=2)
    sampler = ContextSampler(ConstantVelocityPolicy(), config, lambda: train_scene_list, None, future_steps=20)
    drives: list[int] = []
    original = sampler.drive_for_failures

    def counting(gen: torch.Generator, epoch: int = 0):  # type: ignore[no-untyped-def]
        drives.append(epoch)
        return original(gen, epoch)

    sampler.drive_for_failures = counting  # type: ignore[method-assign]
    drawn = [sampler.draw(torch.Generator().manual_seed(e), e)[0] for e in range(5)]
    assert drives == [0, 2, 4]  # epochs 1 and 3 cut their contexts from the previous epoch's drive
    assert sampler.last_failure_events > 0
    # the reused drive still gives that epoch its own contexts (other events or leads)
    assert not torch.equal(drawn[0].states, drawn[1].states)
    # without an epoch (or with failure_refresh_every=1) every call drives afresh
    sampler.draw(torch.Generator().manual_seed(9))
    assert drives == [0, 2, 4, 0]


def test_failure_refresh_run_resumed_mid_block_matches_uninterrupted(train_scene_list: list[ScenarioTensor],
                                                                     tmp_path) -> None:  # type: ignore[no-untyped-def]
    import os

    from trafficrlhf_sdk.alignment import align

    config = {**FAST, "epochs": 3, "save_every": 1, "credit": "agent", "failure_fraction": 0.5,
              "failure_scenes": 3, "failure_drive_s": 3.0, "failure_refresh_every": 2}
    full = _model()
    align(full, FailureReward(), alpha=1.0, scenes=train_scene_list, output_dir=str(tmp_path / "full"), **config)
    part = _model()
    align(part, FailureReward(), alpha=1.0, scenes=train_scene_list, output_dir=str(tmp_path / "cut"),
          callback=lambda epoch, stats: epoch < 0, **config)  # stops after epoch 0: epoch 1 reuses its drive
    assert os.path.isfile(tmp_path / "cut" / "checkpoints" / "checkpoint-1" / "failure_drive.safetensors")
    resumed = _model()
    align(resumed, FailureReward(), alpha=1.0, scenes=train_scene_list, output_dir=str(tmp_path / "cut"),
          resume=True, **config)
    expected, got = full.module.state_dict(), resumed.module.state_dict()
    for key, value in expected.items():
        assert torch.equal(value, got[key]), key


def test_a_reward_horizon_shorter_than_the_models_scores_only_the_first_steps(
        train_scene_list: list[ScenarioTensor]) -> None:
    from trafficrlhf_sdk.reward.builtin import RealismReward

    seen: list[int] = []

    class Recording(RealismReward):
        def agent_scores(self, scenario, logged=None):  # type: ignore[no-untyped-def]
            assert logged is not None and logged.num_steps == scenario.num_steps
            seen.append(scenario.num_steps - scenario.current_index - 1)
            return super().agent_scores(scenario, logged=logged)

    model = _model()
    config = AlignConfig(alpha=1.0, credit="agent", reward_horizon=5, **FAST)
    trainer = AlignTrainer(model, Recording(), config, scenes=train_scene_list)
    assert trainer.future_steps == model.horizon > 5  # the imitation loss keeps the whole horizon
    trainer._rollout(0)
    assert seen == [5]


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

    config = AlignConfig(credit="agent", failure_fraction=1.0, failure_scenes=8, failure_drive_s=6.0,
                         failure_lead_steps=(3, 8), **FAST)
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
    # log_reference="context" keeps the behaviour before the fix, to reproduce the runs trained with it
    seen.clear()
    old = AlignTrainer(_model(), Recording(), config.model_copy(update={"log_reference": "context"}),
                       scenes=train_scene_list)
    old._rollout(0)
    expected_old = contexts[torch.arange(contexts.num_scenes).repeat_interleave(s)].time_slice(
        start, start + scenario.num_steps)
    assert torch.equal(seen[-1][1].states, expected_old.states)


def test_failure_kinds_choose_which_failures_contexts_are_cut_before(
        train_scene_list: list[ScenarioTensor]) -> None:
    events = {}
    for kinds in (("collision",), ("offroad",), ("collision", "offroad")):
        config = AlignConfig(failure_fraction=1.0, failure_scenes=8, failure_drive_s=6.0, failure_lead_steps=(3, 3),
                             history_steps=10, contexts_per_epoch=6, failure_kinds=kinds)
        sampler = ContextSampler(ConstantVelocityPolicy(), config, lambda: train_scene_list, None, future_steps=20)
        contexts, _ = sampler.failure_contexts(6, torch.Generator().manual_seed(0))
        events[kinds] = sampler.last_failure_events
        if kinds == ("collision",) and events[kinds]:
            # driving on from "now", each context has a controlled agent in a collision within the 3-step lead
            from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

            now = contexts.current_index
            again = simulate(ConstantVelocityPolicy(), contexts, SimulationConfig(duration_s=0.4, start_index=now))
            window = again.simulated.time_slice(now + 1, now + 4)
            assert ((collisions_per_step(window) & window.valid).any(-1) & again.controlled).any(-1).all()
    # an agent counts once, at its first failure of the kinds asked for
    both = events[("collision", "offroad")]
    assert 0 < events[("collision",)] < both and 0 < events[("offroad",)] < both
    assert both <= events[("collision",)] + events[("offroad",)]


@pytest.mark.parametrize("kinds", [(), ("crash",)])
def test_failure_kinds_must_name_known_failures(kinds: tuple[str, ...]) -> None:
    with pytest.raises(ValueError, match="failure_kinds"):
        AlignConfig(failure_kinds=kinds)


def test_counterfactual_credit_varies_one_agent_and_holds_the_others_to_sample_zero(
        train_scene_list: list[ScenarioTensor]) -> None:
    config = AlignConfig(alpha=1.0, credit="agent", counterfactual_credit=True, **FAST)
    trainer = AlignTrainer(_model(), FailureReward(margins=True), config, scenes=train_scene_list)
    contexts, _ = trainer.context_sampler.draw(torch.Generator().manual_seed(0))
    out = trainer._sample(contexts, torch.Generator().manual_seed(1))
    agents = out.trace.agents
    assert (agents.sum(-1) >= 2).any()  # some context has two sampled agents, or the test proves nothing
    scores = trainer._counterfactual_agent_scores(contexts, out.futures, agents, None)
    states, valid = trainer._future_states(contexts, out.futures, agents)  # (B, S, A, H, 4): all take sample s
    b, s, a = out.futures.shape[:3]
    for ci in range(b):
        for i in agents[ci].nonzero().flatten().tolist():
            for k in range(s):
                by_hand = states[ci, 0].clone()  # everyone on sample 0 ...
                by_hand[i] = states[ci, k, i]  # ... but agent i on sample k
                scene = trainer._scenarios(contexts[ci], by_hand[None, None], valid[ci, :1][None])
                expected = FailureReward(margins=True).agent_scores(scene)[0, i]
                assert torch.isclose(scores[ci, k, i], expected, atol=1e-6)
    assert torch.all(scores[~agents[:, None, :].expand(b, s, a)] == 0)
    history = trainer.train()
    assert history[0]["first_ratio_max_dev"] == 0.0
    with pytest.raises(ValueError, match="counterfactual_credit"):
        AlignConfig(counterfactual_credit=True, credit="scene")


def test_counterfactual_credit_hands_log_comparing_rewards_the_logged_window(
        train_scene_list: list[ScenarioTensor]) -> None:
    from trafficrlhf_sdk.reward.builtin import RealismReward

    config = AlignConfig(alpha=1.0, credit="agent", counterfactual_credit=True, failure_fraction=0.5,
                         failure_scenes=4, failure_drive_s=4.0, **FAST)
    trainer = AlignTrainer(_model(), RealismReward(margins=True), config, scenes=train_scene_list)
    rollout = trainer._rollout(0)
    b, a = rollout.contexts.num_scenes, rollout.contexts.num_agents
    assert rollout.advantages.shape == (b, 3, a) and torch.isfinite(rollout.advantages).all()
    assert torch.all(rollout.advantages[~rollout.trace.agents[:, None, :].expand(b, 3, a)] == 0)


def test_speed_neutral_advantages_are_least_squares_residuals(train_scene_list: list[ScenarioTensor]) -> None:
    np = pytest.importorskip("numpy")
    config = AlignConfig(alpha=1.0, credit="agent", speed_neutral_advantages=True, **FAST)
    trainer = AlignTrainer(_model(), FailureReward(margins=True), config, scenes=train_scene_list)
    gen = torch.Generator().manual_seed(3)
    rewards, speed = torch.randn(4, 6, 3, generator=gen), 5 + 2 * torch.randn(4, 6, 3, generator=gen)
    adv = trainer._normalize(rewards, dim=1, covariate=speed)
    for c in range(4):
        for a in range(3):
            r, x = rewards[c, :, a].double().numpy(), speed[c, :, a].double().numpy()
            design = np.stack([np.ones_like(x), x], 1)
            residual = r - design @ np.linalg.lstsq(design, r, rcond=None)[0]
            expected = np.clip(residual / (r.std() + config.advantage_eps), -5, 5)
            assert np.allclose(adv[c, :, a].double().numpy(), expected, atol=1e-5)
    # rewards that are exactly a line in speed leave nothing to learn; a constant speed leaves the plain advantages
    assert trainer._normalize(3 - 0.5 * speed, dim=1, covariate=speed).abs().max() < 1e-4
    flat = torch.full_like(speed, 4.0)
    assert torch.allclose(trainer._normalize(rewards, dim=1, covariate=flat), trainer._normalize(rewards, dim=1))


def test_batch_advantage_scale_keeps_each_group_in_proportion_to_its_spread(
        train_scene_list: list[ScenarioTensor]) -> None:
    """'group' blows a group that differs by a hair up to the size of one with a failing sample; 'batch' divides
    every group by one RMS over the sampled entries, so their advantages keep the ratio of their spreads."""
    rewards = torch.zeros(2, 4, 2)
    rewards[0, :, 0] = torch.tensor([0.0, -1.0, 0.0, 0.0])  # agent 0 of context 0: one sample fails
    rewards[1, :, 0] = torch.tensor([0.0, -0.001, 0.0, 0.0])  # the same pattern, a thousand times smaller
    rewards[:, :, 1] = 7.0  # an agent that was not sampled: its values must not enter the scale
    mask = torch.zeros(2, 4, 2, dtype=torch.bool)
    mask[:, :, 0] = True
    per_group = AlignTrainer(_model(), FailureReward(), AlignConfig(alpha=1.0, credit="agent", **FAST),
                             scenes=train_scene_list)._normalize(rewards, dim=1, mask=mask)
    torch.testing.assert_close(per_group[0, :, 0], per_group[1, :, 0], atol=1e-2, rtol=1e-2)  # eps aside
    config = AlignConfig(alpha=1.0, credit="agent", advantage_scale="batch", **FAST)
    trainer = AlignTrainer(_model(), FailureReward(margins=True), config, scenes=train_scene_list)
    batch = trainer._normalize(rewards, dim=1, mask=mask)
    centred = rewards[:, :, 0] - rewards[:, :, 0].mean(1, keepdim=True)
    rms = centred.pow(2).mean().sqrt()
    torch.testing.assert_close(batch[:, :, 0], (centred / rms).clamp(-5, 5))
    assert batch[1, :, 0].abs().max() < 2e-3 * batch[0, :, 0].abs().max()
    rollout = trainer._rollout(0)
    b, a = rollout.contexts.num_scenes, rollout.contexts.num_agents
    sampled = rollout.trace.agents[:, None, :].expand(b, 3, a)
    assert torch.all(rollout.advantages[~sampled] == 0) and torch.isfinite(rollout.advantages).all()
    unclipped = rollout.advantages[sampled]
    assert unclipped.abs().max() > 0, "margins should tell some samples apart"
    if unclipped.abs().max() < config.advantage_clip:
        assert torch.isclose(unclipped.pow(2).mean().sqrt(), torch.tensor(1.0), atol=1e-3)


@pytest.mark.parametrize("credit", ["agent", "scene"])
def test_speed_neutral_rollout_advantages_are_orthogonal_to_sample_speed(
        train_scene_list: list[ScenarioTensor], credit: str) -> None:
    config = AlignConfig(alpha=1.0, credit=credit, speed_neutral_advantages=True, failure_fraction=0.5,
                         failure_scenes=4, failure_drive_s=4.0, **FAST)
    trainer = AlignTrainer(_model(), FailureReward(margins=True), config, scenes=train_scene_list)
    drawn = []
    sample = trainer._sample
    trainer._sample = lambda *args: drawn.append(sample(*args)) or drawn[-1]  # type: ignore[method-assign]
    rollout = trainer._rollout(0)
    del trainer._sample
    adv, agents = rollout.advantages, rollout.trace.agents
    speed = trainer._sample_speeds(drawn[0].futures)  # (B, S, A)
    assert torch.isfinite(adv).all()
    if credit == "scene":
        picked = agents[:, None, :].float()
        speed = (speed * picked).sum(-1) / picked.sum(-1).clamp_min(1)
        groups = agents.any(-1)  # (B,)
    else:
        groups = agents  # (B, A)
    centred = speed - speed.mean(1, keepdim=True)
    unclipped = adv.abs() < config.advantage_clip
    dot = (adv * centred * unclipped).sum(1)  # residuals are orthogonal to the centred speeds of their group
    assert torch.allclose(dot[groups], torch.zeros_like(dot[groups]), atol=1e-3)
    assert (adv != 0).any()  # the failure reward still ranks some samples
    history = trainer.train()
    assert history[0]["first_ratio_max_dev"] == 0.0


def _perturbed_draw(scenes: list[ScenarioTensor], fraction: float, lateral: float, yaw: float, count: int,
                    seed: int) -> tuple[ScenarioTensor, ScenarioTensor, int]:
    """``(contexts, logged, now)`` of one epoch's draw with perturbed contexts."""
    config = AlignConfig(perturb_fraction=fraction, perturb_lateral_m=lateral, perturb_yaw_rad=yaw,
                         **{**FAST, "contexts_per_epoch": count})
    sampler = ContextSampler(_model(), config, lambda: scenes, None, future_steps=20)
    contexts, logged = sampler.draw(torch.Generator().manual_seed(seed))
    return contexts, logged, contexts.current_index


def test_perturbed_contexts_start_beside_the_log_on_the_road_and_imitate_the_log(
        train_scene_list: list[ScenarioTensor]) -> None:
    contexts, logged, now = _perturbed_draw(train_scene_list, 0.5, 1.5, 0.2, count=8, seed=3)
    assert contexts.num_scenes == logged.num_scenes == 8
    moved = contexts[:4]  # perturbed first, then the log
    shift = torch.linalg.vector_norm(moved.xy[:, :, now] - logged[:4].xy[:, :, now], dim=-1)
    sampled = moved.controlled & moved.valid[:, :, now]
    assert int((shift[sampled] > 0.05).sum()) >= sampled.sum() // 2  # most controlled agents were moved ...
    assert float(shift.max()) <= 1.5 + 1e-4  # ... by at most the largest shift
    assert torch.equal(shift[~sampled], torch.zeros_like(shift[~sampled]))  # replayed agents stay on the log
    assert not bool((offroad_per_step(moved)[:, :, now] & sampled & (shift > 0)).any())  # nobody moved off-road
    # the future and the imitation target are the log's; the logged half is not moved at all
    assert torch.equal(moved.states[:, :, now + 1 :], logged[:4].states[:, :, now + 1 :])
    assert torch.equal(contexts[4:].states, logged[4:].states)


def test_a_perturbed_context_keeps_an_agent_on_its_log_where_the_move_would_leave_the_road(
        train_scene_list: list[ScenarioTensor]) -> None:
    contexts, logged, now = _perturbed_draw(train_scene_list, 1.0, 25.0, 0.0, count=6, seed=1)
    shift = torch.linalg.vector_norm(contexts.xy[:, :, now] - logged.xy[:, :, now], dim=-1)
    sampled = contexts.controlled & contexts.valid[:, :, now]
    kept = sampled & (shift < 1e-4)
    assert bool(kept.any())  # a 25 m shift puts some agents off the road: those keep their logged history
    assert not bool((offroad_per_step(contexts)[:, :, now] & sampled & ~kept).any())
    assert not bool((collisions_per_step(contexts)[:, :, now] & ~collisions_per_step(logged)[:, :, now]).any())


@pytest.mark.parametrize(("flags", "message"), [
    (["--perturbed-contexts", "0.5", "--perturb", "1.0"], "--perturb"),
    (["--perturbed-contexts", "0.5", "--perturb", "a,b"], "--perturb"),
    (["--perturbed-contexts", "0.5", "--failure-contexts", "0.75"], "perturb_fraction"),
])
def test_bad_perturbation_flags_get_one_clear_error(tmp_path, capsys, flags: list[str],  # type: ignore[no-untyped-def]
                                                    message: str) -> None:
    from trafficrlhf_sdk.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["align", "--model", "example_gru", "--reward-model", "builtin:collision", "--out", str(tmp_path),
              *flags])
    err = capsys.readouterr().err
    assert exit_info.value.code != 0 and message in err and "Traceback" not in err


def test_the_anchor_samples_uniform_log_contexts_and_pulls_towards_the_starting_model(
        train_scene_list: list[ScenarioTensor]) -> None:
    """With ``anchor_coef`` the rollout carries as many uniform log contexts as PPO contexts, with
    ``anchor_samples`` futures each; with the surrogate and imitation off, the anchor alone moves a model that
    drifted from its starting point back towards it (its KL estimate falls over the epoch's updates)."""
    config = AlignConfig(alpha=0.0, imitation_coef=0.0, anchor_coef=1.0, anchor_samples=2, learning_rate=1e-3,
                         **{**FAST, "ppo_epochs": 4})
    model = _model()
    trainer = AlignTrainer(model, FailureReward(), config, scenes=train_scene_list)
    assert trainer.reference is not None
    rollout = trainer._rollout(0)
    assert rollout.anchor is not None
    contexts, trace = rollout.anchor
    assert contexts.num_scenes == rollout.contexts.num_scenes and trace.agents.shape[0] == contexts.num_scenes
    assert model.log_prob(contexts, trace).shape[1] == 2  # anchor_samples futures per context
    with torch.no_grad():  # drift away from the reference
        torch.manual_seed(1)
        for p in model.module.parameters():
            p.add_(0.05 * torch.randn_like(p))

    def anchor_kl() -> float:
        return _kl_to_reference(trainer, model, contexts, trace)

    before = anchor_kl()
    stats = trainer._optimize(0, rollout)
    assert stats["anchor_kl"] > 0 and stats["updates"] >= 1
    assert anchor_kl() < before


def test_the_passing_anchor_zeroes_passing_agents_advantages_and_holds_them_at_the_start(
        train_scene_list: list[ScenarioTensor]) -> None:
    """``passing_anchor_coef``: an agent is *passing* when none of its samples collides or leaves the road
    (checked here with the metrics' own per-step tests); its advantages become 0 while every other agent keeps
    the advantage it has without the option; with the surrogate and imitation off, the anchor alone brings a
    drifted model back towards its start on the passing agents' samples."""
    common = dict(alpha=0.0, imitation_coef=0.0, credit="agent", failure_fraction=0.5, failure_scenes=4,
                  failure_drive_s=4.0, learning_rate=1e-3, **{**FAST, "ppo_epochs": 4})
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


def test_passing_with_margins_also_excludes_agents_that_come_near_a_failure(
        train_scene_list: list[ScenarioTensor]) -> None:
    config = AlignConfig(credit="agent", passing_anchor_coef=1.0, failure_fraction=0.5, failure_scenes=4,
                         failure_drive_s=4.0, **FAST)
    trainer = AlignTrainer(_model(), FailureReward(margins=True), config, scenes=train_scene_list)
    contexts, _ = trainer._contexts(0)
    out = trainer._sample(contexts, derived_generator(0, 0, "sample"))
    agents = out.trace.agents
    scenarios = trainer.sample_scenarios(contexts, out.futures, agents)
    plain = trainer._passing_agents(scenarios, agents, 3)
    trainer.config = config.model_copy(update={"passing_margins": True})
    strict = trainer._passing_agents(scenarios, agents, 3)
    assert not (strict & ~plain).any() and (plain & ~strict).any()
    near = FailureReward(margins=True).agent_scores(scenarios)
    clean = (near.reshape(out.futures.shape[:3]) == 0).all(1)  # (B, A): no sample with any cost
    assert torch.equal(strict, agents & clean)


def test_a_given_reference_is_the_model_the_anchor_pulls_towards(train_scene_list: list[ScenarioTensor]) -> None:
    """``reference=``: the KL terms hold the policy to that model (a frozen copy; the caller's object is left
    alone) instead of to the policy's own start: with the surrogate and imitation off, the anchor moves the
    policy towards the given reference, and its KL estimate to it falls over the epoch's updates."""
    config = AlignConfig(alpha=0.0, imitation_coef=0.0, anchor_coef=1.0, anchor_samples=2, learning_rate=1e-3,
                         **{**FAST, "ppo_epochs": 4})
    model, target = _model(), _model()
    with torch.no_grad():  # the reference sits away from where the policy starts
        torch.manual_seed(2)
        for p in target.module.parameters():
            p.add_(0.05 * torch.randn_like(p))
    kept = {k: v.clone() for k, v in target.module.state_dict().items()}
    trainer = AlignTrainer(model, FailureReward(), config, scenes=train_scene_list, reference=target)
    assert trainer.reference is not target
    assert all(not p.requires_grad for p in trainer.reference.module.parameters())
    for key, value in trainer.reference.module.state_dict().items():
        assert torch.equal(value, kept[key]), key
    rollout = trainer._rollout(0)
    assert rollout.anchor is not None
    contexts, trace = rollout.anchor

    before = _kl_to_reference(trainer, model, contexts, trace)
    assert before > 0  # the policy starts away from the reference, so the anchor has work to do
    trainer._optimize(0, rollout)
    assert _kl_to_reference(trainer, model, contexts, trace) < before
    for key, value in target.module.state_dict().items():
        assert torch.equal(value, kept[key]), key


def test_a_reference_that_cannot_score_the_policy_or_is_unused_is_refused(
        train_scene_list: list[ScenarioTensor]) -> None:
    anchored = AlignConfig(anchor_coef=1.0, **FAST)
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
