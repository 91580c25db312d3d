"""Ctrl-C in `trafficrlhf rlhf`, then the same command again: the same reward model and aligned model, tensor for
tensor, as a run never interrupted (the step cache and the alignment's epoch checkpoints; see test_pipeline.py
for the logic without data)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.data]

CONFIG = """
model = "ctg"
checkpoint = "ctg-4s"
model_options = { steer_road = true, steer_gate = true }
guidance = "no_collision"
rounds = 1
contexts_per_round = 10
candidates = 5
seconds = 4.0
annotators = ["attentive", "flow"]
probe_scenes = 2

[reward]
ensemble_size = 1
max_epochs = 3

[align]
alpha = 3.0
imitation_coef = 0.0
groups = ["steer"]
epochs = 3
contexts_per_epoch = 2
samples_per_context = 2
failure_fraction = 0.0
credit = "agent"
num_scenes = 12
"""


def _command(config: Path, out: Path) -> list[str]:
    code = "from trafficrlhf_sdk.cli import main; main()"
    return [sys.executable, "-c", code, "rlhf", "--config", str(config), "--out", str(out)]


def _tensors(out: Path) -> dict[str, dict[str, bytes]]:
    from safetensors.numpy import load_file

    return {part: {k: v.tobytes() for k, v in load_file(out / "round_0" / part / "model.safetensors").items()}
            for part in ("reward_model", "aligned")}


def _reset_sigint() -> None:  # a child of a background job starts with SIGINT ignored; Ctrl-C must reach it
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_during_the_reward_model_or_the_alignment_then_rerun_equals_an_uninterrupted_run(
        data_root: str, tmp_path: Path) -> None:
    config = tmp_path / "loop.toml"
    config.write_text(CONFIG)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "TRAFFICRLHF_DATA": data_root}
    subprocess.run(_command(config, tmp_path / "whole"), env=env, check=True, capture_output=True)
    expected = _tensors(tmp_path / "whole")

    out = tmp_path / "interrupted"
    process = subprocess.Popen(_command(config, out), env=env, preexec_fn=_reset_sigint,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    labelled = out / "round_0" / "reward_model"  # the labels are done once the reward-model step starts
    deadline = time.monotonic() + 300
    while not labelled.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    output, _ = process.communicate(timeout=120)
    if process.returncode == 0:
        pytest.skip("the run finished before the interrupt arrived")
    assert process.returncode == 130, output[-2000:]  # interrupted
    assert output.rstrip().endswith("Interrupted")
    assert not (out / "round_0" / "aligned" / "model.safetensors").exists()

    rerun = subprocess.run(_command(config, out), env=env, capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stdout[-2000:] + rerun.stderr[-2000:]
    assert _tensors(out) == expected
