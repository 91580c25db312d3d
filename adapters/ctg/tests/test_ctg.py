"""Tests of the ``ctg`` adapter: contract (check_adapter), guidance, exact log-probabilities, registry, CLI.

Data-dependent tests are skipped when ``trafficrlhf_sdk.scenario.default_data_root()`` lacks nuscenes_pred.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
import torch

from trafficrlhf_sdk.simulation.guidance import GuidanceSet, SpeedLimitGuidance
from trafficrlhf_sdk.scenario import default_data_root

ROOT = os.path.join(default_data_root(), "nuscenes_pred")
HAS_DATA = os.path.isdir(os.path.join(ROOT, "label"))
needs_data = pytest.mark.skipif(not HAS_DATA, reason=f"nuscenes_pred data not found under {ROOT!r}")


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
    "reference_models/baselines/ctg": 40,
    "reference_models/aligned/ctg": 40,
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


def test_the_committed_aligned_ctg_is_its_base_plus_a_steering_head_and_a_braking_prior() -> None:
    """``reference_models/baselines/ctg``: every tensor of the 4 s base ``ctg_small_4s`` bitwise, a trained steering
    head (its zero-initialized output layer moved), and a gap-keeping head that was never trained: zero output
    weights and a bias of -3 (the braking prior), with its recorded gate settings and three steering stages."""
    import json

    from safetensors.torch import load_file

    folder = REPO / "reference_models/baselines/ctg"
    tuned = load_file(str(folder / "model.safetensors"))
    start = load_file(str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s/model.safetensors"))
    assert all(torch.equal(tuned[k], start[k]) for k in start)
    head = sorted(set(tuned) - set(start))
    assert {k.split(".")[0] for k in head} == {"steer", "follow"}
    steer = max(int(k.split(".")[2]) for k in head if k.startswith("steer."))
    assert tuned[f"steer.net.{steer}.weight"].abs().sum() > 0
    last = max(int(k.split(".")[2]) for k in head if k.startswith("follow."))
    assert torch.all(tuned[f"follow.net.{last}.weight"] == 0)
    assert torch.all(tuned[f"follow.net.{last}.bias"] == -3.0)
    cfg = json.loads((folder / "config.json").read_text())["config"]
    gate = (cfg["follow"], cfg["follow_ttc"], cfg["follow_heading_cos"], cfg["follow_gate_steps"])
    assert gate == (True, 3.0, 0.7, 5)
    for stage in (1, 2, 3):
        history = json.loads((folder / f"align_history_stage{stage}.json").read_text())
        assert history["config"]["groups"] == ["steer"] and len(history["history"]) == 70


def test_random_draws_are_made_on_the_generators_device() -> None:
    """A seeded CPU generator cannot draw on a GPU: draws are made where the generator lives and moved, so a GPU
    run gets the CPU run's noise."""
    from ctg_reference.model import draw_device

    assert draw_device(torch.Generator(), "cuda") == torch.device("cpu")
    assert draw_device(None, "cuda") == "cuda"


@needs_data
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_sampling_on_cuda_follows_the_cpu_run(scenes) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_ctg import CTGAdapter

    path = str(REPO / "reference_models/baselines/ctg")
    cpu = CTGAdapter(checkpoint=path, seed=0).sample(scenes, 2, None, torch.Generator().manual_seed(0))
    gpu = CTGAdapter(checkpoint=path, seed=0, device="cuda").sample(scenes.to("cuda"), 2, None,
                                                                    torch.Generator().manual_seed(0))
    torch.testing.assert_close(gpu.futures.cpu(), cpu.futures, atol=1e-2, rtol=1e-3)


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
    scene = scenes[:1]  # the first scene alone
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
    scene = scenes[:1]
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
def test_planning_skips_the_held_agents_denoising_without_changing_the_rollout(scenes, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_ctg import CTGAdapter
    from trafficrlhf_sdk.models.stationary import StationaryHold
    from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

    now = scenes.current_index
    driven = scenes.controlled & scenes.valid[:, :, now]
    first = driven & (driven.cumsum(-1) == 1)  # the first driven agent of each scene stands still at the start
    states = scenes.states.clone()
    states[:, :, now, 2] = torch.where(first, 0.0, states[:, :, now, 2])
    scenes = scenes.replace_unchecked(states=states)
    config = SimulationConfig(duration_s=1.0)
    held = CTGAdapter(seed=3, guidance="no_collision")
    held.reset(scenes)
    assert held._hold.mask(scenes)[driven].any() and not held._hold.mask(scenes)[driven].all()
    calls: list[int] = []
    original = held.model.denoiser.forward
    monkeypatch.setattr(held.model.denoiser, "forward", lambda x, *a: calls.append(x.shape[0]) or original(x, *a))
    skipped = simulate(held, scenes, config)
    monkeypatch.setattr(StationaryHold, "in_plan", property(lambda self: False))  # denoise every row
    rows: list[int] = []
    monkeypatch.setattr(held.model.denoiser, "forward", lambda x, *a: rows.append(x.shape[0]) or original(x, *a))
    full = simulate(held, scenes, config)
    assert torch.equal(skipped.simulated.states, full.simulated.states)
    assert sum(calls) < sum(rows)


@needs_data
def test_seeded_scene_groups_in_one_batch_roll_out_as_each_group_alone(scenes) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_ctg import CTGAdapter
    from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
    from trafficrlhf_sdk.simulation.policies import seed_policy
    from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

    config = SimulationConfig(duration_s=1.0)
    policy = CTGAdapter(seed=0, guidance="no_collision")
    groups = [scenes[0], scenes[1], scenes[2]]
    sizes, seeds = [2, 1, 2], [11, 5, 7]
    batch = ScenarioTensor.concat([g for g, n in zip(groups, sizes) for g in [g] * n])
    policy.seed_scenes(seeds, sizes)
    together = simulate(policy, batch, config).simulated
    policy.seed_scenes(None)
    first = 0
    for group, n, seed in zip(groups, sizes, seeds):
        seed_policy(policy, seed)
        alone = simulate(policy, ScenarioTensor.concat([group] * n), config).simulated
        a = group.num_agents
        assert torch.equal(together.states[first : first + n, :a], alone.states)
        assert torch.equal(together.valid[first : first + n, :a], alone.valid)
        first += n
    with pytest.raises(ValueError, match="covers 5 scenes"):
        policy.seed_scenes(seeds, sizes)
        simulate(policy, scenes, config)


@needs_data
def test_campaign_contexts_made_together_equal_those_made_one_by_one(scenes) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_ctg import CTGAdapter
    from trafficrlhf_sdk.feedback.campaign import generate_candidates, generate_candidates_batch
    from trafficrlhf_sdk.simulation.policies import seed_policy

    def own_agents(scene):  # type: ignore[no-untyped-def]
        """The scene without the batch's padding slots, so the contexts differ in size as loaded one by one."""
        a = int(scene.valid[0].any(-1).nonzero().max()) + 1
        return scene.replace_unchecked(states=scene.states[:, :a], valid=scene.valid[:, :a],
                                       extent=scene.extent[:, :a], agent_type=scene.agent_type[:, :a],
                                       controlled=scene.controlled[:, :a],
                                       agent_ids=tuple(ids[:a] for ids in scene.agent_ids))

    policy = CTGAdapter(seed=0, guidance="no_collision")
    contexts = [own_agents(scenes[i]) for i in range(scenes.num_scenes)]
    assert len({c.num_agents for c in contexts}) > 1
    seeds = [3, 1, 4]
    together = generate_candidates_batch(policy, contexts, seeds, 3, 1.0, 10.0)
    for scene, seed, made in zip(contexts, seeds, together):
        seed_policy(policy, seed)
        alone = generate_candidates(policy, scene, 3, 1.0, 10.0)
        for x, y in zip(made[1:], alone[1:]):
            assert torch.equal(x, y)
        assert torch.equal(made[0].states, alone[0].states) and torch.equal(made[0].controlled, alone[0].controlled)
        assert torch.equal(made[0].map.scene_raster(0), alone[0].map.scene_raster(0))
