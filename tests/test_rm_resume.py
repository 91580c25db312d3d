"""Interrupting ``rm train`` loses nothing: every epoch is checkpointed in the output folder and a resumed run
ends with the same weights, bit for bit, as an uninterrupted one (RNG states, optimizer, moving average and
early-stopping state included)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from trafficrlhf_sdk.cli import get_cli
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.feedback import FeedbackStore, SyntheticAnnotator, SyntheticAnnotatorConfig
from trafficrlhf_sdk.reward import RewardConfig
from trafficrlhf_sdk.reward.evaluation import load_preferences
from trafficrlhf_sdk.reward.trainer import RewardTrainer
from trafficrlhf_sdk.scenario.io import safe_load_file
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

SMALL = {"hidden_sizes": [16, 8], "map_channels": [2, 4], "map_embedding": 4}
SMALL_OPTIONS = [arg for key, value in (("hidden_sizes", "[16,8]"), ("map_channels", "[2,4]"),
                                        ("map_embedding", "4")) for arg in ("--architecture-option", f"{key}={value}")]


@pytest.fixture(scope="module")
def tiny_db(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = str(tmp_path_factory.mktemp("resume") / "feedback.db")
    store = FeedbackStore(path)
    make_tiny_campaign(store, num_contexts=10)
    SyntheticAnnotator(store, "noisy", SyntheticAnnotatorConfig(epsilon=0.2)).label("tiny")
    store.close()
    return path


def config(**changes: object) -> RewardConfig:
    base = {"architecture_config": SMALL, "max_epochs": 4, "batch_size": 3, "progress": False, "num_threads": 1,
            "early_stopping_patience": 2, "learning_rate": 3e-3}
    return RewardConfig(**{**base, **changes})  # type: ignore[arg-type]


class Interrupt:
    """An epoch log that presses Ctrl-C after the given epoch of the given member."""

    def __init__(self, member: int, epoch: int) -> None:
        self.at = (member, epoch)

    def __call__(self, row: dict[str, float]) -> None:
        if (int(row["member"]), int(row["epoch"])) == self.at:
            raise KeyboardInterrupt


def weights(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


@pytest.mark.parametrize(("ensemble", "member", "epoch"), [(1, 0, 1), (1, 0, 3), (2, 0, 4), (2, 1, 2)])
def test_an_interrupted_run_resumes_to_the_same_weights(tiny_db: str, tmp_path: Path, ensemble: int, member: int,
                                                       epoch: int) -> None:
    dataset, _ = load_preferences(tiny_db, "tiny", None, ("noisy",), 0.3, 0)
    cfg = config(ensemble_size=ensemble)
    reference = RewardTrainer(cfg, train_dataset=dataset).train()

    folder = str(tmp_path / "checkpoints")
    with pytest.raises(KeyboardInterrupt):
        RewardTrainer(cfg, train_dataset=dataset, checkpoint_dir=folder, log=Interrupt(member, epoch)).train()
    kept = sorted(os.listdir(folder))
    assert kept and all(name.startswith("checkpoint-") and not name.endswith(".tmp") for name in kept)
    with pytest.raises(TrafficRLHFError, match="--resume"):  # never silently overwritten by a fresh start
        RewardTrainer(cfg, train_dataset=dataset, checkpoint_dir=folder).train()
    resumed = RewardTrainer(cfg, train_dataset=dataset, checkpoint_dir=folder).train(resume=True)

    assert resumed.best_epochs == reference.best_epochs
    assert [(r["member"], r["epoch"], r["train_loss"]) for r in resumed.history] == \
        [(r["member"], r["epoch"], r["train_loss"]) for r in reference.history]
    expected, got = weights(reference.model), weights(resumed.model)
    assert expected.keys() == got.keys()
    assert all(torch.equal(expected[k], got[k]) for k in expected)


def test_resume_refuses_other_settings_and_a_missing_checkpoint(tiny_db: str, tmp_path: Path) -> None:
    dataset, _ = load_preferences(tiny_db, "tiny", None, ("noisy",), 0.3, 0)
    folder = str(tmp_path / "checkpoints")
    with pytest.raises(TrafficRLHFError, match="no checkpoint"):
        RewardTrainer(config(), train_dataset=dataset, checkpoint_dir=folder).train(resume=True)
    with pytest.raises(KeyboardInterrupt):
        RewardTrainer(config(), train_dataset=dataset, checkpoint_dir=folder, log=Interrupt(0, 1)).train()
    with pytest.raises(TrafficRLHFError, match="learning_rate"):
        RewardTrainer(config(learning_rate=1e-3), train_dataset=dataset, checkpoint_dir=folder).train(resume=True)
    other, _ = load_preferences(tiny_db, "tiny", None, ("noisy",), 0.5, 1)
    with pytest.raises(TrafficRLHFError, match="other preference pairs"):
        RewardTrainer(config(), train_dataset=other, checkpoint_dir=folder).train(resume=True)


def test_ctrl_c_in_rm_train_then_resume_equals_an_uninterrupted_run(tiny_db: str, tmp_path: Path) -> None:
    args = ["rm", "train", "--db", tiny_db, "--campaign", "tiny", "--annotator", "noisy", "--epochs", "40",
            "--patience", "40", "--batch-size", "2", "--threads", "1", "--quiet", *SMALL_OPTIONS]
    whole = tmp_path / "whole"
    result = CliRunner().invoke(get_cli(), [*args, "--out", str(whole)], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert not (whole / "checkpoints").exists()  # removed once the model is saved

    out = tmp_path / "interrupted"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    code = "from trafficrlhf_sdk.cli import main; main()"
    # a process started in the background (`cmd &`) ignores SIGINT and its children inherit that: give the run
    # Ctrl-C back, as in a terminal
    process = subprocess.Popen([sys.executable, "-c", code, *args, "--out", str(out)], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    # older checkpoints are rotated out, so wait for any from the third epoch on, not for checkpoint-3 itself
    while not any(p.name[11:].isdigit() and int(p.name[11:]) >= 3 for p in (out / "checkpoints").glob("checkpoint-*")):
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, f"exit code {process.returncode}, expected 130 (interrupted): {err}"
    assert "Interrupted" in err and "--resume" in err and "Traceback" not in err
    assert not (out / "model.safetensors").exists()

    result = CliRunner().invoke(get_cli(), [*args, "--out", str(out), "--resume"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    expected, _ = safe_load_file(whole / "model.safetensors")
    got, _ = safe_load_file(out / "model.safetensors")
    assert all(torch.equal(expected[k], got[k]) for k in expected)
    assert not (out / "checkpoints").exists()


def test_an_interrupted_reward_model_step_continues_from_its_newest_epoch(tiny_db: str, tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """The RLHF loop's and the paper experiments' reward-model steps: rerun after Ctrl-C, the step continues from
    the checkpoint (no step.json yet) and ends with the weights of an uninterrupted step."""
    from trafficrlhf_sdk.pipeline import read_manifest
    from trafficrlhf_sdk.pipeline.stages import reward_model_step

    cfg = config(max_epochs=5, early_stopping_patience=None)
    whole = reward_model_step(str(tmp_path / "whole"), cfg, tiny_db, ["tiny"], val_fraction=0.3)

    save = RewardTrainer._save_checkpoint
    epochs_seen: list[int] = []

    def save_then_interrupt(self: RewardTrainer, member: int, epoch: int, *args: object) -> str:
        folder = save(self, member, epoch, *args)  # type: ignore[arg-type]
        epochs_seen.append(epoch)
        if epoch == 3:
            raise KeyboardInterrupt
        return folder

    folder = str(tmp_path / "step")
    monkeypatch.setattr(RewardTrainer, "_save_checkpoint", save_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        reward_model_step(folder, cfg, tiny_db, ["tiny"], val_fraction=0.3)
    assert read_manifest(folder) is None and os.listdir(os.path.join(folder, "checkpoints"))
    assert epochs_seen == [1, 2, 3]

    def save_and_record(self: RewardTrainer, member: int, epoch: int, *args: object) -> str:
        epochs_seen.append(epoch)
        return save(self, member, epoch, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(RewardTrainer, "_save_checkpoint", save_and_record)
    epochs_seen.clear()
    resumed = reward_model_step(folder, cfg, tiny_db, ["tiny"], val_fraction=0.3)
    assert epochs_seen == [4, 5]  # continued, not trained again
    assert not resumed.cached and read_manifest(folder) is not None
    assert not os.path.exists(os.path.join(folder, "checkpoints"))
    expected, _ = safe_load_file(os.path.join(whole.folder, "model.safetensors"))
    got, _ = safe_load_file(os.path.join(folder, "model.safetensors"))
    assert all(torch.equal(expected[k], got[k]) for k in expected)
    assert resumed["metrics"] == whole["metrics"]
