"""Tests of the ``ctg`` adapter: contract (check_adapter), guidance, exact log-probabilities, registry, CLI.

Data-dependent tests are skipped when ``trafficrlhf_sdk.scenario.default_data_root()`` lacks nuscenes_pred.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
import torch

from trafficrlhf_sdk.guidance import GuidanceSet, SpeedLimitGuidance
from trafficrlhf_sdk.scenario import default_data_root

ROOT = os.path.join(default_data_root(), "nuscenes_pred")
HAS_DATA = os.path.isdir(os.path.join(ROOT, "label"))
needs_data = pytest.mark.skipif(not HAS_DATA, reason=f"nuscenes_pred data not found under {ROOT!r}")


@pytest.fixture(scope="module")
def scenes():  # type: ignore[no-untyped-def]
    """The first 3 long-enough val scenes."""
    if not HAS_DATA:
        pytest.skip("no data")
    from trafficrlhf_nuscenes_pred import NuScenesPredSource

    return NuScenesPredSource(root=ROOT).load_batch("val", 3)


@pytest.fixture(scope="module")
def adapter():  # type: ignore[no-untyped-def]
    """The adapter with the bundled checkpoint."""
    from trafficrlhf_ctg import CTGAdapter, default_checkpoint

    if not (default_checkpoint() / "model.safetensors").is_file():
        pytest.skip("bundled CTG checkpoint missing")
    return CTGAdapter(seed=0)


@needs_data
def test_check_adapter(adapter, scenes) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.testing.check_adapter import check_adapter

    facts = check_adapter(adapter, scenes)
    assert facts["log_prob_shape"][3] == adapter.cfg.sample_steps
    assert set(facts["groups_with_gradient"]) == {"encoder", "decoder"}
    assert 300_000 <= sum(facts["parameters"].values()) <= 1_500_000


REPO = Path(__file__).resolve().parents[3]
COMMITTED = {  # committed CTG checkpoints and their plan horizons (steps of 0.1 s)
    "reference_models/ctg/checkpoints/ctg_small": 20,
    "reference_models/ctg/checkpoints/ctg_small_4s": 40,
    "reference_models/aligned/ctg": 20,
    "reference_models/aligned/ctg_4s": 40,
    "reference_models/aligned/ctg_4s_road": 40,
    "reference_models/aligned/ctg_4s_gated": 40,
}


@needs_data
@pytest.mark.parametrize("path", sorted(COMMITTED))
def test_committed_checkpoints_load_and_plan(path, scenes) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_ctg import CTGAdapter

    adapter = CTGAdapter(checkpoint=str(REPO / path), seed=0)
    assert adapter.horizon == COMMITTED[path]
    now = scenes.current_index
    out = adapter.sample(scenes, 2, None, torch.Generator().manual_seed(0))
    assert out.futures.shape[-2] == COMMITTED[path]
    agents = scenes.controlled & scenes.valid[:, :, now]
    moved = out.futures[:, :, :, -1, :2] - scenes.xy[:, None, :, now]  # (B, S, A, 2)
    assert torch.isfinite(out.futures).all()
    # a trained model keeps its plan within what a car can drive in H steps (< 40 m/s on average)
    assert moved.norm(dim=-1).masked_select(agents[:, None]).max() < 40.0 * COMMITTED[path] * 0.1


@pytest.mark.parametrize("aligned,base", [
    ("reference_models/aligned/ctg", "reference_models/ctg/checkpoints/ctg_small"),
    ("reference_models/aligned/ctg_4s", "reference_models/ctg/checkpoints/ctg_small_4s"),
])
def test_committed_aligned_checkpoints_are_fine_tuned_from_their_base(aligned: str, base: str) -> None:
    from safetensors.torch import load_file

    tuned = load_file(str(REPO / aligned / "model.safetensors"))
    start = load_file(str(REPO / base / "model.safetensors"))
    assert tuned.keys() == start.keys()
    assert all(tuned[k].shape == start[k].shape for k in tuned)
    changed = [k for k in tuned if tuned[k].is_floating_point() and not torch.equal(tuned[k], start[k])]
    assert len(changed) > len(tuned) // 2, f"only {len(changed)} of {len(tuned)} tensors differ from the base"


@pytest.mark.parametrize("name", ["ctg_4s_road", "ctg_4s_gated"])
def test_the_committed_road_steered_ctgs_are_their_base_plus_a_trained_head(name: str) -> None:
    """Only the steering group trained: every base tensor is bitwise the base's, and the head moved off zero."""
    from safetensors.torch import load_file

    tuned = load_file(str(REPO / "reference_models/aligned" / name / "model.safetensors"))
    start = load_file(str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s/model.safetensors"))
    assert all(torch.equal(tuned[k], start[k]) for k in start)
    head = sorted(set(tuned) - set(start))
    assert head and all(k.startswith("steer.") for k in head)
    last = max((k for k in head if k.endswith(".weight")), key=lambda k: int(k.split(".")[2]))
    assert tuned[last].abs().sum() > 0  # the zero-initialized output layer was trained


@needs_data
def test_guided_log_prob_is_exact(adapter, scenes) -> None:  # type: ignore[no-untyped-def]
    guidance = GuidanceSet([SpeedLimitGuidance(limit=2.0)]).fit(scenes)
    out = adapter.sample(scenes, 3, guidance, torch.Generator().manual_seed(7))
    assert out.trace.tensors["guide_delta"].abs().sum() > 0, "guidance did not perturb any step"
    recomputed = adapter.log_prob(scenes, out.trace.detach())
    assert recomputed.shape == out.log_prob.shape
    torch.testing.assert_close(recomputed.detach(), out.log_prob, atol=1e-3, rtol=1e-4)
    # the last step is never guided
    assert out.trace.tensors["guide_delta"][..., -1, :, :].abs().sum() == 0


@needs_data
def test_guidance_lowers_its_loss(adapter, scenes) -> None:  # type: ignore[no-untyped-def]
    guidance = GuidanceSet([SpeedLimitGuidance(limit=2.0)]).fit(scenes)
    agents = scenes.controlled & scenes.valid[:, :, scenes.current_index]
    plain = adapter.sample(scenes, 8, None, torch.Generator().manual_seed(3))
    guided = adapter.sample(scenes, 8, guidance, torch.Generator().manual_seed(3))
    loss = lambda out: guidance.loss(out.futures, scenes.current_index, scenes)[agents[:, None].expand(-1, 8, -1)]  # noqa: E731
    assert loss(guided).mean() < loss(plain).mean()


@needs_data
@pytest.mark.parametrize("guidance", ["speed_limit", "no_collision", None])
def test_selection_scores_rank_first_the_sample_plan_executes(scenes, guidance) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_ctg import CTGAdapter

    from trafficrlhf_sdk.guidance import NoCollisionGuidance

    planner = CTGAdapter(seed=0, plan_samples=5)
    # losses that differ between samples on these scenes: a low limit, and a 15 m buffer around every agent
    planner.guidance = {"speed_limit": GuidanceSet([SpeedLimitGuidance(limit=2.0)]),
                        "no_collision": GuidanceSet([NoCollisionGuidance(buffer_m=15.0)]), None: None}[guidance]
    planner.reset(scenes)
    drawn = []
    sample = planner.sample
    planner.sample = lambda *args, **kwargs: drawn.append(sample(*args, **kwargs)) or drawn[-1]  # type: ignore[method-assign]
    executed = planner.plan(scenes, planner.horizon).states  # (B, A, H, 4)
    scores, k = planner.selection_scores(scenes, drawn[0], planner.guidance)
    assert scores.shape == drawn[0].futures.shape[:3]
    if guidance is None:
        assert k == 1 and not scores.any()
        return
    controlled = scenes.controlled
    assert k == 5 and (scores[:, :, controlled.any(0)] <= 0).all(), "minus a loss"
    best = scores.argmax(1)  # (B, A)
    assert (best[controlled] > 0).any(), "every agent executes sample 0: the check below would be vacuous"
    chosen = drawn[0].futures.gather(1, best[:, None, :, None, None].expand(-1, 1, -1, planner.horizon, 4))[:, 0]
    torch.testing.assert_close(executed[controlled], chosen[controlled].cpu())
    if guidance == "no_collision":  # scene-level: one score per scene and sample, shared by its controlled agents
        for b in range(scenes.num_scenes):
            shared = scores[b][:, controlled[b]]
            assert torch.equal(shared, shared[:, :1].expand_as(shared))


@needs_data
def test_stationary_agents_are_held(adapter, scenes) -> None:  # type: ignore[no-untyped-def]
    now = scenes.current_index
    states = scenes.states.clone()
    states[:, :, now, 2] = 0.0  # everybody stopped now
    stopped = scenes.replace_unchecked(states=states)
    out = adapter.sample(stopped, 2, None, torch.Generator().manual_seed(0))
    agents = out.trace.agents
    xy_now = states[:, :, now, :2][:, None, :, None].expand(-1, 2, -1, adapter.horizon, -1)
    assert torch.equal(out.futures[..., :2][agents[:, None].expand(-1, 2, -1)],
                       xy_now[agents[:, None].expand(-1, 2, -1)])


@needs_data
@pytest.mark.parametrize("rule", ["rollout_start", "every_replan"])
def test_stationary_rule_decides_when_the_speed_is_read(scenes, rule) -> None:  # type: ignore[no-untyped-def]
    """``rollout_start`` (upstream) holds the agents stopped at ``reset`` and only them; ``every_replan`` holds the
    agents stopped at the replan."""
    from trafficrlhf_ctg import CTGAdapter

    now = scenes.current_index
    agents = scenes.controlled & scenes.valid[:, :, now]
    moving = agents & (scenes.states[:, :, now, 2].abs() > 1.0)
    assert moving.sum() >= 3
    states = scenes.states.clone()
    states[:, :, now, 2] = 0.0
    stopped = scenes.replace_unchecked(states=states)
    model = CTGAdapter(seed=0, stationary_rule=rule)

    def held(start, context) -> torch.Tensor:  # type: ignore[no-untyped-def]
        model.reset(start)
        plan = model.plan(context, 20).states  # (B, A, 20, 4)
        return (plan[..., :2] == context.states[:, :, now, None, :2]).all(-1).all(-1)

    assert bool(held(scenes, stopped)[moving].all()) == (rule == "every_replan")  # moving at the start, stopped now
    assert not held(scenes, stopped)[moving].any() or rule == "every_replan"
    assert bool(held(stopped, scenes)[moving].all()) == (rule == "rollout_start")  # stopped at the start, moving now
    assert not held(stopped, scenes)[moving].any() or rule == "rollout_start"


def test_registry_entry_point() -> None:
    from trafficrlhf_sdk import get_traffic_model
    from trafficrlhf_sdk.plugins import registry

    from trafficrlhf_ctg import CTGAdapter

    assert registry("traffic_models").get("ctg") is CTGAdapter
    if (pytest.importorskip("trafficrlhf_ctg").default_checkpoint() / "model.safetensors").is_file():
        model = get_traffic_model("ctg", seed=1)
        assert isinstance(model, CTGAdapter)


@pytest.mark.slow
@needs_data
def test_cli_evaluate(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from click.testing import CliRunner

    from trafficrlhf_sdk.cli import cli

    result = CliRunner().invoke(cli, ["evaluate", "--model", "ctg", "--scenes", "3", "--guidance", "speed_limit",
                                      "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "results.json").is_file()


@needs_data
def test_finer_map_crop_covers_the_same_ground(scenes) -> None:  # type: ignore[no-untyped-def]
    """``map_resolution`` reaches the features: a 96-cell crop at 0.5 m spans the 48 m of the default crop, so
    both see nearly the same drivable share per agent, while the finer one resolves more edge cells."""
    from ctg_reference.data import agent_features
    from ctg_reference.model import CTGConfig

    coarse = agent_features(scenes, CTGConfig())["map"]
    fine = agent_features(scenes, CTGConfig(map_size=96, map_resolution=0.5))["map"]
    assert coarse.shape[-2:] == (48, 48) and fine.shape[-2:] == (96, 96)
    agents = scenes.controlled & scenes.valid[:, :, scenes.current_index]
    share_coarse = coarse[:, :, 0].mean((-1, -2))[agents]
    share_fine = fine[:, :, 0].mean((-1, -2))[agents]
    assert share_coarse.min() > 0.05  # controlled agents stand on roads
    assert (share_fine - share_coarse).abs().max() < 0.03


def test_model_size_knobs_reach_the_layers_and_old_configs_keep_their_layout() -> None:
    """``cnn_width`` / ``unet_dims`` / ``cond_dim`` / ``map_dim`` size the layers; a config.json written before
    ``cnn_width`` existed loads with the original 8-16-32-64 map CNN (so committed checkpoints still load)."""
    import json

    from ctg_reference.model import CTGConfig, CTGModel

    old = json.loads((REPO / "reference_models/ctg/checkpoints/ctg_small_4s/config.json").read_text())["config"]
    assert "cnn_width" not in old
    convs = [m for m in CTGModel(CTGConfig.from_dict(old)).encoder.cnn if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [8, 16, 32, 64]

    cfg = CTGConfig(horizon=40, unet_dims=(48, 96), cond_dim=256, map_dim=256, cnn_width=24)
    model = CTGModel(CTGConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))))
    assert model.cfg == cfg
    convs = [m for m in model.encoder.cnn if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [24, 48, 96, 192]
    assert model.encoder.map_head[0].out_features == 256
    assert model.denoiser.mid1.conv1.out_channels == 96 and model.denoiser.down1.conv1.out_channels == 48
    features = {"map": torch.zeros(3, 3, 48, 48), "history": torch.zeros(3, 10, 5),
                "history_valid": torch.ones(3, 10, dtype=torch.bool), "extent": torch.ones(3, 2),
                "neighbours": torch.zeros(3, 8, 7), "neighbour_valid": torch.zeros(3, 8, dtype=torch.bool)}
    assert model.encode(features).shape == (3, 256)


# ------------------------------------------------------------ interaction: neighbours' plans
def _plan_adapter(**options):  # type: ignore[no-untyped-def]
    """A fresh (untrained) 4 s CTG that conditions on its neighbours' plans at 1, 2, 3 and 4 s."""
    from ctg_reference.model import CTGConfig
    from trafficrlhf_ctg import CTGAdapter

    cfg = CTGConfig(horizon=40, neighbour_plan_steps=[10, 20, 30, 40])
    return CTGAdapter(config=cfg.to_dict(), seed=0, **options)


@needs_data
def test_neighbour_plans_are_in_the_agent_frame_and_only_for_neighbours_ahead(scenes) -> None:  # type: ignore[no-untyped-def]
    """Each shown plan is the neighbour's scene-frame position rotated into the agent's frame (checked point by
    point with an independent rotation); neighbours behind the agent or without a plan are hidden."""
    import math

    from ctg_reference.data import agent_features, neighbour_plan_features
    from ctg_reference.model import CTGConfig

    cfg = CTGConfig(horizon=40, neighbour_plan_steps=[10, 20, 30, 40])
    features = agent_features(scenes, cfg)
    b, a = scenes.num_scenes, scenes.num_agents
    positions = torch.randn(b, 2, a, 4, 2, generator=torch.Generator().manual_seed(0)) * 30
    known = torch.ones(b, 2, a, 4, dtype=torch.bool)
    known[:, :, 0] = False  # agent slot 0 has no plan
    plan, valid = neighbour_plan_features(scenes, features["neighbours"], features["neighbour_valid"],
                                          features["neighbour_index"], positions, known)
    assert plan.shape == (b, 2, a, cfg.num_neighbours, 4, 2) and valid.shape == plan.shape[:-1]
    now = scenes.current_index
    checked = 0
    for scene, sample, agent, k, step in valid.nonzero().tolist():
        j = int(features["neighbour_index"][scene, agent, k])
        assert j != 0 and features["neighbours"][scene, agent, k, 0] > 0
        x0, y0, _, yaw = scenes.states[scene, agent, now].tolist()
        dx, dy = (positions[scene, sample, j, step] - torch.tensor([x0, y0])).tolist()
        expected = (math.cos(yaw) * dx + math.sin(yaw) * dy, -math.sin(yaw) * dx + math.cos(yaw) * dy)
        assert plan[scene, sample, agent, k, step].tolist() == pytest.approx(expected, abs=1e-3)
        checked += 1
    assert checked > 0
    behind = features["neighbour_valid"] & (features["neighbours"][..., 0] <= 0)
    assert behind.any() and not (valid & behind[:, None, :, :, None]).any()
    assert (plan[~valid] == 0).all()


def test_per_sample_plans_encode_like_one_row_per_sample() -> None:
    """The encoder's sample axis is a batch axis: conditioning on S plans at once equals conditioning row by
    row; with every plan hidden it equals the encoding without plans."""
    from ctg_reference.model import CTGConfig, CTGModel

    torch.manual_seed(0)
    model = CTGModel(CTGConfig(horizon=40, neighbour_plan_steps=[10, 20, 30, 40])).eval()
    n, s, k = 3, 4, 8
    features = {"map": (torch.rand(n, 3, 48, 48) > 0.5).float(), "history": torch.randn(n, 10, 5),
                "history_valid": torch.ones(n, 10, dtype=torch.bool), "extent": torch.ones(n, 2),
                "neighbours": torch.randn(n, k, 7), "neighbour_valid": torch.rand(n, k) > 0.3}
    plan, plan_valid = torch.randn(n, s, k, 4, 2) * 10, torch.rand(n, s, k, 4) > 0.4
    with torch.no_grad():
        joint = model.encode({**features, "neighbour_plan": plan, "neighbour_plan_valid": plan_valid})
        assert joint.shape == (n, s, model.cfg.cond_dim)
        for i in range(s):
            single = model.encode({**features, "neighbour_plan": plan[:, i], "neighbour_plan_valid": plan_valid[:, i]})
            assert torch.allclose(joint[:, i], single, atol=1e-5)
        nobody = torch.zeros_like(plan_valid[:, 0])
        hidden = model.encode({**features, "neighbour_plan": plan[:, 0], "neighbour_plan_valid": nobody})
        assert torch.allclose(hidden, model.encode(features), atol=1e-6)
        other = model.encode({**features, "neighbour_plan": plan[:, 0] + 5, "neighbour_plan_valid": plan_valid[:, 0]})
        assert not torch.allclose(other, joint[:, 0])  # the plans are read


@needs_data
@pytest.mark.parametrize(("mode", "plan_shape"), [("joint", (5, 4, 2)), ("proposal", (4, 2)), ("none", None)])
def test_plan_modes_keep_the_contract_and_exact_log_prob(scenes, mode, plan_shape) -> None:  # type: ignore[no-untyped-def]
    """The neighbours' plans (per denoising step, or one proposal) are part of the context: check_adapter
    passes, the trace carries them, the guided chain's log-probability recomputed from the trace equals the
    sampling-time value, and changing the stored plans changes it (they are really read)."""
    from trafficrlhf_sdk.testing.check_adapter import check_adapter

    adapter = _plan_adapter(plan_mode=mode)
    check_adapter(adapter, scenes)
    guidance = GuidanceSet.parse("no_collision").fit(scenes)
    out = adapter.sample(scenes, 3, guidance, torch.Generator().manual_seed(1))
    assert torch.allclose(adapter.log_prob(scenes, out.trace), out.log_prob, atol=1e-3, rtol=1e-5)
    if plan_shape is None:
        assert "plan_positions" not in out.trace.tensors
        return
    plans = out.trace.tensors["plan_positions"]
    assert plans.shape == (scenes.num_scenes, 3, scenes.num_agents, *plan_shape)
    trace = type(out.trace)({**out.trace.tensors, "plan_positions": plans + 3.0}, out.trace.agents, out.trace.now)
    assert not torch.allclose(adapter.log_prob(scenes, trace), out.log_prob, atol=1e-3)


def test_joint_denoising_conditions_each_step_on_the_previous_clean_prediction() -> None:
    """``cond_fn`` is called before every step after the first with that step's input's clean prediction, and
    the conditioning it returns is the one the step uses (a per-step conditioning recomputes the same
    log-probabilities)."""
    from ctg_reference.model import CTGConfig, CTGModel

    torch.manual_seed(0)
    model = CTGModel(CTGConfig(horizon=20)).eval()
    n, s = 4, 3
    base = torch.randn(n, model.cfg.cond_dim)
    calls, conds = [], [base[:, None].expand(n, s, -1)]

    def cond_fn(step: int, x0: torch.Tensor) -> torch.Tensor:
        calls.append((step, tuple(x0.shape)))
        conds.append(base[:, None] + x0.mean((-1, -2))[..., None])  # depends on the prediction
        return conds[-1]

    with torch.no_grad():
        _, chain, _, log_prob = model.sample(base, s, torch.Generator().manual_seed(0), cond_fn=cond_fn)
        assert calls == [(i, (n, s, 20, 2)) for i in range(1, model.cfg.sample_steps)]
        per_step = torch.stack(conds, 2)  # (N, S, K, D)
        assert torch.allclose(model.chain_log_prob(per_step, chain), log_prob, atol=1e-3)
        assert not torch.allclose(model.chain_log_prob(base, chain), log_prob, atol=1e-3)


@needs_data
def test_training_windows_see_the_same_logged_plans_as_imitation_loss(scenes) -> None:  # type: ignore[no-untyped-def]
    """The training script's batched featurization and the adapter's per-step path (used by imitation_loss)
    give the same neighbour plans for the same window."""
    from ctg_reference.data import agent_features, logged_neighbour_plans, window_mask
    from ctg_reference.model import CTGConfig
    from ctg_reference.train import scene_samples

    cfg = CTGConfig(horizon=40, neighbour_plan_steps=[10, 20, 30, 40])
    first = ("states", "valid", "extent", "agent_type", "controlled")  # the first scene alone
    scene = scenes.replace_unchecked(**{k: getattr(scenes, k)[:1] for k in first})
    samples = scene_samples(scene, cfg, stride=1000)  # one window: now = history_steps
    t = cfg.history_steps
    at_t = scene.replace_unchecked(current_index=t)
    features = agent_features(at_t, cfg)
    plan, valid = logged_neighbour_plans(at_t, cfg, features)
    mask = window_mask(scene, t, cfg.horizon, cfg.history_steps)
    assert samples is not None and samples["neighbour_plan"].shape[0] == int(mask.sum())
    assert torch.equal(samples["neighbour_plan_valid"], valid[mask])
    assert torch.allclose(samples["neighbour_plan"], plan[mask], atol=1e-4)
    assert valid[mask].any()


# ------------------------------------------------------------ interaction: scene-level denoising
def _scene_adapter(**options):  # type: ignore[no-untyped-def]
    """A fresh 4 s CTG that denoises agents jointly, its mixer's zero-initialized output layer randomized so that
    it really reads the neighbours."""
    from ctg_reference.model import CTGConfig
    from trafficrlhf_ctg import CTGAdapter

    adapter = CTGAdapter(config=CTGConfig(horizon=40, scene_denoising=True).to_dict(), seed=0, **options)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in adapter.model.mixer.out.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.5)
    return adapter


def test_co_denoised_rows_point_at_the_same_agent_in_the_same_window() -> None:
    """Each neighbour's row is the row of the same window holding that agent slot; neighbours that are not rows,
    or not valid, get -1 (checked against a plain loop)."""
    from ctg_reference.data import co_denoised_rows

    gen = torch.Generator().manual_seed(0)
    w, a, k = 4, 6, 3
    mask = torch.rand(w, a, generator=gen) > 0.4
    index = torch.randint(0, a, (w, a, k), generator=gen)
    valid = torch.rand(w, a, k, generator=gen) > 0.3
    rows = co_denoised_rows(mask, index, valid)
    slots = mask.nonzero().tolist()  # row r is (window, agent) slots[r]
    assert rows.shape == (len(slots), k)
    for r, (win, agent) in enumerate(slots):
        for j in range(k):
            target = [win, int(index[win, agent, j])]
            expected = slots.index(target) if valid[win, agent, j] and target in slots else -1
            assert int(rows[r, j]) == expected


def test_an_untrained_mixer_changes_nothing_and_a_trained_one_reads_the_neighbours() -> None:
    """With its zero-initialized output the mixer adds nothing (same chain log-probabilities as without it); once
    its output is non-zero, changing a co-denoised neighbour's chain changes the row's log-probabilities, and a
    row without co-denoised neighbours is unaffected."""
    from ctg_reference.model import CTGConfig, CTGModel

    torch.manual_seed(0)
    model = CTGModel(CTGConfig(horizon=20, scene_denoising=True)).eval()
    n, s, k = 3, 2, 8
    neighbour_row = torch.full((n, k), -1, dtype=torch.long)
    neighbour_row[0, 0], neighbour_row[1, 2] = 1, 0  # rows 0 and 1 see each other, row 2 sees nobody
    features = {"neighbours": torch.randn(n, k, 7), "neighbour_valid": torch.ones(n, k, dtype=torch.bool),
                "neighbour_row": neighbour_row}
    scene = model.scene_rows(features)
    cond = torch.randn(n, model.cfg.cond_dim)
    with torch.no_grad():
        _, chain, _, log_prob = model.sample(cond, s, torch.Generator().manual_seed(0), scene=scene)
        assert torch.allclose(model.chain_log_prob(cond, chain), log_prob, atol=1e-4)
        for p in model.mixer.out.parameters():
            p.normal_(0, 0.5)
        _, chain, _, log_prob = model.sample(cond, s, torch.Generator().manual_seed(0), scene=scene)
        assert torch.allclose(model.chain_log_prob(cond, chain, scene=scene), log_prob, atol=1e-3)
        moved = chain.clone()
        moved[1, :, :-1] += 1.0  # row 1's noisy states, which row 0 reads
        changed = model.chain_log_prob(cond, moved, scene=scene)
        assert not torch.allclose(changed[0], log_prob[0], atol=1e-3)
        assert torch.allclose(changed[2], log_prob[2], atol=1e-4)


def test_scene_loss_shares_the_noise_level_within_a_group() -> None:
    """``loss(group=...)`` draws one diffusion step per group: every row of a group is denoised at the same k."""
    from ctg_reference.model import CTGConfig, CTGModel

    torch.manual_seed(0)
    model = CTGModel(CTGConfig(horizon=20, scene_denoising=True))
    seen: list[torch.Tensor] = []
    forward = model.denoiser.forward
    model.denoiser.forward = lambda x, t, cond: (seen.append(t), forward(x, t, cond))[1]  # type: ignore[method-assign]
    n = 12
    group = torch.tensor([0, 0, 0, 1, 1, 2, 3, 3, 3, 3, 4, 5])
    features = {"neighbours": torch.randn(n, 8, 7), "neighbour_valid": torch.ones(n, 8, dtype=torch.bool),
                "neighbour_row": torch.randint(-1, n, (n, 8))}
    loss, _ = model.loss(torch.randn(n, model.cfg.cond_dim), torch.randn(n, 20, 2), torch.rand(n) * 10,
                         generator=torch.Generator().manual_seed(3), scene=model.scene_rows(features), group=group)
    loss.backward()
    (k,) = seen
    for g in group.unique():
        assert k[group == g].unique().numel() == 1
    assert k.unique().numel() > 1
    assert model.mixer.net[0].weight.grad is not None


@needs_data
def test_scene_denoising_adapter_keeps_the_contract_and_exact_log_prob(scenes) -> None:  # type: ignore[no-untyped-def]
    """check_adapter passes (the mixer trains with the decoder), the guided chain's log-probability recomputed from
    the trace equals the sampling-time value, and it depends on the other sampled agents' chains."""
    from trafficrlhf_sdk.testing.check_adapter import check_adapter

    adapter = _scene_adapter()
    facts = check_adapter(adapter, scenes)
    assert set(facts["groups_with_gradient"]) == {"encoder", "decoder"}
    assert any(p is adapter.model.mixer.out.weight for p in adapter.parameter_groups()["decoder"])
    guidance = GuidanceSet.parse("no_collision").fit(scenes)
    out = adapter.sample(scenes, 3, guidance, torch.Generator().manual_seed(1))
    assert torch.allclose(adapter.log_prob(scenes, out.trace), out.log_prob, atol=1e-3, rtol=1e-5)
    agents = out.trace.agents
    scene = int(agents.sum(-1).argmax())
    first, second = agents[scene].nonzero()[:2, 0].tolist()
    chain = out.trace.tensors["chain"].clone()
    chain[scene, :, second, :-1] += 1.0
    moved = adapter.log_prob(scenes, type(out.trace)({**out.trace.tensors, "chain": chain}, agents, out.trace.now))
    assert not torch.allclose(moved[scene, :, first], out.log_prob[scene, :, first], atol=1e-3)
    assert torch.isfinite(adapter.imitation_loss(scenes))


@needs_data
def test_training_windows_list_the_same_co_denoised_neighbours_as_the_adapter(scenes) -> None:  # type: ignore[no-untyped-def]
    """The training script's rows of one window name the same co-denoised neighbours as the adapter's path for
    that step, and a training batch re-indexes them onto the same agents."""
    from ctg_reference.data import agent_features, co_denoised_rows, window_mask
    from ctg_reference.model import CTGConfig
    from ctg_reference.train import scene_batch, scene_samples

    cfg = CTGConfig(horizon=40, scene_denoising=True)
    first = ("states", "valid", "extent", "agent_type", "controlled")
    scene = scenes.replace_unchecked(**{k: getattr(scenes, k)[:1] for k in first})
    samples = scene_samples(scene, cfg, stride=5)
    t = cfg.history_steps
    features = agent_features(scene.replace_unchecked(current_index=t), cfg)
    mask = window_mask(scene, t, cfg.horizon, cfg.history_steps)
    expected = co_denoised_rows(mask, features["neighbour_index"], features["neighbour_valid"])
    assert samples is not None and (expected >= 0).any()
    first_window = samples["window"] == 0
    assert torch.equal(samples["neighbour_row"][first_window], expected)
    samples["map"] = samples["map"].float()
    idx = first_window.nonzero()[:, 0].flip(0)  # a batch in another order
    batch = scene_batch(samples, idx)
    for r, original in enumerate(idx.tolist()):
        for j, row in enumerate(batch["neighbour_row"][r].tolist()):
            target = int(samples["neighbour_row"][original, j])
            assert (row == -1) == (target == -1) and (row == -1 or int(idx[row]) == target)
    assert batch["group"].unique().tolist() == [0]


@needs_data
@pytest.mark.parametrize("options", [("steer",), ("steer_road",), ("steer_road", "steer_neighbours")])
def test_a_fresh_steering_head_samples_as_the_base_and_trains_alone(scenes, tmp_path, options) -> None:  # type: ignore[no-untyped-def]
    """``steer=True`` (or ``steer_road=True``, a head that also reads the road, with ``steer_neighbours`` the
    traffic too) adds a zero head: same guided
    futures and log-probabilities as the base under one generator; it is the ``steer`` group and gets the only
    gradient of a log-probability once its output layer is non-zero; the head then changes the sampled futures
    and the guided log-probability stays exact; it survives save_pretrained/from_pretrained without the option."""
    from trafficrlhf_ctg import CTGAdapter

    path = str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s")
    flags = dict.fromkeys(options, True)
    base, steered = CTGAdapter(checkpoint=path, seed=0), CTGAdapter(checkpoint=path, seed=0, **flags)
    assert steered.cfg.steer_road == ("steer_road" in options)
    assert steered.cfg.steer_neighbours == ("steer_neighbours" in options)
    torch.manual_seed(123)  # whatever the global generator holds, a fresh head is the same draw
    again = CTGAdapter(checkpoint=path, seed=1, **flags)
    for name, tensor in steered.model.steer.state_dict().items():
        assert torch.equal(tensor, again.model.steer.state_dict()[name]), name
    assert "steer" not in base.parameter_groups() and set(steered.parameter_groups()) == {"encoder", "decoder", "steer"}
    guidance = GuidanceSet.parse("no_collision").fit(scenes)
    a = base.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    b = steered.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    torch.testing.assert_close(a.futures, b.futures)
    torch.testing.assert_close(a.log_prob, b.log_prob)

    with torch.no_grad():
        steered.model.steer.net[-1].weight.normal_(0, 0.05)
    out = steered.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    agents = out.trace.agents
    moved = (out.futures - a.futures)[:, :, :, :, :2].norm(dim=-1).amax(-1)  # (B, S, A)
    assert moved.masked_select(agents[:, None]).min() > 0
    recomputed = steered.log_prob(scenes, out.trace.detach())
    torch.testing.assert_close(recomputed.detach(), out.log_prob, atol=1e-3, rtol=1e-4)
    for group in steered.parameter_groups().values():
        for p in group:
            p.grad = None
    recomputed.sum().backward()
    head = steered.parameter_groups()["steer"]
    assert all(p.grad is not None for p in head[-2:]) and head[-2].grad.abs().sum() > 0

    steered.save_pretrained(str(tmp_path))
    loaded = CTGAdapter.from_pretrained(str(tmp_path), seed=0)
    assert loaded.cfg.steer and loaded.cfg.steer_road == ("steer_road" in options)
    assert loaded.cfg.steer_neighbours == ("steer_neighbours" in options)
    again = loaded.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    torch.testing.assert_close(again.futures, out.futures)


def test_neighbour_proximity_matches_a_per_point_loop_and_ignores_missing_neighbours() -> None:
    """Against a plain Python loop over rows, samples, steps, probes and neighbours: each neighbour driven on at
    its current velocity, clearance = centre distance less both mean half-extents, proximity exp(-clearance /
    scale) (1 when the footprints overlap), the largest over valid neighbours; 0 with none."""
    from ctg_reference.model import neighbour_proximity

    gen = torch.Generator().manual_seed(0)
    n, k, s, h, dt, offset, scale = 3, 4, 2, 5, 0.1, 1.0, 2.0
    yaw_n = torch.rand(n, k, generator=gen) * 6.28
    neighbours = torch.cat([torch.randn(n, k, 2, generator=gen) * 6, torch.cos(yaw_n)[..., None],
                            torch.sin(yaw_n)[..., None], torch.rand(n, k, 1, generator=gen) * 10,
                            3 + torch.rand(n, k, 1, generator=gen) * 2, 1.5 + torch.rand(n, k, 1, generator=gen)], -1)
    valid = torch.rand(n, k, generator=gen) > 0.3
    valid[2] = False  # a row without neighbours
    extent = torch.tensor([[4.5, 1.9], [4.0, 1.8], [5.0, 2.0]])
    states = torch.randn(n, s, h, 4, generator=gen) * 5
    got = neighbour_proximity(neighbours, valid, extent, states, dt, offset, scale)
    assert got.shape == (n, s, h, 3)
    expected = torch.zeros(n, s, h, 3)
    for i in range(n):
        for j in range(s):
            for t in range(h):
                x, y, _, yaw = states[i, j, t].tolist()
                probes = [(x, y), (x - math.sin(yaw) * offset, y + math.cos(yaw) * offset),
                          (x + math.sin(yaw) * offset, y - math.cos(yaw) * offset)]
                for p, (px, py) in enumerate(probes):
                    for m in range(k):
                        if not valid[i, m]:
                            continue
                        nx, ny, c, sn, v, length, width = neighbours[i, m].tolist()
                        cx, cy = nx + v * c * (t + 1) * dt, ny + v * sn * (t + 1) * dt
                        reach = (extent[i].sum().item() + length + width) / 4
                        clearance = max(math.hypot(px - cx, py - cy) - reach, 0.0)
                        expected[i, j, t, p] = max(expected[i, j, t, p].item(), math.exp(-clearance / scale))
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)
    assert torch.all(got[2] == 0)
    assert neighbour_proximity(neighbours[:, :0], valid[:, :0], extent, states, dt, offset, scale).abs().sum() == 0


def test_the_steering_gate_leaves_plans_on_a_clear_road_alone_and_scales_others_by_their_hazard() -> None:
    """``steer_gate``: the head's shift is multiplied by the plan's largest hazard (off-road share inside the
    crop, neighbour proximity): all road and nobody near gives no shift at all; no road gives the ungated shift;
    a neighbour on the plan gives it too; past the crop's edge the missing map is no hazard."""
    from ctg_reference.model import CTGConfig, CTGModel

    torch.manual_seed(0)
    model = CTGModel(CTGConfig(horizon=8, steer=True, steer_road=True, steer_neighbours=True, steer_gate=True))
    with torch.no_grad():
        model.steer.net[-1].weight.normal_(0, 0.1)
    n, r, g = 2, 3, model.cfg.map_size
    cond = torch.randn(n * r, model.cfg.cond_dim)
    x0 = torch.randn(n * r, 8, 2) * 0.3
    v0 = torch.full((n,), 2.0)
    neighbours = torch.zeros(n, 1, 7)
    neighbours[..., 2], neighbours[..., 5], neighbours[..., 6] = 1.0, 4.5, 1.9
    far = torch.zeros(n, 1, dtype=torch.bool)
    extent = torch.tensor([[4.5, 1.9]] * n)

    def shift(drivable: torch.Tensor, valid: torch.Tensor, gate: bool) -> torch.Tensor:
        model.cfg.steer_gate = gate
        return model._steer_shift(cond, x0, 2, (drivable, v0, neighbours, valid, extent), n)

    road, no_road = torch.ones(n, 1, g, g), torch.zeros(n, 1, g, g)
    assert torch.all(shift(road, far, gate=True) == 0)
    assert shift(road, far, gate=False).abs().amin() > 0
    torch.testing.assert_close(shift(no_road, far, gate=True), shift(no_road, far, gate=False))
    near = torch.ones(n, 1, dtype=torch.bool)  # a neighbour standing where every plan starts
    torch.testing.assert_close(shift(road, near, gate=True), shift(road, near, gate=False))
    v0.fill_(80.0)  # plans that leave the 48 m crop within 0.5 s: the unmapped rest is not off-road
    assert torch.all(shift(road, far, gate=True) == 0)


def test_a_lateral_only_head_shifts_the_yaw_rate_and_leaves_acceleration_to_the_base() -> None:
    """``steer_lateral_only``: the acceleration channel of the shift is exactly 0, the yaw-rate channel is the
    full head's."""
    from ctg_reference.model import CTGConfig, CTGModel

    torch.manual_seed(0)
    model = CTGModel(CTGConfig(horizon=8, steer=True, steer_road=True))
    with torch.no_grad():
        model.steer.net[-1].weight.normal_(0, 0.1)
    n, r, g = 2, 3, model.cfg.map_size
    cond, x0 = torch.randn(n * r, model.cfg.cond_dim), torch.randn(n * r, 8, 2) * 0.3
    steer_map = (torch.zeros(n, 1, g, g), torch.full((n,), 2.0))
    full = model._steer_shift(cond, x0, 2, steer_map, n)
    model.cfg.steer_lateral_only = True
    lateral = model._steer_shift(cond, x0, 2, steer_map, n)
    assert full[..., 0].abs().amin() > 0 and torch.all(lateral[..., 0] == 0)
    torch.testing.assert_close(lateral[..., 1], full[..., 1], atol=0, rtol=0)


def test_the_road_profile_reads_the_crop_cells_the_plan_passes_and_their_side_neighbours() -> None:
    """At agent-frame points on crop-cell centres (``map_crops``' convention: rows ahead, columns to the left,
    a quarter of the rows behind) the bilinear profile equals those cells' values; the offsets one cell across a
    plan heading along +x read the cells to its left and right, and a plan heading along +y swaps the axes."""
    from ctg_reference.model import MAP_BEHIND_FRACTION, road_profile

    g, res = 16, 0.5
    crop = (torch.rand(2, 1, g, g, generator=torch.Generator().manual_seed(0)) > 0.5).float()
    u = torch.tensor([[5, 6, 7, 9], [12, 3, 4, 8]])  # rows (ahead)
    v = torch.tensor([[3, 4, 10, 12], [1, 7, 8, 14]])  # columns (left)
    x = (u - MAP_BEHIND_FRACTION * g + 0.5) * res
    y = (v - g / 2 + 0.5) * res
    heading_x = torch.stack([x, y, torch.zeros_like(x), torch.zeros_like(x)], -1)[:, None]  # (N, S=1, H=4, 4)
    got = road_profile(crop, heading_x, res, offset=res)[:, 0]  # (N, H, 3)
    rows = torch.arange(2)[:, None]
    torch.testing.assert_close(got[..., 0], crop[rows, 0, u, v])
    torch.testing.assert_close(got[..., 1], crop[rows, 0, u, v + 1])
    torch.testing.assert_close(got[..., 2], crop[rows, 0, u, v - 1])
    heading_y = heading_x.clone()
    heading_y[..., 3] = math.pi / 2  # left of a plan heading along +y is -x: the row behind
    got = road_profile(crop, heading_y, res, offset=res)[:, 0]
    torch.testing.assert_close(got[..., 1], crop[rows, 0, u - 1, v], atol=1e-5, rtol=0)
    torch.testing.assert_close(got[..., 2], crop[rows, 0, u + 1, v], atol=1e-5, rtol=0)
    far = heading_x.clone()
    far[..., 0] = 100.0  # beyond the crop
    assert torch.all(road_profile(crop, far, res, offset=res) == 0)


def test_the_gate_options_apply_to_a_saved_head_and_are_refused_where_they_cannot_act() -> None:
    from trafficrlhf_ctg import CTGAdapter

    from trafficrlhf_sdk.errors import TrafficRLHFError

    road = str(REPO / "reference_models/aligned/ctg_4s_road")
    gated = CTGAdapter(checkpoint=road, steer_gate=True, steer_gate_offset=2.0)
    assert gated.cfg.steer_gate and gated.model.cfg.steer_gate and gated.model.cfg.steer_gate_offset == 2.0
    assert not CTGAdapter(checkpoint=road).cfg.steer_gate
    committed = str(REPO / "reference_models/aligned/ctg_4s_gated")
    assert CTGAdapter(checkpoint=committed).cfg.steer_gate
    assert not CTGAdapter(checkpoint=committed, steer_gate=False).cfg.steer_gate
    with pytest.raises(TrafficRLHFError, match="needs a steering head"):
        CTGAdapter(checkpoint=str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s"), steer_gate=True)
    with pytest.raises(TrafficRLHFError, match="only acts with a gate"):
        CTGAdapter(checkpoint=road, steer_gate_offset=2.0)
    lateral = CTGAdapter(checkpoint=committed, steer_lateral_only=True)
    assert lateral.model.cfg.steer_lateral_only and lateral.cfg.steer_gate
    assert not CTGAdapter(checkpoint=committed).cfg.steer_lateral_only
    with pytest.raises(TrafficRLHFError, match="steer_lateral_only=true needs a steering head"):
        CTGAdapter(checkpoint=str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s"), steer_lateral_only=True)


def test_widening_a_saved_road_head_to_read_the_traffic_keeps_its_output_until_fine_tuned(tmp_path: Path) -> None:
    """``steer_neighbours=true`` on a saved road head: the new neighbour inputs get zero weights, so with the gate
    reading the road alone (``steer_gate_traffic=false``) the shift equals the saved head's exactly; with the
    traffic gate a neighbour on the plan opens the gate where the road left it shut."""
    from trafficrlhf_ctg import CTGAdapter

    from trafficrlhf_sdk.errors import TrafficRLHFError

    committed = str(REPO / "reference_models/aligned/ctg_4s_gated")
    saved = CTGAdapter(checkpoint=committed).model
    widened = CTGAdapter(checkpoint=committed, steer_neighbours=True, steer_gate_traffic=False).model
    traffic = CTGAdapter(checkpoint=committed, steer_neighbours=True).model
    assert widened.cfg.steer_neighbours and not widened.cfg.steer_gate_traffic and traffic.cfg.steer_gate_traffic
    old_state, new_state = saved.state_dict(), widened.state_dict()
    assert all(torch.equal(old_state[key], new_state[key]) for key in old_state if key != "steer.net.0.weight")
    torch.manual_seed(0)
    n, r, h, g = 3, 4, saved.cfg.horizon, saved.cfg.map_size
    cond = torch.randn(n * r, saved.cfg.cond_dim)
    x0 = torch.randn(n * r, h, 2) * 0.5
    drivable = (torch.rand(n, 1, g, g) > 0.3).float()
    v0 = torch.tensor([3.0, 6.0, 9.0])
    neighbours = torch.zeros(n, 2, 7)
    neighbours[..., 0] = torch.tensor([6.0, 15.0])
    neighbours[..., 2], neighbours[..., 5], neighbours[..., 6] = 1.0, 4.5, 1.9
    valid, extent = torch.ones(n, 2, dtype=torch.bool), torch.tensor([[4.5, 1.9]] * n)
    full_map = (drivable, v0, neighbours, valid, extent)
    with torch.no_grad():
        expected = saved._steer_shift(cond, x0, 2, (drivable, v0), n)
        torch.testing.assert_close(widened._steer_shift(cond, x0, 2, full_map, n), expected, atol=1e-6, rtol=1e-5)
        clear = torch.ones_like(drivable)
        assert torch.all(widened._steer_shift(cond, x0, 2, (clear, *full_map[1:]), n) == 0)
        assert traffic._steer_shift(cond, x0, 2, (clear, *full_map[1:]), n).abs().amax() > 0
    with pytest.raises(TrafficRLHFError, match="steer_gate_traffic"):
        CTGAdapter(checkpoint=committed, steer_gate_traffic=False)
    blind = tmp_path / "blind_head"
    CTGAdapter(checkpoint=str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s"), steer=True).save_pretrained(
        str(blind))
    with pytest.raises(TrafficRLHFError, match="widens a road-reading head only"):
        CTGAdapter(checkpoint=str(blind), steer_neighbours=True)


def test_lead_gaps_match_a_per_step_loop_and_a_hand_computed_follower() -> None:
    """:func:`lead_gaps` against a plain Python loop (neighbours at constant velocity; in the path = ahead along the
    planned heading and within half of both widths plus the margin to the side; gap bumper to bumper, clipped;
    closing speed against the lead's speed along the heading; hazard against the desired gap), and one case by
    hand: a car 20 m ahead at 5 m/s, the plan at a steady 10 m/s straight on."""
    from ctg_reference.steering import LEAD_GAP_CLIP, lead_gaps

    gen = torch.Generator().manual_seed(1)
    n, k, s, h, dt, margin, s0, headway = 3, 5, 2, 6, 0.1, 0.5, 2.0, 1.5
    yaw_n = torch.rand(n, k, generator=gen) * 0.6 - 0.3
    neighbours = torch.cat([torch.rand(n, k, 1, generator=gen) * 40 - 5, torch.randn(n, k, 1, generator=gen) * 2,
                            torch.cos(yaw_n)[..., None], torch.sin(yaw_n)[..., None],
                            torch.rand(n, k, 1, generator=gen) * 12, 3 + torch.rand(n, k, 1, generator=gen) * 2,
                            1.5 + torch.rand(n, k, 1, generator=gen)], -1)
    valid = torch.rand(n, k, generator=gen) > 0.2
    valid[2] = False
    extent = torch.tensor([[4.5, 1.9], [4.0, 1.8], [5.0, 2.0]])
    states = torch.cat([torch.rand(n, s, h, 1, generator=gen) * 10, torch.randn(n, s, h, 1, generator=gen),
                        torch.rand(n, s, h, 1, generator=gen) * 12, torch.randn(n, s, h, 1, generator=gen) * 0.2], -1)
    got = lead_gaps(neighbours, valid, extent, states, dt, margin, s0, headway)
    assert got.shape == (n, s, h, 3)
    for i in range(n):
        for j in range(s):
            for t in range(h):
                x, y, v, yaw = states[i, j, t].tolist()
                best, lead_speed = LEAD_GAP_CLIP, v
                for m in range(k):
                    nx, ny, c, sn, speed, length, width = neighbours[i, m].tolist()
                    cx, cy = nx + speed * c * (t + 1) * dt, ny + speed * sn * (t + 1) * dt
                    along = (cx - x) * math.cos(yaw) + (cy - y) * math.sin(yaw)
                    across = abs(-(cx - x) * math.sin(yaw) + (cy - y) * math.cos(yaw))
                    if not valid[i, m] or along <= 0 or across > (extent[i, 1].item() + width) / 2 + margin:
                        continue
                    gap = min(max(along - (extent[i, 0].item() + length) / 2, 0.0), LEAD_GAP_CLIP)
                    if gap < best:
                        best = gap
                        lead_speed = speed * (c * math.cos(yaw) + sn * math.sin(yaw))
                expected = [best, v - lead_speed, min(max(1 - best / (s0 + headway * v), 0.0), 1.0)]
                torch.testing.assert_close(got[i, j, t], torch.tensor(expected), atol=1e-4, rtol=1e-4)
    assert torch.all(got[2, ..., 0] == LEAD_GAP_CLIP) and torch.all(got[2, ..., 2] == 0)

    ahead = torch.tensor([[[20.0, 0.0, 1.0, 0.0, 5.0, 4.5, 1.9], [20.0, 3.5, 1.0, 0.0, 5.0, 4.5, 1.9],
                           [-8.0, 0.0, 1.0, 0.0, 5.0, 4.5, 1.9]]])  # in the lane, one lane over, behind
    t = torch.arange(1, 4) * dt
    plan = torch.stack([10 * t, torch.zeros(3), torch.full((3,), 10.0), torch.zeros(3)], -1)[None, None]
    one = lead_gaps(ahead, torch.ones(1, 3, dtype=torch.bool), torch.tensor([[4.5, 1.9]]), plan, dt, margin, s0,
                    headway)[0, 0]
    gap = 20 + 5 * t - 10 * t - 4.5
    torch.testing.assert_close(one, torch.stack([gap, torch.full((3,), 5.0), 1 - gap / 17.0], -1))


@needs_data
def test_a_fresh_follow_head_samples_as_its_checkpoint_acts_only_behind_a_lead_and_saves(
        scenes, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``follow=True`` on the committed gated model adds a zero gap-keeping head next to its steering head: same
    guided futures and log-probabilities under one generator, every saved tensor kept; it is the ``follow`` group.
    With a non-zero output layer its shift is exactly 0 for rows with nobody ahead (the gate), non-zero behind a
    close lead and on the acceleration channel only; the guided log-probability stays exact, a log-probability's
    gradient reaches the head, and the head survives save_pretrained/from_pretrained without the option."""
    from ctg_reference.model import CTGConfig, CTGModel
    from trafficrlhf_ctg import CTGAdapter

    path = str(REPO / "reference_models/aligned/ctg_4s_gated")
    base, follow = CTGAdapter(checkpoint=path, seed=0), CTGAdapter(checkpoint=path, seed=0, follow=True)
    assert follow.cfg.follow and follow.cfg.steer_gate and "follow" not in base.parameter_groups()
    assert set(follow.parameter_groups()) == {"encoder", "decoder", "steer", "follow"}
    for name, tensor in base.model.state_dict().items():
        assert torch.equal(tensor, follow.model.state_dict()[name]), name
    guidance = GuidanceSet.parse("no_collision").fit(scenes)
    a = base.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    b = follow.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    torch.testing.assert_close(a.futures, b.futures)
    torch.testing.assert_close(a.log_prob, b.log_prob)

    model = CTGModel(CTGConfig(horizon=8, follow=True))
    with torch.no_grad():
        model.follow.net[-1].weight.normal_(0, 0.5)
        model.follow.net[-1].bias.fill_(0.5)
    x0 = torch.zeros(2, 8, 2)  # two rows, one sample each: about 0.1 m/s^2 (the normalization's mean)
    lead = torch.tensor([[[8.0, 0.0, 1.0, 0.0, 2.0, 4.5, 1.9]], [[8.0, 0.0, 1.0, 0.0, 2.0, 4.5, 1.9]]])
    steer_map = (torch.ones(2, 1, 48, 48), torch.full((2,), 8.0), lead, torch.tensor([[True], [False]]),
                 torch.tensor([[4.5, 1.9], [4.5, 1.9]]))
    shift = model._follow_shift(x0, 3, steer_map, 2)
    assert shift[0, :, 0].abs().min() > 0 and torch.all(shift[1] == 0) and torch.all(shift[..., 1] == 0)

    with torch.no_grad():
        follow.model.follow.net[-1].weight.normal_(0, 0.05)
        follow.model.follow.net[-1].bias.fill_(-0.5)  # brake wherever the gate opens
    out = follow.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    assert not torch.equal(out.futures, a.futures)
    recomputed = follow.log_prob(scenes, out.trace.detach())
    torch.testing.assert_close(recomputed.detach(), out.log_prob, atol=1e-3, rtol=1e-4)
    recomputed.sum().backward()
    head = follow.parameter_groups()["follow"]
    assert head[-2].grad is not None and head[-2].grad.abs().sum() > 0
    follow.save_pretrained(str(tmp_path))
    loaded = CTGAdapter.from_pretrained(str(tmp_path), seed=0)
    assert loaded.cfg.follow and loaded.cfg.steer_gate
    again = loaded.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    torch.testing.assert_close(again.futures, out.futures)
