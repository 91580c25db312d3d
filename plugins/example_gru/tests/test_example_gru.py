"""``example_gru``: the adapter passes the SDK's conformance check, is found through its entry point, runs in
``trafficrlhf evaluate``, and broken variants are caught by ``check_adapter`` with a message saying what to fix.

Tests on a small synthetic scene run everywhere; those on real nuScenes val scenes read
``<default_data_root()>/nuscenes_pred`` and are skipped when it is absent (nuScenes: CC BY-NC-SA 4.0).
"""

from __future__ import annotations

import importlib.util
import json
import math
import os

import pytest
import torch
from click.testing import CliRunner
from safetensors.torch import load_file

from trafficrlhf_sdk import get_scenario_source, get_traffic_model, list_plugins, registry
from trafficrlhf_sdk.cli import get_cli
from trafficrlhf_sdk.models import PolicyTrace, SampleOutput
from trafficrlhf_sdk.scenario import AgentType, MapRaster, ScenarioTensor, default_data_root
from trafficrlhf_sdk.testing.check_adapter import AdapterCheckError, check_adapter
from trafficrlhf_example_gru import BUNDLED_CHECKPOINT, ExampleGRUAdapter, GRUConfig

HAS_DATA = os.path.isdir(os.path.join(default_data_root(), "nuscenes_pred", "label")) and (
    importlib.util.find_spec("trafficrlhf_nuscenes_pred") is not None
)
needs_data = pytest.mark.skipif(
    not HAS_DATA, reason=f"nuscenes_pred data (or its plugin) not found under {default_data_root()!r}"
)


# ------------------------------------------------------------------------------------------- fixtures
def synthetic_scene(steps: int = 60, now: int = 30) -> ScenarioTensor:
    """One straight two-lane road along +x (all drivable in y in [-6, 6]); three cars and one padding slot."""
    t = torch.arange(steps, dtype=torch.float32) * 0.1
    rows = []
    for x0, y, v in ((0.0, -2.0, 8.0), (20.0, -2.0, 6.0), (40.0, 2.0, -0.0)):
        rows.append(torch.stack([x0 + v * t, torch.full_like(t, y), torch.full_like(t, v), torch.zeros_like(t)], -1))
    rows.append(torch.zeros(steps, 4))
    states = torch.stack(rows)[None]
    valid = torch.ones(1, 4, steps, dtype=torch.bool)
    valid[:, 3] = False
    raster = torch.zeros(1, 3, 300, 60, dtype=torch.uint8)  # 2 px/m: x in [0, 150), y in [-15, 15)
    raster[:, 0, :, 18:42] = 1  # drivable: |y| < 6 m
    raster[:, 2, :, 29:31] = 1  # lane divider at y = 0
    world_to_pixel = torch.tensor([[[2.0, 0.0, 0.0], [0.0, 2.0, 30.0], [0.0, 0.0, 1.0]]])
    return ScenarioTensor(
        states=states * valid[..., None],
        valid=valid,
        extent=torch.tensor([[[4.5, 1.9], [4.8, 2.0], [4.2, 1.8], [0.0, 0.0]]]),
        agent_type=torch.tensor([[AgentType.VEHICLE] * 3 + [AgentType.UNSET]]),
        controlled=torch.tensor([[True, True, True, False]]),
        current_index=now,
        map=MapRaster(raster=raster, world_to_pixel=world_to_pixel),
        scene_ids=("synthetic",),
    )


@pytest.fixture(scope="module")
def adapter() -> ExampleGRUAdapter:
    """The adapter with its bundled checkpoint."""
    return ExampleGRUAdapter()


@pytest.fixture(scope="module")
def val_scenes() -> ScenarioTensor:
    """The first 3 long-enough nuscenes_pred val scenes."""
    if not HAS_DATA:
        pytest.skip("nuscenes_pred data not available")
    return get_scenario_source("nuscenes_pred").load_batch("val", 3)


# ------------------------------------------------------------------------------------------- the contract
@needs_data
def test_check_adapter_passes_on_real_scenes(adapter: ExampleGRUAdapter, val_scenes: ScenarioTensor) -> None:
    facts = check_adapter(adapter, val_scenes)
    assert set(facts["parameters"]) == {"encoder", "decoder"}
    assert facts["frozen_parameters"] == 0
    assert sorted(facts["groups_with_gradient"]) == ["decoder", "encoder"]
    assert facts["log_prob_shape"] == (3, 3, val_scenes.num_agents)


def test_check_adapter_passes_on_a_synthetic_scene(adapter: ExampleGRUAdapter) -> None:
    facts = check_adapter(adapter, synthetic_scene())
    assert facts["log_prob_shape"] == (1, 3, 4)


def test_sample_log_prob_and_trace_semantics(adapter: ExampleGRUAdapter) -> None:
    scene = synthetic_scene()
    out = adapter.sample(scene, 4, generator=torch.Generator().manual_seed(0))
    assert out.futures.shape == (1, 4, 4, 20, 4) and out.trace.tensors["actions"].shape == (1, 4, 4, 20, 2)
    assert out.log_prob[..., 3].eq(0).all() and out.log_prob[..., :3].ne(0).all()  # padding slot not sampled
    # the futures are the traced actions rolled from the current state: step 1 speed = v0 + dt * clipped acc
    first = out.futures[0, :, 0, 0]
    v0 = scene.states[0, 0, scene.current_index, 2]
    acc = out.trace.tensors["actions"][0, :, 0, 0, 0].clamp(-10.0, 8.0)  # the SDK's acceleration bounds
    assert torch.allclose(first[:, 2], v0 + 0.1 * acc, atol=1e-5)
    # log_prob is differentiable and teacher-forced on the trace: perturbing the actions changes it
    lp = adapter.log_prob(scene, out.trace.detach())
    assert lp.requires_grad
    shifted = PolicyTrace({"actions": out.trace.tensors["actions"] + 0.5}, out.trace.agents, out.trace.now)
    assert not torch.isclose(adapter.log_prob(scene, shifted)[..., :3], lp[..., :3]).any()
    with pytest.raises(ValueError, match="current_index"):
        adapter.log_prob(scene.replace_unchecked(current_index=20), out.trace)


def test_imitation_loss_trains() -> None:
    torch.manual_seed(0)
    model = ExampleGRUAdapter(config=GRUConfig(embed=16, hidden=16).model_dump(mode="json"))
    scene = synthetic_scene()
    params = [p for group in model.parameter_groups().values() for p in group]
    optimizer = torch.optim.Adam(params, lr=1e-2)
    losses = []
    for _ in range(15):
        loss = model.imitation_loss(scene)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert math.isfinite(losses[0]) and losses[-1] < losses[0] - 0.5


def test_bundled_checkpoint_is_loaded_by_default_and_checkpoint_overrides(tmp_path) -> None:
    for name in ("config.json", "model.safetensors", "training_log.json", "training_curve.png"):
        assert os.path.isfile(os.path.join(BUNDLED_CHECKPOINT, name)), name
    bundled = load_file(os.path.join(BUNDLED_CHECKPOINT, "model.safetensors"))
    default = ExampleGRUAdapter().module.state_dict()
    assert all(torch.equal(default[k], v) for k, v in bundled.items())
    torch.manual_seed(1)
    other = ExampleGRUAdapter(config=GRUConfig(hidden=32).model_dump(mode="json"))
    other.save_pretrained(str(tmp_path))
    loaded = ExampleGRUAdapter(checkpoint=str(tmp_path))
    assert loaded.config.hidden == 32
    assert all(torch.equal(loaded.module.state_dict()[k], v) for k, v in other.module.state_dict().items())


@needs_data
def test_training_script_writes_a_loadable_checkpoint(tmp_path) -> None:
    from trafficrlhf_example_gru.train import main

    log = main(["--out", str(tmp_path), "--minutes", "1", "--max-steps", "3", "--scenes", "4", "--group-size", "2",
                "--val-scenes", "1", "--val-every", "2"])
    assert log["steps"] == 3 and log["seed"] == 0 and len(log["train_loss"]) == 3
    assert all(math.isfinite(v) for v in log["train_loss"])
    for name in ("config.json", "model.safetensors", "training_log.json", "training_curve.png"):
        assert os.path.isfile(tmp_path / name), name
    assert isinstance(ExampleGRUAdapter.from_pretrained(str(tmp_path)), ExampleGRUAdapter)


# ------------------------------------------------------------------------------------------- plugin system
def test_registry_finds_example_gru_through_the_entry_point() -> None:
    models = registry("traffic_models")
    assert models.get("example_gru") is ExampleGRUAdapter
    assert models.owner("example_gru") == "example_gru"  # the entry-point name, not a default plugin
    row = {r["name"]: r for r in list_plugins()}["example_gru"]
    assert row["version"] == "0.1.0" and "register_traffic_models" in row["hooks"] and not row["default"]
    assert isinstance(get_traffic_model("example_gru", seed=3), ExampleGRUAdapter)


@needs_data
def test_trafficrlhf_evaluate_runs_example_gru() -> None:
    result = CliRunner().invoke(get_cli(), ["evaluate", "--model", "example_gru", "--scenes", "3", "--json"],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["metadata"]["model"] == "example_gru" and report["num_scenes"] == 3
    assert 0.0 <= report["metrics"]["failure_rate"] <= 1.0
    assert math.isfinite(report["metrics"]["realism_ctg"])


# ------------------------------------------------------------------------------------------- broken variants
class FreshNoiseLogProb(ExampleGRUAdapter):
    """Broken: log_prob ignores the trace and scores a freshly drawn sample instead."""

    def log_prob(self, context: ScenarioTensor, trace: PolicyTrace) -> torch.Tensor:
        fresh = self.sample(context, trace.tensors["actions"].shape[1]).trace
        return super().log_prob(context, fresh)


class TruncatedSample(ExampleGRUAdapter):
    """Broken: sample returns only the first 10 of the 20 steps."""

    def sample(self, context, num_samples, guidance=None, generator=None) -> SampleOutput:
        out = super().sample(context, num_samples, guidance, generator)
        return SampleOutput(out.futures[..., :10, :], out.trace, out.log_prob)


class IgnoresGenerator(ExampleGRUAdapter):
    """Broken: draws its noise from torch's global generator."""

    def sample(self, context, num_samples, guidance=None, generator=None) -> SampleOutput:
        return super().sample(context, num_samples, guidance, None)


@pytest.mark.parametrize(
    ("broken", "what", "fix"),
    [
        (FreshNoiseLogProb, "log_prob() recomputed from the trace differs from the sampling-time value",
         "store in the trace everything the sample depended on"),
        (TruncatedSample, "futures have shape (1, 3, 4, 10, 4), expected (1, 3, 4, 20, 4)",
         "return (B, S, A, horizon, 4) scene-frame states for every agent slot"),
        (IgnoresGenerator, "two sample() calls with identically seeded generators differ",
         "draw all randomness from the `generator` argument"),
    ],
)
def test_check_adapter_catches_broken_adapters(broken: type[ExampleGRUAdapter], what: str, fix: str) -> None:
    with pytest.raises(AdapterCheckError) as info:
        check_adapter(broken(), synthetic_scene())
    message = str(info.value)
    assert f"adapter {broken.__name__} ('example_gru')" in message
    assert what in message and f"Fix: {fix}" in message
