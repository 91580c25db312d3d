"""`trafficrlhf report`: one page over evaluation folders, pooling seed folders and giving each run's change
against the base with an interval over scenes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from trafficrlhf_sdk.errors import DataNotFoundError, TrafficRLHFError
from trafficrlhf_sdk.evaluation.compare import run_folders
from trafficrlhf_sdk.evaluation.report import write_report

SCENES = [f"scene-{i:04d}" for i in range(12)]


def _write(folder: Path, seed: int, failures: list[float], checkpoint: str) -> None:
    folder.mkdir(parents=True)
    agents = [2] * len(failures)
    metrics = {"failure_rate": sum(failures) / len(failures), "collision_rate": 0.0,
               "offroad_rate": sum(failures) / len(failures), "realism_ctg": 0.08, "realism_body": 0.1,
               "speed_ratio": 1.0}
    result = {"metrics": metrics, "logged": {}, "num_scenes": len(failures), "num_controlled_agents": sum(agents),
              "metadata": {"seed": seed, "model": "ctg", "checkpoint": checkpoint, "guidance": "no_collision",
                           "scene_ids": SCENES[: len(failures)]},
              "per_scene": {"controlled_agents": agents, "failure_rate": failures, "collision_rate":
                            [0.0] * len(failures), "offroad_rate": failures}}
    (folder / "results.json").write_text(json.dumps(result))


def test_seed_folders_are_pooled_and_each_run_gets_an_interval_against_the_base(tmp_path: Path) -> None:
    base_failures = [[0.5, 0.0, 0.5, 1.0, 0.0, 0.5, 0.5, 0.0, 1.0, 0.5, 0.0, 0.5],
                     [0.5, 0.5, 0.0, 1.0, 0.0, 0.5, 0.0, 0.5, 1.0, 0.5, 0.5, 0.0]]
    for seed, failures in enumerate(base_failures):
        _write(tmp_path / "base" / f"seed_{seed}", seed, failures, "ctg-4s")
    for seed in range(2):  # the aligned model halves every scene's failures
        _write(tmp_path / "aligned" / f"seed_{seed}", seed, [f / 2 for f in base_failures[seed]], "ctg-aligned")
    assert run_folders(str(tmp_path / "base")) == [str(tmp_path / "base" / "seed_0"),
                                                   str(tmp_path / "base" / "seed_1")]
    path = write_report(str(tmp_path / "report"), [("base", str(tmp_path / "base")),
                                                   ("aligned", str(tmp_path / "aligned"))])
    text = Path(path).read_text()
    assert "each value the mean over seeds 0, 1" in text
    base_mean = (sum(base_failures[0]) + sum(base_failures[1])) / 24
    assert f"| failure rate | {base_mean:.4f} | {base_mean / 2:.4f} |" in text
    assert "### aligned against base" in text
    row = next(line for line in text.splitlines() if line.startswith("| failure rate |") and "%" in line)
    assert "-50.0 %" in row  # every scene halves: the change and both interval ends are -50 %
    assert row.count("-50.0 %") == 3


def test_a_single_run_folder_is_read_as_one_seed(tmp_path: Path) -> None:
    _write(tmp_path / "base", 0, [0.5, 0.0, 1.0], "ctg-4s")
    _write(tmp_path / "other", 0, [0.5, 0.5, 1.0], "other")
    assert run_folders(str(tmp_path / "base")) == [str(tmp_path / "base")]
    text = Path(write_report(str(tmp_path / "r"), [("base", str(tmp_path / "base")),
                                                   ("other", str(tmp_path / "other"))])).read_text()
    assert "; seed 0." in text and "+33.3 %" in text


def test_a_missing_results_file_names_the_folder(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataNotFoundError, match=r"results\.json"):
        write_report(str(tmp_path / "r"), [("base", str(tmp_path / "empty"))])


def test_two_runs_under_one_label_are_refused(tmp_path: Path) -> None:
    _write(tmp_path / "base", 0, [0.5, 0.0, 1.0], "ctg-4s")
    with pytest.raises(TrafficRLHFError, match=r"'this run', 'this_run' name more than one run"):
        write_report(str(tmp_path / "r"), [("this run", str(tmp_path / "base")), ("this_run", str(tmp_path / "base"))])
    assert not (tmp_path / "r").exists()


def test_runs_of_different_seeds_under_the_same_model_name_are_compared_as_given(tmp_path: Path) -> None:
    """The report pairs the runs it was given, whatever their labels in results.json (here both 'ctg-4s')."""
    failures = [0.5, 0.0, 0.5, 1.0, 0.0, 0.5]
    for seed in (0, 1):
        _write(tmp_path / "a" / f"seed_{seed}", seed, failures, "ctg-4s")
    for seed in (2, 3):
        _write(tmp_path / "b" / f"seed_{seed}", seed, [f / 2 for f in failures], "ctg-4s")
    text = Path(write_report(str(tmp_path / "r"), [("a", str(tmp_path / "a")), ("b", str(tmp_path / "b"))])).read_text()
    assert "seeds a: 0, 1; b: 2, 3" in text and "(2 / 2 seed(s))" in text
    row = next(line for line in text.splitlines() if line.startswith("| failure rate |") and "%" in line)
    assert row.count("-50.0 %") == 3


def test_results_without_per_scene_values_get_a_note_instead_of_an_interval(tmp_path: Path) -> None:
    for name in ("base", "other"):
        _write(tmp_path / name, 0, [0.5, 0.0, 1.0], name)
        result = json.loads((tmp_path / name / "results.json").read_text())
        del result["per_scene"]
        (tmp_path / name / "results.json").write_text(json.dumps(result))
    text = Path(write_report(str(tmp_path / "r"), [("base", str(tmp_path / "base")),
                                                   ("other", str(tmp_path / "other"))])).read_text()
    assert "No interval: no per-scene failure" in text and "| failure rate | 0.5000 | 0.5000 |" in text
