"""``scripts/kinematics_profile.py``: the log's and a model's kinematic spread in closed loop."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "kinematics_profile.py"


def _script():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("kinematics_profile", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_profile_matches_numpy() -> None:
    values = torch.randn(500, generator=torch.Generator().manual_seed(0)) * 2.0
    row = _script().profile(values)
    assert row["n"] == 500
    assert row["mean_abs"] == pytest.approx(float(np.abs(values.numpy()).mean()), rel=1e-6)
    assert row["q10"] == pytest.approx(float(np.quantile(values.numpy(), 0.1)), rel=1e-5)
    assert row["q99"] == pytest.approx(float(np.quantile(values.numpy(), 0.99)), rel=1e-5)


def test_a_replayed_log_has_the_logs_profile_and_a_constant_velocity_one_is_calmer(val_scenes) -> None:  # type: ignore[no-untyped-def]
    script = _script()
    replay = script.closed_loop_profiles("log_replay", None, None, val_scenes, seed=0, batch_size=2)
    for q in script.QUANTITIES:
        assert replay["model"][q] == pytest.approx(replay["log"][q], rel=1e-5, abs=1e-5)
    assert replay["log"]["speed"]["n"] > 0
    steady = script.closed_loop_profiles("constant_velocity", None, None, val_scenes, seed=0, batch_size=2)
    # constant speed and heading: no longitudinal acceleration, less spread than the log
    assert steady["model"]["lon_acc"]["mean_abs"] < 0.05 < steady["log"]["lon_acc"]["mean_abs"]
