"""Tests of the ``bits`` adapter: contract (check_adapter), the frozen policy through a training step, exact
log-probabilities of the masked goal distribution, BITS selection, registry and CLI.

Tests on a small synthetic scene run everywhere; those on real nuScenes val scenes read
``<default_data_root()>/nuscenes_pred`` and are skipped when it is absent (nuScenes: CC BY-NC-SA 4.0).
"""

from __future__ import annotations

import os

import pytest
import torch

from trafficrlhf_sdk.models.adapter import PolicyTrace
from trafficrlhf_sdk.scenario import AgentType, MapRaster, ScenarioTensor, default_data_root
from trafficrlhf_sdk.testing.check_adapter import check_adapter

ROOT = os.path.join(default_data_root(), "nuscenes_pred")
HAS_DATA = os.path.isdir(os.path.join(ROOT, "label"))
needs_data = pytest.mark.skipif(not HAS_DATA, reason=f"nuscenes_pred data not found under {ROOT!r}")


def synthetic_scene(steps: int = 60, now: int = 30) -> ScenarioTensor:
    """A straight road along +x (drivable for |y| < 6 m); three cars and one padding slot."""
    t = torch.arange(steps, dtype=torch.float32) * 0.1
    rows = [torch.stack([x0 + v * t, torch.full_like(t, y), torch.full_like(t, v), torch.zeros_like(t)], -1)
            for x0, y, v in ((0.0, -2.0, 8.0), (20.0, -2.0, 6.0), (40.0, 2.0, 0.0))]
    rows.append(torch.zeros(steps, 4))
    valid = torch.ones(1, 4, steps, dtype=torch.bool)
    valid[:, 3] = False
    raster = torch.zeros(1, 3, 300, 60, dtype=torch.uint8)  # 2 px/m: x in [0, 150), y in [-15, 15)
    raster[:, 0, :, 18:42] = 1
    raster[:, 2, :, 29:31] = 1
    return ScenarioTensor(
        states=torch.stack(rows)[None] * valid[..., None],
        valid=valid,
        extent=torch.tensor([[[4.5, 1.9], [4.8, 2.0], [4.2, 1.8], [0.0, 0.0]]]),
        agent_type=torch.tensor([[AgentType.VEHICLE] * 3 + [AgentType.UNSET]]),
        controlled=torch.tensor([[True, True, True, False]]),
        current_index=now,
        map=MapRaster(raster=raster, world_to_pixel=torch.tensor([[[2.0, 0.0, 0.0], [0.0, 2.0, 30.0],
                                                                   [0.0, 0.0, 1.0]]])),
        scene_ids=("synthetic",),
    )


@pytest.fixture(scope="module")
def adapter():  # type: ignore[no-untyped-def]
    """The adapter with the bundled checkpoint."""
    from trafficrlhf_bits import BITSAdapter, default_checkpoint

    if not (default_checkpoint() / "model.safetensors").is_file():
        pytest.skip("bundled BITS checkpoint missing")
    return BITSAdapter(seed=0)


@pytest.fixture(scope="module")
def scenes() -> ScenarioTensor:
    """The first 3 long-enough val scenes."""
    if not HAS_DATA:
        pytest.skip("no data")
    from trafficrlhf_nuscenes_pred import NuScenesPredSource

    return NuScenesPredSource(root=ROOT).load_batch("val", 3)


# ------------------------------------------------------------------------------------------- contract
@needs_data
def test_check_adapter_on_real_scenes(adapter, scenes) -> None:  # type: ignore[no-untyped-def]
    facts = check_adapter(adapter, scenes)
    assert set(facts["parameters"]) == {"goal_encoder", "goal_decoder"}
    assert set(facts["groups_with_gradient"]) == {"goal_encoder", "goal_decoder"}
    assert facts["frozen_parameters"] == sum(p.numel() for p in adapter.model.policy.parameters()) > 0
    assert facts["log_prob_shape"] == (3, 3, scenes.num_agents)


def test_check_adapter_on_a_synthetic_scene(adapter) -> None:  # type: ignore[no-untyped-def]
    facts = check_adapter(adapter, synthetic_scene())
    assert facts["log_prob_shape"] == (1, 3, 4)


def test_policy_stays_bitwise_frozen_through_a_training_step(adapter) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_bits import BITSAdapter

    model = BITSAdapter(seed=0)  # a private copy: this test changes the goal network
    scene = synthetic_scene()
    groups = model.parameter_groups()
    offered = {id(p) for ps in groups.values() for p in ps}
    policy = dict(model.model.policy.named_parameters())
    assert not offered & {id(p) for p in policy.values()}, "a policy parameter is offered for training"
    assert offered == {id(p) for p in model.model.goal_net.parameters()}
    policy_before = {k: v.detach().clone() for k, v in model.model.policy.state_dict().items()}
    goal_before = {k: v.detach().clone() for k, v in model.model.goal_net.state_dict().items()}

    out = model.sample(scene, 4, generator=torch.Generator().manual_seed(0))
    model.module.train()
    loss = model.imitation_loss(scene) - model.log_prob(scene, out.trace.detach()).sum() / out.trace.agents.sum()
    optimizer = torch.optim.AdamW([p for ps in groups.values() for p in ps], lr=1e-2, weight_decay=0.1)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    model.module.eval()

    assert all(p.grad is None for p in policy.values())
    for key, value in model.model.policy.state_dict().items():
        assert torch.equal(value, policy_before[key]), f"policy tensor {key} changed"
    assert any(not torch.equal(v, goal_before[k]) for k, v in model.model.goal_net.state_dict().items())


def test_committed_aligned_checkpoint_plans_and_keeps_the_bundled_policy() -> None:
    """``reference_models/baselines/bits`` loads, plans 2 s, and differs from the bundled checkpoint only in the goal
    network: alignment never trains the goal-conditioned policy."""
    from safetensors.torch import load_file

    from trafficrlhf_bits import BITSAdapter, default_checkpoint

    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    aligned = os.path.join(repo, "reference_models", "baselines", "bits")
    model = BITSAdapter(checkpoint=aligned, seed=0)
    plan = model.plan(synthetic_scene(), 20).states
    assert plan.shape == (1, 4, 20, 4) and torch.isfinite(plan).all()
    mine = load_file(os.path.join(aligned, "model.safetensors"))
    base = load_file(str(default_checkpoint() / "model.safetensors"))
    assert mine.keys() == base.keys()
    policy = [k for k in base if k.startswith("policy.")]
    goal = [k for k in base if k.startswith("goal_net.") and base[k].is_floating_point()]
    assert policy and all(torch.equal(mine[k], base[k]) for k in policy)
    assert any(not torch.equal(mine[k], base[k]) for k in goal)


def test_log_prob_is_the_masked_goal_distribution(adapter) -> None:  # type: ignore[no-untyped-def]
    scene = synthetic_scene()
    out = adapter.sample(scene, 6, generator=torch.Generator().manual_seed(3))
    cell, drivable = out.trace.tensors["cell"], out.trace.tensors["drivable"]
    assert cell.shape == (1, 6, 4) and drivable.shape == (1, 6, 4, adapter.cfg.map_size**2)
    agents = out.trace.agents[:, None].expand(-1, 6, -1)
    assert drivable.gather(-1, cell[..., None])[..., 0][agents].all(), "a goal was drawn off the drivable cells"
    assert (out.log_prob[~agents] == 0).all() and (out.log_prob[agents] < 0).all()
    recomputed = adapter.log_prob(scene, out.trace.detach())
    assert recomputed.requires_grad
    torch.testing.assert_close(recomputed.detach(), out.log_prob, atol=1e-5, rtol=1e-5)
    # the stationary car is held still; the moving ones move forward
    assert torch.equal(out.futures[0, :, 2, :, :2], scene.states[0, 2, 30, :2].expand(6, 20, 2))
    assert (out.futures[0, :, 0, -1, 0] > scene.states[0, 0, 30, 0]).all()


@pytest.mark.parametrize("rule", ["rollout_start", "every_replan"])
def test_stationary_rule_decides_when_the_speed_is_read(rule) -> None:  # type: ignore[no-untyped-def]
    """Car 2 is stopped at the rollout start and car 0 moving; then car 2 drives off and car 0 stops.
    ``rollout_start`` (upstream) keeps holding car 2 and lets car 0 go on; ``every_replan`` does the opposite."""
    from trafficrlhf_bits import BITSAdapter

    scene = synthetic_scene()
    states = scene.states.clone()
    states[0, 0, 30, 2], states[0, 2, 30, 2] = 0.0, 6.0
    later = scene.replace_unchecked(states=states)
    model = BITSAdapter(seed=0, stationary_rule=rule)
    model.reset(scene)
    plan = model.plan(later, 20).states  # (1, 4, 20, 4)
    held = (plan[0, :3, :, :2] == later.states[0, :3, 30, None, :2]).all(-1).all(-1)
    assert held.tolist() == ([False, False, True] if rule == "rollout_start" else [True, False, False])


def test_plan_picks_the_best_bits_score(adapter) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_bits import BITSAdapter

    scene = synthetic_scene()
    model = BITSAdapter(seed=0, plan_samples=8)
    model.reset(scene)
    plan = model.plan(scene, 50)
    assert plan.states.shape == (1, 4, 50, 4) and torch.isfinite(plan.states).all()
    # with only the drivable-area term, the executed plan is one of the on-road samples when there is one
    off = BITSAdapter(seed=0, plan_samples=8, selection_weights=(0.0, 0.0, 1.0))
    off.reset(scene)
    chosen = off.plan(scene, 20).states[0, :2, :, :2]  # the two moving cars
    lookup = scene.map.lookup(chosen.reshape(1, -1, 2)).reshape(2, 20)  # type: ignore[union-attr]
    assert lookup.all()


def test_train_on_selection_samples_what_plan_executes(adapter) -> None:  # type: ignore[no-untyped-def]
    """Each sample is BITS's choice among a goal set; its log-probability is the set's; same draw as plan()."""
    from trafficrlhf_bits import BITSAdapter
    from trafficrlhf_sdk.simulation.guidance import GuidanceSet

    scene = synthetic_scene()
    k = 4
    model = BITSAdapter(seed=0, plan_samples=k, train_on_selection=True, guidance="no_collision")
    guidance = GuidanceSet.parse("no_collision")
    guidance.fit(scene)
    out = model.sample(scene, 3, guidance, generator=torch.Generator().manual_seed(5))
    cell = out.trace.tensors["cell"]
    assert out.futures.shape == (1, 3, 4, 20, 4) and cell.shape == (1, 3, 4, k)
    # the set's log-probability = the sum of its goals' (each under the masked goal distribution)
    single = BITSAdapter(seed=0)
    single.model.load_state_dict(model.model.state_dict())
    flat = PolicyTrace({"cell": cell.permute(0, 1, 3, 2).reshape(1, 3 * k, 4),
                        "drivable": out.trace.tensors["drivable"].repeat_interleave(k, 1)}, out.trace.agents, 30)
    per_goal = single.log_prob(scene, flat).reshape(1, 3, k, 4).sum(2)
    torch.testing.assert_close(out.log_prob, per_goal.detach(), atol=1e-4, rtol=1e-5)
    recomputed = model.log_prob(scene, out.trace.detach())
    assert recomputed.requires_grad
    torch.testing.assert_close(recomputed.detach(), out.log_prob, atol=1e-5, rtol=1e-5)
    # one group with plan()'s generator state executes exactly plan()'s choice
    model.reset(scene)
    planned = model.plan(scene, 20).states
    model.reset(scene)
    again = model._sample_selected(scene, 1, model.guidance, model._generator).futures[:, 0]
    torch.testing.assert_close(again, planned)


def test_guided_plan_runs_every_guidance(adapter) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_bits import BITSAdapter

    scene = synthetic_scene()
    for name in ("speed_limit", "target_speed", "no_collision", "no_offroad", "goal_waypoint"):
        model = BITSAdapter(seed=0, guidance=name)
        model.reset(scene)
        assert torch.isfinite(model.plan(scene, 20).states).all(), name


# ------------------------------------------------------------------------------------------- plugin system
def test_registry_entry_point() -> None:
    from trafficrlhf_sdk import get_traffic_model, list_plugins
    from trafficrlhf_sdk.plugins import registry

    from trafficrlhf_bits import BITSAdapter, default_checkpoint

    assert registry("traffic_models").get("bits") is BITSAdapter
    assert registry("traffic_models").owner("bits") == "bits"
    row = {r["name"]: r for r in list_plugins()}["bits"]
    assert "register_traffic_models" in row["hooks"] and not row["default"]
    if (default_checkpoint() / "model.safetensors").is_file():
        assert isinstance(get_traffic_model("bits", seed=1), BITSAdapter)


@pytest.mark.slow
@needs_data
def test_cli_evaluate(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import json

    from click.testing import CliRunner

    from trafficrlhf_sdk.cli import get_cli

    result = CliRunner().invoke(get_cli(), ["evaluate", "--model", "bits", "--scenes", "3", "--out", str(tmp_path),
                                            "--json"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "results.json").read_text())
    assert report["metadata"]["model"] == "bits" and report["num_scenes"] == 3
    assert 0.0 <= report["metrics"]["failure_rate"] <= 1.0
