"""Alignment (stage III): the PPO fine-tuner over the adapter contract, and the Gymnasium environment.

Uses the ``example_gru`` plugin on a few real nuScenes train scenes and hand-written rewards, so it runs in
well under a minute on one CPU thread.
"""

from __future__ import annotations

import os

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer, align
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.metrics.failure import collisions_per_step
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.testing.rewards import SlowDownReward

gru = pytest.importorskip("trafficrlhf_example_gru")

FAST = dict(epochs=2, contexts_per_epoch=4, samples_per_context=3, minibatch_contexts=2, ppo_epochs=2,
            progress_bar=False)


class NoCollisionReward:
    """Per-step reward: minus the share of controlled agents in a collision."""

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        mask = scenario.controlled[:, :, None] & scenario.valid
        bad = (collisions_per_step(scenario) & mask).sum(1).float()
        return -(bad / mask.sum(1).clamp_min(1))


@pytest.fixture(scope="module")
def train_scenes(nuscenes_source) -> ScenarioTensor:  # type: ignore[no-untyped-def]
    return nuscenes_source.load_batch("train", 6)


def _model():  # type: ignore[no-untyped-def]
    torch.manual_seed(0)
    return gru.ExampleGRUAdapter()


def _state(model) -> dict[str, torch.Tensor]:  # type: ignore[no-untyped-def]
    return {k: v.detach().clone() for k, v in model.module.state_dict().items()}


def test_frozen_groups_stay_bitwise_equal(train_scenes: ScenarioTensor) -> None:
    model = _model()
    before = _state(model)
    encoder = {id(p) for p in model.parameter_groups()["encoder"]}
    names = {n for n, p in model.module.named_parameters() if id(p) in encoder}
    align(model, NoCollisionReward(), alpha=1.0, scenes=train_scenes, groups=("decoder",), **FAST)
    after = _state(model)
    assert names, "the example model offers an encoder group"
    for key, value in before.items():
        if key in names:
            assert torch.equal(value, after[key]), key
    assert any(not torch.equal(before[k], after[k]) for k in before if k not in names), "the decoder must train"
    assert all(p.requires_grad for p in model.module.parameters()), "requires_grad is restored after training"


def test_first_ppo_epoch_ratios_are_one(train_scenes: ScenarioTensor) -> None:
    model = _model()
    result = align(model, NoCollisionReward(), alpha=1.0, scenes=train_scenes, **FAST)
    for stats in result.history:
        assert stats["first_ratio_max_dev"] == 0.0  # before any update the ratio is exactly 1
        assert stats["sample_log_prob_gap"] < 1e-3  # adapter.log_prob reproduces the sampling log-prob
    # with a zero learning rate nothing moves, so every ratio of every pass is 1: no clipping, KL 0
    frozen = align(_model(), NoCollisionReward(), alpha=1.0, scenes=train_scenes,
                   **{**FAST, "learning_rate": 0.0})
    assert all(s["approx_kl"] == 0.0 and s["clip_fraction"] == 0.0 for s in frozen.history)


def test_run_without_output_dir_logs_to_stdout_and_writes_no_files(train_scenes: ScenarioTensor, tmp_path,
                                                                     monkeypatch, capsys) -> None:
    # SB3's configure(None, ...) would make an SB3-<date> folder in the temp dir on every call
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    monkeypatch.delenv("SB3_LOGDIR", raising=False)
    align(_model(), NoCollisionReward(), alpha=1.0, scenes=train_scenes,
          **{**FAST, "epochs": 1, "progress_bar": True})
    assert list(tmp_path.iterdir()) == []
    assert "train/" in capsys.readouterr().out  # the epoch's table still reaches stdout


def test_mean_reward_rises_on_a_small_problem(train_scenes: ScenarioTensor) -> None:
    model = _model()
    config = {**FAST, "epochs": 12, "contexts_per_epoch": 6, "samples_per_context": 4, "minibatch_contexts": 3,
              "imitation_coef": 0.0, "learning_rate": 3e-3, "ppo_epochs": 2}
    history = align(model, SlowDownReward(), alpha=1.0, scenes=train_scenes, **config).history
    first = sum(h["reward_mean"] for h in history[:3]) / 3
    last = sum(h["reward_mean"] for h in history[-3:]) / 3
    assert last > first + 0.05, (first, last)


def test_interrupted_and_resumed_run_matches_uninterrupted(train_scenes: ScenarioTensor, tmp_path) -> None:
    config = {**FAST, "epochs": 3, "save_every": 1, "kl_coef": 0.1}
    full = _model()
    align(full, NoCollisionReward(), alpha=1.0, scenes=train_scenes, output_dir=str(tmp_path / "full"), **config)

    part = _model()
    align(part, NoCollisionReward(), alpha=1.0, scenes=train_scenes, output_dir=str(tmp_path / "cut"),
          callback=lambda epoch, stats: epoch < 0, **config)  # "interrupted" after the first epoch
    assert os.path.isdir(tmp_path / "cut" / "checkpoints" / "checkpoint-1")
    resumed = _model()  # a fresh process: the starting weights, then the checkpoint
    result = align(resumed, NoCollisionReward(), alpha=1.0, scenes=train_scenes, output_dir=str(tmp_path / "cut"),
                   resume=True, **config)
    assert len(result.history) == 3
    for key, value in _state(full).items():
        assert torch.equal(value, _state(resumed)[key]), key
    assert os.path.isfile(tmp_path / "cut" / "logs" / "progress.csv")
    # the final folder is a save_pretrained checkpoint the adapter (and `trafficrlhf evaluate`) loads
    loaded = gru.ExampleGRUAdapter(checkpoint=str(tmp_path / "cut"))
    for key, value in _state(full).items():
        assert torch.equal(value, _state(loaded)[key]), key


def test_config_errors_are_clear(train_scenes: ScenarioTensor) -> None:
    with pytest.raises(ValueError, match="extra"):
        AlignConfig(learning_rat=1e-3)
    with pytest.raises(ValueError, match="output_dir"):
        AlignConfig(resume=True)
    with pytest.raises(TrafficRLHFError, match="offers"):
        AlignTrainer(_model(), NoCollisionReward(), AlignConfig(groups=("initializer",)), scenes=train_scenes)


def test_gymnasium_env_passes_check_env_and_trains_with_sb3(train_scenes: ScenarioTensor) -> None:
    pytest.importorskip("gymnasium")
    sb3 = pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_checker import check_env

    from trafficrlhf_sdk.alignment import TrafficRLHFEnv

    env = TrafficRLHFEnv(train_scenes[:3], NoCollisionReward())
    check_env(env, warn=True)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and "ego" in info
    steps, done = 0, False
    while not done:  # 10 s at 0.5 s per action = 20 steps
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        assert -1.0 <= reward <= 1.0
        steps, done = steps + 1, terminated or truncated
    assert steps == 20
    agent = sb3.PPO("MlpPolicy", env, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu")
    from stable_baselines3.common.logger import Logger

    agent.set_logger(Logger(None, []))  # SB3's default logger would leave an SB3-<date> folder in the temp dir
    agent.learn(256)
    action, _ = agent.predict(obs, deterministic=True)
    assert env.action_space.contains(action)


def test_cli_align_then_evaluate_the_aligned_checkpoint(data_root: str, tmp_path) -> None:
    """A TOML recipe plus command-line overrides trains, records its config, and the result evaluates by folder
    alone (the adapter is read from its config.json); bad recipes get one clear error naming the file."""
    import json

    from click.testing import CliRunner

    from trafficrlhf_sdk.cli import get_cli

    recipe = tmp_path / "recipe.toml"
    recipe.write_text('model = "example_gru"\nreward_model = "builtin:collision"\nthreads = 1\n'
                      '[align]\ncontexts_per_epoch = 2\nsamples_per_context = 2\ncredit = "agent"\n'
                      'failure_fraction = 0.5\nfailure_scenes = 2\nepochs = 5\n', encoding="utf-8")
    out = str(tmp_path / "aligned")
    runner = CliRunner()
    result = runner.invoke(get_cli(), ["align", "--config", str(recipe), "--out", out, "--epochs", "2",
                                       "--scenes", "3", "--quiet"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert "aligned example_gru for 2 epochs" in result.output
    summary = json.load(open(os.path.join(out, "align_summary.json"), encoding="utf-8"))
    assert summary["alpha"] == 0.3 and summary["epochs"] == 2 and summary["reward_model"] == "builtin:collision"
    history = json.load(open(os.path.join(out, "align_history.json"), encoding="utf-8"))
    assert history["config"]["credit"] == "agent" and history["config"]["failure_fraction"] == 0.5
    assert history["config"]["epochs"] == 2 and history["reward_model"] == "builtin:collision"
    assert "heldout_realism" in history["history"][0] and os.path.isfile(os.path.join(out, "overoptimization.png"))
    result = runner.invoke(get_cli(), ["evaluate", "--checkpoint", out, "--scenes", "2", "--json"],
                           catch_exceptions=False)
    assert result.exit_code == 0, result.output
    report = json.loads(result.output[result.output.index("{"):])
    assert report["metadata"]["checkpoint"] == out and report["metadata"]["model"] == "example_gru"
    assert 0 <= report["metrics"]["failure_rate"] <= 1
    wrong = runner.invoke(get_cli(), ["evaluate", "--model", "ctg", "--checkpoint", out, "--scenes", "1"])
    assert wrong.exit_code != 0 and "saved by traffic model 'example_gru'" in str(wrong.exception)
    bad = runner.invoke(get_cli(), ["align", "--model", "example_gru", "--reward-model", "builtin:nope", "--out", out])
    assert bad.exit_code != 0 and "builtin:collision" in str(bad.exception)
    broken = tmp_path / "broken.toml"
    broken.write_text('model = "example_gru"\nreward_model = "builtin:collision"\n[align]\nepoch = 3\n')
    bad = runner.invoke(get_cli(), ["align", "--config", str(broken), "--out", out])
    assert bad.exit_code != 0 and "broken.toml" in str(bad.exception) and "epoch" in str(bad.exception)
    bad = runner.invoke(get_cli(), ["align", "--model", "example_gru", "--out", out])
    assert bad.exit_code != 0 and "--reward-model" in str(bad.exception)

def test_target_kl_stops_the_ppo_passes_early(train_scenes: ScenarioTensor) -> None:
    config = {**FAST, "epochs": 1, "ppo_epochs": 4, "learning_rate": 1e-2}
    full = align(_model(), NoCollisionReward(), alpha=1.0, scenes=train_scenes, **config).history[0]
    early = align(_model(), NoCollisionReward(), alpha=1.0, scenes=train_scenes, target_kl=1e-9, **config).history[0]
    assert full["early_stop"] == 0.0 and full["updates"] == 8.0  # 4 passes x 2 minibatches
    assert early["early_stop"] == 1.0 and early["updates"] < full["updates"]


@given(st.lists(st.text(min_size=1, max_size=4), unique=True, max_size=60), st.integers(2, 12))
def test_holdout_splits_the_scene_list(ids: list[str], every: int) -> None:
    """Training and held-out scenes partition the split; every k-th scene is held out, in order."""
    from trafficrlhf_sdk.alignment.contexts import held_out_scene_ids, training_scene_ids

    train, held = training_scene_ids(ids, every), held_out_scene_ids(ids, every)
    assert not set(train) & set(held) and sorted(train + held) == sorted(ids)
    assert len(held) == len(ids) // every and held == [ids[i] for i in range(every - 1, len(ids), every)]
    assert training_scene_ids(ids, None) == ids


def test_alignment_never_loads_held_out_scenes(data_root: str) -> None:
    trainer = AlignTrainer(_model(), NoCollisionReward(), AlignConfig(num_scenes=4, holdout_every=3))
    loaded = [s.scene_ids[0] for s in trainer._load_scenes()]
    from trafficrlhf_sdk import get_scenario_source

    ids = get_scenario_source("nuscenes_pred").scene_ids("train")
    assert loaded == [ids[0], ids[1], ids[3], ids[4]]


def test_mirror_scenes_adds_a_mirror_image_of_every_training_scene(train_scenes: ScenarioTensor) -> None:
    from trafficrlhf_sdk.scenario import MIRROR_SUFFIX

    plain = AlignTrainer(_model(), NoCollisionReward(), AlignConfig(**FAST), scenes=train_scenes)._load_scenes()
    trainer = AlignTrainer(_model(), NoCollisionReward(), AlignConfig(mirror_scenes=True, **FAST),
                           scenes=train_scenes)
    scenes = trainer._load_scenes()
    n = train_scenes.num_scenes
    assert len(plain) == n and len(scenes) == 2 * n
    assert [s.scene_ids[0] for s in scenes[n:]] == [s.scene_ids[0] + MIRROR_SUFFIX for s in scenes[:n]]
    assert torch.equal(scenes[n].states[..., 1], -scenes[0].states[..., 1])
    drawn = set()
    for epoch in range(4):
        contexts, _ = trainer.context_sampler.draw(torch.Generator().manual_seed(epoch))
        drawn |= set(contexts.scene_ids)
    assert any(s.endswith(MIRROR_SUFFIX) for s in drawn) and not all(s.endswith(MIRROR_SUFFIX) for s in drawn)
    trainer.train()  # failure drives and PPO run on both halves


def _log_start(window: ScenarioTensor, scenes: dict[str, ScenarioTensor]) -> int | None:
    """The step of its logged scene at which the single-scene ``window`` starts (None: not a window of the log)."""
    scene = scenes[window.scene_ids[0]]
    steps, agents = window.num_steps, scene.num_agents
    for t in range(scene.num_steps - steps + 1):
        valid = scene.valid[0, :, t: t + steps]
        if torch.equal(window.valid[0, :agents], valid) and torch.equal(
                window.states[0, :agents][valid], scene.states[0, :, t: t + steps][valid]):
            return t
    return None



def test_the_monitor_keeps_the_best_held_out_epoch_and_stops_after_its_patience() -> None:
    from trafficrlhf_sdk.alignment.monitor import HeldOutMonitor

    weight = torch.nn.Parameter(torch.zeros(2))
    monitor = HeldOutMonitor(patience=2, smoothing=0.0)
    stops = []
    for epoch, (realism, value) in enumerate([(0.5, 1.0), (0.7, 2.0), (0.6, 3.0), (0.65, 4.0)], start=1):
        with torch.no_grad():
            weight.fill_(value)
        stops.append(monitor.update(epoch, realism, [weight]))
    assert stops == [False, False, False, True]
    assert monitor.restore_best([weight]) == 2 and torch.equal(weight.detach(), torch.full((2,), 2.0))


def test_early_stopping_keeps_the_weights_the_monitor_scored(train_scenes: ScenarioTensor, tmp_path) -> None:
    """The held-out realism of an epoch is measured before its update, so the kept weights are those after
    ``best_epoch`` updates (0: the starting weights), and the weights after the last update are scored too."""
    model = _model()
    snapshots = [[p.detach().clone() for p in model.module.parameters()]]

    def keep(epoch: int, stats: dict[str, float]) -> None:
        snapshots.append([p.detach().clone() for p in model.module.parameters()])

    config = {**FAST, "epochs": 4, "learning_rate": 3e-3, "early_stopping_patience": 10}
    align(model, NoCollisionReward(), alpha=1.0, scenes=train_scenes, output_dir=str(tmp_path / "run"),
          callback=keep, **config)
    import json

    with open(tmp_path / "run" / "align_history.json", encoding="utf-8") as handle:
        saved = json.load(handle)
    best = saved["best_epoch"]
    realism = [row["heldout_realism"] for row in saved["history"]] + [saved["history"][-1]["final_heldout_realism"]]
    assert len(snapshots) == 5 and 0 <= best <= 4
    assert any(not torch.equal(a, b) for a, b in zip(snapshots[0], snapshots[-1], strict=True)), "nothing trained"
    smoothed, values = None, []
    for value in realism:  # the monitor's moving average (weight 0.7 on the past)
        smoothed = value if smoothed is None else 0.7 * smoothed + 0.3 * value
        values.append(smoothed)
    assert best == max(range(5), key=lambda k: (values[k], -k))
    for kept, expected in zip(model.module.parameters(), snapshots[best], strict=True):
        assert torch.equal(kept.detach(), expected)
