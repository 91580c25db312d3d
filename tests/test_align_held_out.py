"""Held-out evaluation during alignment (``eval_every``), keeping the best evaluated weights (``keep_best``) and
the learning-rate schedule."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer, align
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.testing.rewards import SlowDownReward

gru = pytest.importorskip("trafficrlhf_example_gru")

FAST = dict(epochs=3, contexts_per_epoch=4, samples_per_context=3, minibatch_contexts=2, ppo_epochs=2,
            progress_bar=False, log_formats=("csv",))
SCRIPTED = {1: 0.30, 2: 0.10, 3: 0.20}  # held-out failure rate after each epoch: epoch 2 is the best


@pytest.fixture(scope="module")
def scenes(nuscenes_source) -> tuple[ScenarioTensor, ScenarioTensor]:  # type: ignore[no-untyped-def]
    batch = nuscenes_source.load_batch("train", 8)
    return batch[:6], batch[6:]


def _model():  # type: ignore[no-untyped-def]
    torch.manual_seed(0)
    return gru.ExampleGRUAdapter()


def _state(model) -> dict[str, torch.Tensor]:  # type: ignore[no-untyped-def]
    return {k: v.detach().clone() for k, v in model.module.state_dict().items()}


def _scripted_trainer(config: AlignConfig, train: ScenarioTensor, held: ScenarioTensor) -> AlignTrainer:
    """A trainer whose held-out evaluation returns :data:`SCRIPTED` (the epoch is read off its history)."""
    trainer = AlignTrainer(_model(), SlowDownReward(), config, scenes=train, eval_scenes=held)
    assert trainer.held_out is not None
    trainer.held_out.evaluate = lambda: {"eval_failure_rate": SCRIPTED[len(trainer.history) + 1]}  # type: ignore
    return trainer


def test_held_out_evaluation_does_not_change_training(scenes) -> None:  # type: ignore[no-untyped-def]
    train, held = scenes
    plain = align(_model(), SlowDownReward(), alpha=1.0, scenes=train, **FAST)
    watched = align(_model(), SlowDownReward(), alpha=1.0, scenes=train, eval_scenes=held, eval_every=1,
                    eval_seeds=2, **FAST)
    for a, b in zip(plain.history, watched.history, strict=True):
        assert a["reward_mean"] == b["reward_mean"] and a["loss"] == b["loss"]
    for key, value in _state(plain.model).items():
        assert torch.equal(value, _state(watched.model)[key]), key
    for stats in watched.history:  # every epoch evaluated, real closed-loop figures
        assert 0.0 <= stats["eval_failure_rate"] <= 1.0
        assert stats["eval_failure_rate"] >= max(stats["eval_collision_rate"], stats["eval_offroad_rate"])
        assert stats["eval_realism_ctg"] >= 0.0
    assert all("eval_failure_rate" not in stats for stats in plain.history)


def test_keep_best_ends_with_the_best_evaluated_weights(scenes, tmp_path) -> None:  # type: ignore[no-untyped-def]
    train, held = scenes
    config = AlignConfig(alpha=1.0, eval_every=1, keep_best=True, output_dir=str(tmp_path), **FAST)
    trainer = _scripted_trainer(config, train, held)
    snapshots: list[dict[str, torch.Tensor]] = []
    trainer.train(lambda epoch, stats: snapshots.append(_state(trainer.model)))
    assert trainer.held_out is not None and trainer.held_out.best_epoch == 2
    for key, value in snapshots[1].items():
        assert torch.equal(value, _state(trainer.model)[key]), key
    assert any(not torch.equal(v, snapshots[2][k]) for k, v in snapshots[1].items()), "epoch 3 moved the weights"
    saved = gru.ExampleGRUAdapter(checkpoint=str(tmp_path))  # the saved model is the best one too
    for key, value in snapshots[1].items():
        assert torch.equal(value, _state(saved)[key]), key


def test_keep_best_survives_an_interruption(scenes, tmp_path) -> None:  # type: ignore[no-untyped-def]
    train, held = scenes
    base = dict(alpha=1.0, eval_every=1, keep_best=True, save_every=1, **FAST)
    full = _scripted_trainer(AlignConfig(output_dir=str(tmp_path / "full"), **base), train, held)
    full.train()
    cut = _scripted_trainer(AlignConfig(output_dir=str(tmp_path / "cut"), **base), train, held)
    cut.train(lambda epoch, stats: epoch < 1)  # stops after epoch 2, the best one
    resumed = _scripted_trainer(AlignConfig(output_dir=str(tmp_path / "cut"), resume=True, **base), train, held)
    resumed.train()
    assert resumed.held_out is not None and resumed.held_out.best_epoch == 2
    for key, value in _state(full.model).items():
        assert torch.equal(value, _state(resumed.model)[key]), key


def test_held_out_configuration_errors(scenes) -> None:  # type: ignore[no-untyped-def]
    train, _ = scenes
    with pytest.raises(ValueError, match="eval_every"):
        AlignConfig(keep_best=True)
    with pytest.raises(TrafficRLHFError, match="holdout_every"):
        AlignTrainer(_model(), SlowDownReward(), AlignConfig(eval_every=1, **FAST), scenes=train)


def test_cli_keep_best_needs_eval_every(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["align", "--model", "example_gru", "--reward-model", "builtin:collision", "--out", str(tmp_path),
              "--keep-best"])
    err = capsys.readouterr().err
    assert exit_info.value.code != 0 and "needs `eval_every`" in err and "Traceback" not in err


@pytest.mark.parametrize(("schedule", "expected"), [("linear", [1e-3, 1e-3 * 2 / 3, 1e-3 / 3]),
                                                    ("constant", [1e-3] * 3)])
def test_learning_rate_schedule(scenes, schedule: str, expected: list[float]) -> None:  # type: ignore[no-untyped-def]
    """``lr_schedule='linear'``: epoch e trains at lr x (1 - e / epochs); 'constant' keeps lr."""
    train, _ = scenes
    config = AlignConfig(alpha=1.0, learning_rate=1e-3, lr_schedule=schedule, **FAST)
    trainer = AlignTrainer(_model(), SlowDownReward(), config, scenes=train)
    seen: list[float] = []
    trainer.train(lambda epoch, stats: seen.append(trainer.optimizer.param_groups[0]["lr"]))
    assert seen == pytest.approx(expected)
