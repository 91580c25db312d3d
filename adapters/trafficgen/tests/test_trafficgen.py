"""Tests of the ``trafficgen`` adapter: contract (check_adapter), the frozen initializer, initialization under a
seed, the mixture density, greedy planning, registry and CLI.

Data-dependent tests are skipped when ``trafficrlhf_sdk.scenario.default_data_root()`` lacks nuscenes_pred; the
others run on a small synthetic scene.
"""

from __future__ import annotations

import math
import os

import pytest
import torch

from trafficrlhf_sdk.simulation.dynamics import unicycle_rollout as sdk_unicycle_rollout
from trafficrlhf_sdk.models.adapter import PolicyTrace
from trafficrlhf_sdk.scenario import AgentType, MapRaster, ScenarioTensor, default_data_root

ROOT = os.path.join(default_data_root(), "nuscenes_pred")
HAS_DATA = os.path.isdir(os.path.join(ROOT, "label"))
needs_data = pytest.mark.skipif(not HAS_DATA, reason=f"nuscenes_pred data not found under {ROOT!r}")


def _checkpoint_or_skip():  # type: ignore[no-untyped-def]
    from trafficrlhf_trafficgen import default_checkpoint

    if not (default_checkpoint() / "model.safetensors").is_file():
        pytest.skip("bundled TrafficGen checkpoint missing")


@pytest.fixture(scope="module")
def adapter():  # type: ignore[no-untyped-def]
    """The adapter with the bundled checkpoint."""
    from trafficrlhf_trafficgen import TrafficGenAdapter

    _checkpoint_or_skip()
    return TrafficGenAdapter(seed=0)


@pytest.fixture(scope="module")
def scenes():  # type: ignore[no-untyped-def]
    """The first 3 long-enough val scenes."""
    if not HAS_DATA:
        pytest.skip("no data")
    from trafficrlhf_nuscenes_pred import NuScenesPredSource

    return NuScenesPredSource(root=ROOT).load_batch("val", 3)


@pytest.fixture(scope="module")
def synthetic() -> ScenarioTensor:
    """One 200 m x 40 m road (3 px/m) along x, three vehicles driving along it at 5-8 m/s, 6 s at 0.1 s."""
    raster = torch.zeros(1, 3, 600, 300, dtype=torch.uint8)
    raster[:, 0, :, 90:210] = 1  # drivable band y in [30, 70) m
    world_to_pixel = torch.tensor([[[3.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 1.0]]])
    t = torch.arange(60) * 0.1
    starts, lanes, speeds = (20.0, 45.0, 70.0), (45.0, 55.0, 45.0), (6.0, 5.0, 8.0)
    states = torch.stack([torch.stack([x0 + v * t, torch.full_like(t, y), torch.full_like(t, v), torch.zeros_like(t)],
                                      -1) for x0, y, v in zip(starts, lanes, speeds)])[None]
    return ScenarioTensor(
        states=states, valid=torch.ones(1, 3, 60, dtype=torch.bool), extent=torch.tensor([[[4.5, 1.9]] * 3]),
        agent_type=torch.full((1, 3), int(AgentType.VEHICLE)), controlled=torch.ones(1, 3, dtype=torch.bool),
        dt=0.1, current_index=30, map=MapRaster(raster=raster, world_to_pixel=world_to_pixel),
    )


# --------------------------------------------------------------------------------------------- contract
@needs_data
def test_check_adapter(adapter, scenes) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.testing.check_adapter import check_adapter

    facts = check_adapter(adapter, scenes)
    assert facts["log_prob_shape"] == (3, 3, scenes.num_agents)
    assert set(facts["groups_with_gradient"]) == {"encoder", "decoder"}
    assert facts["frozen_parameters"] == sum(p.numel() for p in adapter.model.initializer.parameters())


def test_check_adapter_synthetic(adapter, synthetic) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.testing.check_adapter import check_adapter

    facts = check_adapter(adapter, synthetic, check_save_load=False)
    assert facts["frozen_parameters"] > 0
    assert facts["choices"] == adapter.cfg.modes


@pytest.mark.parametrize("broken", ["detached", "unnormalized"])
def test_check_adapter_catches_broken_choices(synthetic, broken) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_trafficgen import TrafficGenAdapter
    from trafficrlhf_sdk.testing.check_adapter import AdapterCheckError, check_adapter

    _checkpoint_or_skip()
    adapter = TrafficGenAdapter(seed=0)
    inner = adapter.choice_log_prob
    adapter.choice_log_prob = (lambda c: inner(c).detach()) if broken == "detached" else (lambda c: inner(c) + 1.0)
    with pytest.raises(AdapterCheckError, match="no gradient" if broken == "detached" else "more than 1"):
        check_adapter(adapter, synthetic, check_save_load=False)


def test_initializer_bitwise_frozen_through_training_step(adapter, synthetic) -> None:  # type: ignore[no-untyped-def]
    """An Adam step (with weight decay) on every offered group moves the forecaster, not a bit of the initializer."""
    offered = {id(p) for ps in adapter.parameter_groups().values() for p in ps}
    assert not offered & {id(p) for p in adapter.model.initializer.parameters()}, "initializer parameters offered"
    frozen = {k: v.clone() for k, v in adapter.model.initializer.state_dict().items()}
    forecaster = {k: v.clone() for k, v in adapter.model.forecaster.state_dict().items()}
    weights = {k: v.clone() for k, v in adapter.model.state_dict().items()}
    try:
        optimizer = torch.optim.AdamW([p for ps in adapter.parameter_groups().values() for p in ps], lr=1e-2,
                                      weight_decay=0.1)
        out = adapter.sample(synthetic, 2, None, torch.Generator().manual_seed(0))
        loss = adapter.imitation_loss(synthetic) - adapter.log_prob(synthetic, out.trace.detach()).sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        for key, value in adapter.model.initializer.state_dict().items():
            assert torch.equal(value, frozen[key]), f"initializer tensor {key} changed"
        moved = [k for k, v in adapter.model.forecaster.state_dict().items() if not torch.equal(v, forecaster[k])]
        assert moved, "the training step did not move the forecaster"
    finally:
        adapter.model.load_state_dict(weights)
        adapter.model.zero_grad(set_to_none=True)


# --------------------------------------------------------------------------------------------- initializer
def _check_initialized(scene: ScenarioTensor, init: ScenarioTensor) -> None:
    from trafficgen_reference.model import boxes_overlap

    valid = init.valid[0, :, 0]
    assert valid.sum() >= 2, "the initializer placed no vehicle"
    assert init.map.lookup(init.xy[:, :, 0])[0][valid].all(), "a vehicle was placed off the drivable area"
    length, width = init.extent[0, valid, 0], init.extent[0, valid, 1]
    assert ((length >= 2.5) & (length <= 18.0) & (width >= 1.4) & (width <= 3.2)).all()
    assert (init.speed[0, valid, 0] >= 0).all()
    boxes = torch.cat([init.states[0, valid, 0][:, [0, 1, 3]], init.extent[0, valid]], -1)
    for i in range(1, boxes.shape[0]):  # placed boxes overlap neither each other nor the context agent
        assert not boxes_overlap(boxes[i], boxes[:i]).any()
    # the context agent is the logged one
    slot = init.extras["initialized"]["context_slot"]
    torch.testing.assert_close(init.states[0, 0, 0], scene.states[0, slot, scene.current_index])


def test_initialize_scene_synthetic(adapter, synthetic) -> None:  # type: ignore[no-untyped-def]
    init = adapter.initialize_scene(synthetic, seed=4, num_agents=4)
    _check_initialized(synthetic, init)
    again = adapter.initialize_scene(synthetic, seed=4, num_agents=4)
    assert torch.equal(init.states, again.states) and torch.equal(init.extent, again.extent)


@needs_data
def test_initialize_scene_on_drivable_and_deterministic(adapter, scenes) -> None:  # type: ignore[no-untyped-def]
    for i in range(scenes.num_scenes):
        scene = scenes[i]
        init = adapter.initialize_scene(scene, seed=11, num_agents=6)
        _check_initialized(scene, init)
        again = adapter.initialize_scene(scene, seed=11, num_agents=6)
        assert torch.equal(init.states, again.states) and torch.equal(init.extent, again.extent)
    other = adapter.initialize_scene(scenes[0], seed=12, num_agents=6)
    first = adapter.initialize_scene(scenes[0], seed=11, num_agents=6)
    assert not torch.equal(other.states, first.states), "the seed does not change the placement"


# --------------------------------------------------------------------------------------------- density
def test_log_density_prefers_the_mode_mean(adapter, synthetic) -> None:  # type: ignore[no-untyped-def]
    """The most likely mode's mean scores higher than the same actions shifted far away; the marginal mixture
    density is at least the joint (mode, actions) density."""
    now = synthetic.current_index
    agents = synthetic.controlled & synthetic.valid[:, :, now]
    with torch.no_grad():
        out, _ = adapter._forecast(synthetic, agents)
    best = out.log_pi.argmax(-1)
    mean = out.mean[torch.arange(best.shape[0]), best]  # (N, H, 2)
    far = mean + torch.tensor([3.0, 0.5])
    b, a = agents.shape
    actions = torch.zeros(b, a, 2, adapter.horizon, 2)
    actions[agents] = torch.stack([mean, far], 1)
    mode = torch.zeros(b, a, 2, dtype=torch.long)
    mode[agents] = best[:, None].expand(-1, 2)
    trace = PolicyTrace({"mode": mode.transpose(1, 2), "actions": actions.transpose(1, 2)}, agents, now)
    with torch.no_grad():
        joint = adapter.log_prob(synthetic, trace)  # (B, 2, A)
        marginal = adapter.marginal_log_prob(synthetic, trace)
    mask = agents[:, None].expand(-1, 2, -1)
    assert (joint[:, 0][agents] > joint[:, 1][agents] + 10).all()
    assert (marginal[mask] >= joint[mask] - 1e-4).all()


def test_choices_are_the_modes_mean_plans_with_their_probabilities(adapter, synthetic) -> None:  # type: ignore[no-untyped-def]
    """``choice_futures`` rolls every mode's mean actions out for the sampled agents; ``choice_log_prob`` is the
    mode distribution (summing to 1 over the modes, 0 for agents not sampled) and carries gradients."""
    from trafficgen_reference.model import unicycle_rollout

    now = synthetic.current_index
    agents = synthetic.controlled & synthetic.valid[:, :, now]
    futures = adapter.choice_futures(synthetic)
    m = adapter.cfg.modes
    assert futures.shape == (1, m, 3, adapter.horizon, 4) and not futures.requires_grad
    with torch.no_grad():
        out, state_now = adapter._forecast(synthetic, agents)
    expected = unicycle_rollout(state_now[:, None].expand(-1, m, 4), out.mean, 0.1)  # (N, M, H, 4)
    torch.testing.assert_close(futures.transpose(1, 2)[agents], expected)
    log_prob = adapter.choice_log_prob(synthetic)
    assert log_prob.shape == (1, m, 3) and log_prob.requires_grad
    torch.testing.assert_close(log_prob.exp().sum(1)[agents], torch.ones(int(agents.sum())))
    torch.testing.assert_close(log_prob.transpose(1, 2)[agents], out.log_pi)
    log_prob.exp()[:, 0].sum().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in adapter.parameter_groups()["decoder"])
    adapter.module.zero_grad(set_to_none=True)


def test_choice_coef_needs_a_trained_group_that_moves_the_modes(synthetic) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_trafficgen import TrafficGenAdapter
    from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
    from trafficrlhf_sdk.errors import TrafficRLHFError
    from trafficrlhf_sdk.reward.builtin import FailureReward

    _checkpoint_or_skip()
    config = AlignConfig(choice_coef=1.0, credit="agent", groups=("steer",), epochs=1, contexts_per_epoch=2,
                         samples_per_context=2, progress_bar=False)
    trainer = AlignTrainer(TrafficGenAdapter(seed=0, steer_head=True), FailureReward(), config, scenes=synthetic)
    with pytest.raises(TrafficRLHFError, match=r"no trained parameter group \['steer'\] moves"):
        trainer.train()


def test_unicycle_matches_sdk_dynamics() -> None:
    """The model's own unicycle equals the SDK's (no bounds) while the speed stays positive."""
    from trafficgen_reference.model import unicycle_rollout

    gen = torch.Generator().manual_seed(0)
    state = torch.tensor([[1.0, -2.0, 8.0, 0.3], [0.0, 0.0, 5.0, -2.0]])
    actions = torch.randn(2, 20, 2, generator=gen) * torch.tensor([1.0, 0.2])
    torch.testing.assert_close(unicycle_rollout(state, actions, 0.1), sdk_unicycle_rollout(state, actions, 0.1, None))
    stop = unicycle_rollout(torch.tensor([[0.0, 0.0, 1.0, 0.0]]), torch.full((1, 20, 2), -5.0), 0.1)
    assert (stop[..., 2] >= 0).all() and stop[0, -1, 0] <= 0.1 + 1e-6  # stops instead of reversing


def test_boxes_overlap() -> None:
    from trafficgen_reference.model import boxes_overlap

    box = torch.tensor([0.0, 0.0, 0.0, 4.0, 2.0])
    others = torch.tensor([[3.9, 0.0, 0.0, 4.0, 2.0], [4.1, 0.0, 0.0, 4.0, 2.0], [0.0, 2.5, math.pi / 2, 4.0, 2.0],
                           [2.2, 2.2, math.pi / 4, 1.0, 1.0]])
    assert boxes_overlap(box, others).tolist() == [True, False, True, False]


# --------------------------------------------------------------------------------------------- policy
def test_greedy_plan_is_the_most_likely_mode_mean(adapter, synthetic) -> None:  # type: ignore[no-untyped-def]
    from trafficgen_reference.model import unicycle_rollout

    adapter.reset(synthetic)
    plan = adapter.plan(synthetic, 30).states  # 20 planned steps + 10 held at constant velocity
    assert plan.shape == (1, 3, 30, 4)
    assert torch.equal(plan, adapter.plan(synthetic, 30).states)
    now = synthetic.current_index
    agents = synthetic.controlled & synthetic.valid[:, :, now]
    with torch.no_grad():
        out, state_now = adapter._forecast(synthetic, agents)
    best = out.log_pi.argmax(-1)
    expected = unicycle_rollout(state_now, out.mean[torch.arange(best.shape[0]), best], 0.1)
    torch.testing.assert_close(plan[agents][:, : adapter.horizon], expected)


def test_guidance_filters_samples(synthetic) -> None:  # type: ignore[no-untyped-def]
    """With guidance the plan is the best of ``plan_samples`` samples (each guidance name is accepted)."""
    from trafficrlhf_trafficgen import TrafficGenAdapter

    _checkpoint_or_skip()
    for name in ("speed_limit", "target_speed", "no_collision", "no_offroad", "goal_waypoint"):
        guided = TrafficGenAdapter(seed=0, guidance=name, plan_samples=4)
        guided.reset(synthetic)
        plan = guided.plan(synthetic, 20).states
        assert plan.shape == (1, 3, 20, 4) and torch.isfinite(plan).all()
    guided = TrafficGenAdapter(seed=0, guidance="speed_limit", plan_samples=8)
    guided.reset(synthetic)
    guided.guidance.guidances[0].limit = torch.tensor([1.0])  # a tight limit: the chosen plan must be the slowest
    gen = torch.Generator().manual_seed(0)
    out = guided.sample(synthetic, 8, None, gen)
    loss = guided.guidance.loss(out.futures, synthetic.current_index, synthetic)  # (1, 8, 3)
    guided.reset(synthetic)
    guided.guidance.guidances[0].limit = torch.tensor([1.0])
    plan = guided.plan(synthetic, 20).states
    chosen = loss.argmin(1)[0]  # per agent
    for agent in range(3):
        torch.testing.assert_close(plan[0, agent], out.futures[0, int(chosen[agent]), agent])


@needs_data
def test_choice_coef_moves_the_modes_towards_the_better_scored_ones(adapter) -> None:  # type: ignore[no-untyped-def]
    """With ``choice_coef`` the rollout scores every mode's plan of every sampled agent (advantages ``(B, M, A)``,
    mean 0 over the modes, 0 for agents not sampled), and updates on that term alone raise the expected reward
    over the modes on the same contexts (the failure reward with its margins, so that modes differ)."""
    import copy

    from trafficrlhf_nuscenes_pred import NuScenesPredSource
    from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
    from trafficrlhf_sdk.reward.builtin import FailureReward

    scenes = NuScenesPredSource(root=ROOT).load_batch("train", 6)
    model = copy.deepcopy(adapter)
    config = AlignConfig(alpha=1.0, imitation_coef=0.0, choice_coef=1.0, credit="agent", failure_fraction=0.0,
                         epochs=1, contexts_per_epoch=6, samples_per_context=2, minibatch_contexts=6,
                         ppo_epochs=8, learning_rate=1e-3, progress_bar=False)
    trainer = AlignTrainer(model, FailureReward(margins=True), config, scenes=scenes)
    rollout = trainer._rollout(0)
    adv, agents = rollout.choice_advantages, rollout.trace.agents
    b, a = agents.shape
    assert adv is not None and adv.shape == (b, adapter.cfg.modes, a)
    assert torch.all(adv.transpose(1, 2)[~agents] == 0)
    torch.testing.assert_close(adv.mean(1), torch.zeros(b, a))
    assert (adv != 0).any(), "the draw needs an agent whose modes differ"
    choices = trainer.sample_scenarios(rollout.contexts, model.choice_futures(rollout.contexts), agents)
    reward = FailureReward(margins=True).agent_scores(choices).reshape(adv.shape)

    def expected_reward() -> float:
        with torch.no_grad():
            prob = model.choice_log_prob(rollout.contexts).exp()
        return float(((prob * reward).sum(1))[agents].mean())

    before = expected_reward()
    rollout.advantages = torch.zeros_like(rollout.advantages)  # the surrogate off: the choice term alone moves it
    stats = trainer._optimize(0, rollout)
    assert stats["updates"] == 8
    assert expected_reward() > before


# --------------------------------------------------------------------------------------------- registry / CLI
def test_registry_entry_point() -> None:
    from importlib.metadata import entry_points

    from trafficrlhf_sdk import get_traffic_model
    from trafficrlhf_sdk.plugins import registry

    from trafficrlhf_trafficgen import TrafficGenAdapter

    names = {ep.name: ep.value for ep in entry_points(group="trafficrlhf_sdk")}
    assert names.get("trafficgen") == "trafficrlhf_trafficgen"
    assert registry("traffic_models").get("trafficgen") is TrafficGenAdapter
    _checkpoint_or_skip()
    assert isinstance(get_traffic_model("trafficgen", seed=1), TrafficGenAdapter)


@needs_data
def test_cli_evaluate(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """`trafficrlhf evaluate --model trafficgen` on 3 scenes (about 2 s)."""
    from click.testing import CliRunner

    from trafficrlhf_sdk.cli import cli

    _checkpoint_or_skip()
    result = CliRunner().invoke(cli, ["evaluate", "--model", "trafficgen", "--scenes", "3", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "results.json").is_file()


# --------------------------------------------------------------------------------------------- committed weights
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
BUNDLED = "reference_models/trafficgen/checkpoints/trafficgen_small"
COMMITTED = {  # committed TrafficGen checkpoints, their forecast horizons (steps of 0.1 s) and their starting weights
    BUNDLED: (20, None),
    "reference_models/trafficgen/checkpoints/trafficgen_small_4s": (40, BUNDLED),
    "reference_models/baselines/trafficgen": (40, "reference_models/trafficgen/checkpoints/trafficgen_small_4s"),
}


@pytest.mark.parametrize("path", sorted(COMMITTED))
def test_committed_checkpoints_plan_and_keep_the_initializer(path, synthetic) -> None:  # type: ignore[no-untyped-def]
    """Every committed checkpoint loads, plans its horizon, and shares the bundled initializer bitwise (it is
    frozen everywhere: alignment never trains it, the 4 s forecaster was trained with ``--init-from``)."""
    from safetensors.torch import load_file

    from trafficrlhf_trafficgen import TrafficGenAdapter

    horizon, start = COMMITTED[path]
    full = os.path.join(REPO, path)
    adapter = TrafficGenAdapter(checkpoint=full, seed=0)
    assert adapter.horizon == horizon
    plan = adapter.plan(synthetic, horizon).states
    assert plan.shape == (1, 3, horizon, 4) and torch.isfinite(plan).all()
    if start is not None:
        mine = load_file(os.path.join(full, "model.safetensors"))
        base = load_file(os.path.join(REPO, start, "model.safetensors"))
        initializer = [k for k in base if k.startswith("initializer.")]
        assert initializer and all(torch.equal(mine[k], base[k]) for k in initializer)
        forecaster = [k for k in base if k.startswith("forecaster.") and base[k].is_floating_point()]
        assert any(mine[k].shape != base[k].shape or not torch.equal(mine[k], base[k]) for k in forecaster)


# --------------------------------------------------------------------------------------------- training script
@needs_data
@pytest.mark.slow
def test_train_longer_horizon_copies_the_initializer(synthetic, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``train --horizon 40 --init-from CKPT``: a 4 s forecaster beside the donor's initializer, bitwise; the
    adapter loads it and plans 40 steps."""
    from safetensors.torch import load_file

    from trafficgen_reference.train import main
    from trafficrlhf_trafficgen import TrafficGenAdapter, default_checkpoint

    _checkpoint_or_skip()
    out = tmp_path / "tg_4s"
    main(["--out", str(out), "--horizon", "40", "--init-from", str(default_checkpoint()), "--steps", "3",
          "--train-scenes", "3", "--val-every", "1000"])
    donor, trained = load_file(default_checkpoint() / "model.safetensors"), load_file(out / "model.safetensors")
    initializer = [k for k in donor if k.startswith("initializer.")]
    assert initializer and all(torch.equal(donor[k], trained[k]) for k in initializer)
    assert any(not torch.equal(donor[k], trained[k]) for k in donor if k.startswith("forecaster.")
               and donor[k].shape == trained[k].shape)
    adapter = TrafficGenAdapter(checkpoint=str(out), seed=0)
    assert adapter.horizon == 40
    plan = adapter.plan(synthetic, 40).states
    assert plan.shape == (1, 3, 40, 4) and torch.isfinite(plan).all()


def test_train_rejects_a_bad_horizon_and_a_missing_donor(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from trafficgen_reference.train import main

    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--horizon", "15"])
    assert "--horizon must be an even number" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--init-from", str(tmp_path / "nowhere")])
    assert "--init-from" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------- heads
@pytest.mark.parametrize("option, group", [("road_head", "road"), ("steer_head", "steer")])
def test_a_head_starts_with_zero_effect_and_saves_with_the_model(synthetic, tmp_path, option, group) -> None:  # type: ignore[no-untyped-def]
    """A new head leaves samples and log-probabilities exactly as the base's, gets gradients, and once trained
    changes them and travels with the checkpoint."""
    from trafficrlhf_trafficgen import TrafficGenAdapter

    _checkpoint_or_skip()
    base, head = TrafficGenAdapter(seed=0), TrafficGenAdapter(seed=0, **{option: True})
    assert set(head.parameter_groups()) == {"encoder", "decoder", group} and group not in base.parameter_groups()
    for key, value in base.module.state_dict().items():
        assert torch.equal(value, head.module.state_dict()[key]), key
    drawn = base.sample(synthetic, 6, None, torch.Generator().manual_seed(0))
    again = head.sample(synthetic, 6, None, torch.Generator().manual_seed(0))
    assert torch.equal(drawn.futures, again.futures)
    log_prob = head.log_prob(synthetic, again.trace)
    torch.testing.assert_close(log_prob, base.log_prob(synthetic, drawn.trace))
    log_prob.sum().backward()
    last = head.parameter_groups()[group][-2:]  # the zero-initialized last layer: the only one with gradients yet
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in last)
    with torch.no_grad():  # a trained head: it changes the policy, and the checkpoint keeps it
        for p in head.parameter_groups()[group]:
            p.add_(0.1)
    if group == "steer":  # (on the synthetic road every mode stays on it, so a road head shifts them alike)
        assert not torch.allclose(head.log_prob(synthetic, again.trace), log_prob)
    head.save_pretrained(str(tmp_path / group))
    loaded = TrafficGenAdapter.from_pretrained(str(tmp_path / group), seed=0)
    assert getattr(loaded.cfg, option)
    torch.testing.assert_close(loaded.log_prob(synthetic, again.trace), head.log_prob(synthetic, again.trace))
    for key, value in head.module.state_dict().items():
        assert torch.equal(value, loaded.module.state_dict()[key]), key


def test_road_features_read_the_drivable_area_along_each_plan() -> None:
    from trafficgen_reference.model import Forecaster, TrafficGenConfig

    cfg = TrafficGenConfig(horizon=20, road_head=True)
    forecaster = Forecaster(cfg)
    size = cfg.map_size
    crop = torch.zeros(1, cfg.map_channels, size, size)
    crop[0, 0, :, 17:23] = 1  # a 6 m corridor straight ahead: agent-frame y in [-3, 3)
    history = torch.zeros(1, cfg.history_steps, 5)
    history[:, -1, 2] = 5.0  # 5 m/s now
    f = {"map": crop, "history": history}
    mean = torch.zeros(1, 2, cfg.horizon, 2)
    mean[0, 1, :, 1] = 1.0  # mode 1 turns left at 1 rad/s: it leaves the corridor
    features = forecaster.road_features(f, mean)  # (1, 2, 4K): (on, left of, right of) the plan per point, inside
    k = cfg.horizon // 5
    probes, inside = features[0, :, : 3 * k].reshape(2, k, 3), features[0, :, 3 * k:]
    on, left, right = probes.unbind(-1)
    assert torch.equal(probes[0], torch.ones(k, 3)) and torch.equal(inside, torch.ones(2, k))
    # the turning plan starts in the corridor and has left it, on and beside the plan, by 2 s
    assert on[1, -1] == 0 and left[1, -1] == 0 and on[1, 0] == 1 and right[1, 0] == 1
