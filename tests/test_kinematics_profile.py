"""``scripts/kinematics_profile.py``: the log's and a model's kinematic spread in closed loop."""

from __future__ import annotations


import numpy as np
import pytest
import torch

def test_profile_matches_numpy(load_script) -> None:  # type: ignore[no-untyped-def]
    values = torch.randn(500, generator=torch.Generator().manual_seed(0)) * 2.0
    row = load_script("kinematics_profile").profile(values)
    assert row["n"] == 500
    assert row["mean_abs"] == pytest.approx(float(np.abs(values.numpy()).mean()), rel=1e-6)
    assert row["q10"] == pytest.approx(float(np.quantile(values.numpy(), 0.1)), rel=1e-5)
    assert row["q99"] == pytest.approx(float(np.quantile(values.numpy(), 0.99)), rel=1e-5)


def test_a_replayed_log_has_the_logs_profile_and_a_constant_velocity_one_is_calmer(  # type: ignore[no-untyped-def]
        val_scenes, load_script) -> None:
    script = load_script("kinematics_profile")
    replay = script.closed_loop_profiles("log_replay", None, None, val_scenes, seed=0, batch_size=2)
    for q in script.QUANTITIES:
        assert replay["model"][q] == pytest.approx(replay["log"][q], rel=1e-5, abs=1e-5)
    assert replay["log"]["speed"]["n"] > 0
    steady = script.closed_loop_profiles("constant_velocity", None, None, val_scenes, seed=0, batch_size=2)
    # constant speed and heading: no longitudinal acceleration, less spread than the log
    assert steady["model"]["lon_acc"]["mean_abs"] < 0.05 < steady["log"]["lon_acc"]["mean_abs"]
