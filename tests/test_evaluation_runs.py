"""Multi-seed evaluation and scene selection from Python (``trafficrlhf_sdk.evaluation.runs``)."""

from __future__ import annotations

import json
import os

import pytest

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario import default_data_root


@pytest.fixture(scope="module")
def source():  # type: ignore[no-untyped-def]
    if not os.path.isdir(os.path.join(default_data_root(), "nuscenes_pred", "label")):
        pytest.skip(f"nuscenes_pred not found under {default_data_root()!r}")
    from trafficrlhf_sdk import get_scenario_source

    return get_scenario_source("nuscenes_pred")


def test_evaluate_seeds_gives_each_run_and_their_mean(source, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.evaluation import EvaluationConfig, evaluate_policy, evaluate_seeds
    from trafficrlhf_sdk.plugins import build_policy

    scenes = source.load_batch("val", 3)
    build = lambda seed: build_policy("noisy_log", {"seed": seed})  # noqa: E731
    runs = evaluate_seeds(build, scenes, [3, 4], EvaluationConfig(batch_size=2))
    assert runs.seeds == [3, 4]
    rates = [report.values["failure_rate"] for report in runs.reports]
    assert runs.mean["failure_rate"] == pytest.approx(sum(rates) / 2)
    # each run is the run evaluate_policy makes at that seed
    alone = evaluate_policy(build(4), scenes, EvaluationConfig(batch_size=2, seed=4))
    assert alone.values["failure_rate"] == pytest.approx(rates[1], abs=1e-12)
    folders = runs.save(str(tmp_path))
    assert [os.path.basename(f) for f in folders] == ["seed_3", "seed_4"]
    assert json.loads((tmp_path / "seed_4" / "results.json").read_text())["metadata"]["seed"] == 4
    with pytest.raises(TrafficRLHFError, match="distinct seeds"):
        evaluate_seeds(build, scenes, [1, 1])


def test_run_evaluation_selects_scenes_and_names_the_checkpoint(source, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.evaluation import EvaluationRequest, run_evaluation

    ids = source.scene_ids("val")
    notes: list[str] = []
    outcome = run_evaluation(EvaluationRequest(model="noisy_log", scene_ids=(ids[5], ids[2]), seeds=(0, 1)),
                             str(tmp_path / "out"), log=notes.append, progress=False)
    assert [r.metadata["scene_ids"] for r in outcome.runs.reports] == [[ids[5], ids[2]]] * 2
    assert outcome.folders == [str(tmp_path / "out" / "seed_0"), str(tmp_path / "out" / "seed_1")]
    assert outcome.label == "noisy_log"
    with pytest.raises(TrafficRLHFError, match="--scene-id"):
        run_evaluation(EvaluationRequest(model="noisy_log", scene_ids=(ids[2] + "x",)))
    with pytest.raises(ValueError, match="distinct seeds"):
        EvaluationRequest(seeds=(2, 2))


def test_run_label_names_guidance_and_checkpoint() -> None:
    from trafficrlhf_sdk.evaluation import run_label

    assert run_label({"model": "ctg"}) == "ctg"
    assert run_label({"model": "ctg", "checkpoint": "ctg-aligned", "guidance": "no_collision"}) == \
        "ctg + no_collision (ctg-aligned)"
    # two folders both named `aligned` stay apart
    assert run_label({"model": "ctg", "checkpoint": "out/round_0/aligned"}) == "ctg (round_0/aligned)"
    assert run_label({"model": "ctg", "checkpoint": "out/round_1/aligned"}) == "ctg (round_1/aligned)"
