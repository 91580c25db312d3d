"""Side-by-side qualitative figures: tiny synthetic scenes where constant velocity fails and the log does not, the
scene choice, the GIF's frames and panels, the still; and ``trafficrlhf render compare`` on three real scenes."""

from __future__ import annotations

import json
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from PIL import Image

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig
from trafficrlhf_sdk.evaluation.side_by_side import (
    PanelSpec,
    failing_scenes,
    panel_specs,
    save_side_by_side_animation,
    save_side_by_side_still,
    side_by_side_frames,
    simulate_side_by_side,
)
from trafficrlhf_sdk.scenario.map import MapRaster
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import ConstantVelocityPolicy, LogReplayPolicy
from trafficrlhf_sdk.simulation.simulator import SimulationConfig

DT, NOW, STEPS = 0.1, 10, 41  # 1 s of history, 3 s simulated


def _road() -> MapRaster:
    """x in [-60, 160) m, |y| < 6 m drivable, 2 px/m."""
    raster = torch.zeros(1, 3, 440, 80, dtype=torch.uint8)
    ys = (torch.arange(80) + 0.5) / 2 - 20
    raster[0, 0, :, ys.abs() < 6] = 1
    raster[0, 2, :, (ys.abs() - 2).abs() < 0.25] = 1
    return MapRaster(raster=raster, world_to_pixel=torch.tensor([[[2.0, 0.0, 120.0], [0.0, 2.0, 40.0],
                                                                  [0.0, 0.0, 1.0]]]))


def _track(x0: float, y: torch.Tensor | float, speed: torch.Tensor | float) -> torch.Tensor:
    """States (T, 4) of a car starting at x0 with per-step ``y`` and ``speed``."""
    speed = torch.as_tensor(speed, dtype=torch.float32).expand(STEPS).clone()
    y = torch.as_tensor(y, dtype=torch.float32).expand(STEPS).clone()
    x = x0 + torch.cumsum(speed * DT, 0) - speed[0] * DT
    vy = torch.diff(y, append=y[-1:] + (y[-1:] - y[-2:-1])) / DT
    return torch.stack([x, y, speed, torch.atan2(vy, speed.clamp_min(0.1))], -1)


def _scenes() -> ScenarioTensor:
    """Three scenes of two controlled cars: 0 plain driving (nobody fails), 1 a lane change whose heading at the
    start sends constant velocity off the road (1 failure), 2 a car braking behind a stopped one, which constant
    velocity drives into (2 failures: both cars of the collision)."""
    t = torch.arange(STEPS) * DT
    plain = [_track(0.0, -4.0, 10.0), _track(5.0, 4.0, 10.0)]
    after = (t - 1.0).clamp(0.0, 1.0)  # out towards the centre line at 3 m/s until the start, then easing off
    swerve = -4.5 + 3.0 * t.clamp(max=1.0) + 3.0 * after - 1.5 * after**2
    lane_change = [_track(0.0, swerve, 10.0), _track(20.0, 4.0, 10.0)]
    braking = torch.where(t < 1.2, torch.tensor(10.0), (10.0 - 6.0 * (t - 1.2)).clamp(min=0.0))
    queue = [_track(0.0, -4.0, braking), _track(30.0, -4.0, 0.0)]
    states = torch.stack([torch.stack(plain), torch.stack(lane_change), torch.stack(queue)])
    scene_map = _road()
    return ScenarioTensor(
        states=states, valid=torch.ones(3, 2, STEPS, dtype=torch.bool),
        extent=torch.tensor([[4.5, 1.9], [4.6, 1.9]]).expand(3, 2, 2).clone(),
        agent_type=torch.ones(3, 2, dtype=torch.long), controlled=torch.ones(3, 2, dtype=torch.bool), dt=DT,
        current_index=NOW, map=MapRaster(scene_map.padded(), scene_map.world_to_pixel.expand(3, 3, 3).clone(),
                                         rows=torch.zeros(3, dtype=torch.long)),
        scene_ids=("tiny-plain", "tiny-offroad", "tiny-collision"), agent_ids=(("a", "b"),) * 3, source="tiny",
    )


@pytest.fixture(scope="module")
def runs():  # type: ignore[no-untyped-def]
    config = EvaluationConfig(simulation=SimulationConfig(duration_s=3.0))
    return simulate_side_by_side([ConstantVelocityPolicy(), lambda seed: LogReplayPolicy()], _scenes(),
                                 ["constant velocity", "log replay"], seed=0, config=config, note="tiny")


def test_the_base_fails_where_it_should_and_the_log_does_not(runs) -> None:  # type: ignore[no-untyped-def]
    assert [runs.failing_agents(0, b) for b in range(3)] == [0, 1, 2]
    assert [runs.failing_agents(1, b) for b in range(3)] == [0, 0, 0]
    assert runs.failure_rates[1] == 0.0 and runs.failure_rates[0] > 0.0


def test_the_most_failing_scene_comes_first_and_clean_scenes_never(runs) -> None:  # type: ignore[no-untyped-def]
    assert failing_scenes(runs) == [2, 1]
    assert failing_scenes(runs, top=1) == [2]


def test_the_animation_has_one_frame_per_step_shown_and_one_panel_per_model(runs, tmp_path) -> None:  # type: ignore[no-untyped-def]
    frames = side_by_side_frames(runs, 2, frame_hz=5.0, dpi=60)
    shown = list(range(0, STEPS - 1 + 1, 2))  # 1 s before the start (step 0) to the end (step 40), every 0.2 s
    assert len(frames) == len(shown)
    height, width, _ = frames[0].shape
    assert all(f.shape == frames[0].shape for f in frames)
    assert width > 1.6 * height  # two panels side by side over a long road
    path = save_side_by_side_animation(runs, 2, tmp_path / "scene.gif", frame_hz=5.0, dpi=60)
    with Image.open(path) as gif:
        assert gif.format == "GIF" and gif.n_frames == len(shown) and gif.size == (width, height)
        assert gif.info["loop"] == 0 and gif.info["duration"] == 200
    # the failures appear: the last frame holds much more of the failure red than the first (only the legend's)
    def red(frame: np.ndarray) -> int:
        return int((np.abs(frame.astype(int) - np.array([0xE3, 0x00, 0x1B])).sum(-1) < 40).sum())

    assert red(frames[-1]) > red(frames[0]) + 50
    with pytest.raises(ValueError, match=r"\.gif"):
        save_side_by_side_animation(runs, 2, tmp_path / "scene.mp4")


def test_the_still_is_a_png_at_the_base_first_failure(runs, tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = save_side_by_side_still(runs, 1, tmp_path / "still.png", dpi=60)
    assert open(path, "rb").read(8) == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="out of range"):
        save_side_by_side_still(runs, 3, tmp_path / "x.png")


def test_panels_pair_models_and_checkpoints() -> None:
    assert panel_specs(checkpoints=["ctg-4s", "ctg-baseline"]) == (PanelSpec(checkpoint="ctg-4s"),
                                                                   PanelSpec(checkpoint="ctg-baseline"))
    assert [p.model for p in panel_specs(["ctg"], ["a/", "b"])] == ["ctg", "ctg"]
    assert [p.name for p in panel_specs(["ctg"], ["runs/base/", "b"])] == ["base", "b"]
    assert [p.name for p in panel_specs(["constant_velocity", "log_replay"])] == ["constant_velocity", "log_replay"]
    with pytest.raises(TrafficRLHFError, match="--model was given 2 times"):
        panel_specs(["a", "b"], ["x", "y", "z"])
    with pytest.raises(TrafficRLHFError, match="--checkpoint"):
        panel_specs()


def test_render_compare_errors_name_the_argument(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.cli import get_cli

    result = CliRunner().invoke(get_cli(), ["render", "compare", "--out", str(tmp_path)])
    assert result.exit_code != 0 and "--checkpoint" in str(result.exception)
    (tmp_path / "file").write_text("x")
    result = CliRunner().invoke(get_cli(), ["render", "compare", "--model", "constant_velocity", "--model",
                                            "log_replay", "--out", str(tmp_path / "file")])
    assert result.exit_code != 0 and "--out" in str(result.exception) and "is a file" in str(result.exception)


@pytest.mark.slow
@pytest.mark.data
def test_render_compare_on_three_real_scenes(data_root: str, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.cli import get_cli

    pytest.importorskip("trafficrlhf_nuscenes_pred")
    out = tmp_path / "compare"
    result = CliRunner().invoke(get_cli(), ["render", "compare", "--model", "constant_velocity", "--model",
                                            "log_replay", "--scenes", "3", "--worst", "2", "--frame-hz", "2",
                                            "--out", str(out)])
    assert result.exit_code == 0, (result.output, result.exception)
    summary = json.loads((out / "side_by_side.json").read_text())
    assert len(summary["scene_ids"]) == 3 and [m["label"] for m in summary["models"]] == ["constant_velocity",
                                                                                         "log_replay"]
    drawn = summary["drawn"]
    assert 1 <= len(drawn) <= 2  # constant velocity fails somewhere in these scenes
    counts = [row["failing_agents"]["constant_velocity"] for row in drawn]
    assert counts == sorted(counts, reverse=True) and min(counts) > 0
    for row in drawn:
        with Image.open(out / row["animation"]) as gif:
            assert gif.n_frames == len(range(20, 130 + 1, 5))  # from 1 s before the 3 s start to 13 s, at 2 Hz
        assert (out / row["still"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert row["scene_id"] in result.output
