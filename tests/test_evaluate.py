"""``trafficrlhf evaluate`` end to end on a few real scenes, and its error messages."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario import default_data_root


@pytest.fixture(scope="module")
def has_data() -> None:
    """Skip unless nuscenes_pred and its source plugin are available."""
    if not os.path.isdir(os.path.join(default_data_root(), "nuscenes_pred", "label")):
        pytest.skip(f"nuscenes_pred not found under {default_data_root()!r}")
    from trafficrlhf_sdk.plugins import registry

    if "nuscenes_pred" not in registry("scenario_sources"):
        pytest.skip("the nuscenes_pred source plugin is not installed")


@pytest.fixture(scope="module")
def cli():  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.cli import get_cli

    return get_cli()


@pytest.mark.slow
def test_evaluate_constant_velocity_writes_results(has_data, cli, tmp_path) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    result = CliRunner().invoke(
        cli, ["evaluate", "--model", "constant_velocity", "--scenes", "5", "--out", str(out), "--json"]
    )
    assert result.exit_code == 0, (result.output, result.exception)
    assert (out / "results.json").is_file() and (out / "histograms.png").is_file()
    assert (out / "histograms.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    saved = json.loads((out / "results.json").read_text())
    printed = json.loads(result.stdout)  # --json prints the same report on stdout (progress bars go to stderr)
    assert printed["metrics"] == saved["metrics"]
    assert saved["num_scenes"] == 5 and saved["num_controlled_agents"] > 0
    assert saved["metadata"]["model"] == "constant_velocity" and len(saved["metadata"]["scene_ids"]) == 5
    metrics, logged = saved["metrics"], saved["logged"]
    for key in ("failure_rate", "collision_rate", "offroad_rate", "realism_ctg", "realism_body"):
        assert key in metrics and key in logged, key
    assert 0.0 <= metrics["failure_rate"] <= 1.0
    assert logged["realism_ctg"] == 0.0 and logged["realism_body"] == 0.0  # the log against itself
    assert metrics["realism_ctg"] > 0.0
    assert set(saved["histograms"]) == {"ctg", "body"}
    # per scene, in scene_ids order; the reported rates are their means over scenes with a controlled agent
    per_scene = saved["per_scene"]
    assert len(per_scene["failure_rate"]) == 5 and sum(per_scene["controlled_agents"]) == saved["num_controlled_agents"]
    for key in ("failure_rate", "collision_rate", "offroad_rate", "speed_ratio"):
        values = [v for v in per_scene[key] if v is not None]
        assert sum(values) / len(values) == pytest.approx(metrics[key], abs=1e-12), key
    table = CliRunner().invoke(cli, ["evaluate", "--model", "constant_velocity", "--scenes", "5",
                                     "--worst-scenes", "2", "--render-worst", "2", "--out", str(tmp_path / "r")])
    assert table.exit_code == 0, (table.output, table.exception)
    failing = sum(1 for v in per_scene["failure_rate"] if v)
    assert f"failure is spread over {failing} of 5 scenes" in table.output
    assert "the 2 scenes with the largest failure share" in table.output.replace("\n", " ")
    worst = max(range(5), key=lambda i: (per_scene["failure_rate"][i] or 0.0))
    assert saved["metadata"]["scene_ids"][worst] in table.output
    pngs = sorted(p.name for p in (tmp_path / "r" / "worst_scenes").iterdir())
    assert len(pngs) == min(2, failing) and pngs[0].startswith("01_scene-")


def test_render_worst_needs_out(cli) -> None:  # type: ignore[no-untyped-def]
    result = CliRunner().invoke(cli, ["evaluate", "--model", "constant_velocity", "--render-worst", "3"])
    assert result.exit_code != 0
    assert "--render-worst 3" in str(result.exception) and "--out" in str(result.exception)


def test_unknown_model_lists_the_registered_ones(has_data, cli) -> None:  # type: ignore[no-untyped-def]
    result = CliRunner().invoke(cli, ["evaluate", "--model", "nope", "--scenes", "1"])
    assert result.exit_code != 0
    assert isinstance(result.exception, TrafficRLHFError)
    message = str(result.exception)
    assert "'nope'" in message
    for name in ("constant_velocity", "log_replay", "noisy_log"):
        assert name in message


def test_unknown_model_through_the_console_entry_point(has_data, capsys) -> None:  # type: ignore[no-untyped-def]
    """``main`` turns the error into one ``Error:`` line on stderr and exit code 2."""
    from trafficrlhf_sdk.cli import EXIT_USER_ERROR, main

    with pytest.raises(SystemExit) as info:
        main(["evaluate", "--model", "nope", "--scenes", "1"])
    assert info.value.code == EXIT_USER_ERROR
    err = capsys.readouterr().err
    error_lines = [line for line in err.splitlines() if line.startswith("Error:")]
    assert len(error_lines) == 1 and "nope" in error_lines[0] and "constant_velocity" in error_lines[0]


def test_guidance_is_refused_for_a_model_without_it(has_data, cli) -> None:  # type: ignore[no-untyped-def]
    result = CliRunner().invoke(cli, ["evaluate", "--model", "constant_velocity", "--guidance", "x", "--scenes", "1"])
    assert result.exit_code != 0
    assert isinstance(result.exception, TrafficRLHFError)
    message = str(result.exception)
    assert "constant_velocity" in message and "guidance" in message


def test_evaluate_help_mentions_the_protocol(cli) -> None:  # type: ignore[no-untyped-def]
    result = CliRunner().invoke(cli, ["evaluate", "--help"])
    assert result.exit_code == 0
    for option in ("--model", "--scenes", "--out", "--json", "--guidance"):
        assert option in result.output


def test_scene_id_picks_scenes_and_names_a_wrong_one(has_data, cli, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk import get_scenario_source

    ids = get_scenario_source("nuscenes_pred").scene_ids("val")
    result = CliRunner().invoke(cli, ["evaluate", "--model", "constant_velocity", "--scene-id", ids[7],
                                      "--scene-id", ids[3], "--json"])
    assert result.exit_code == 0, (result.output, result.exception)
    assert json.loads(result.stdout)["metadata"]["scene_ids"] == [ids[7], ids[3]]
    wrong = CliRunner().invoke(cli, ["evaluate", "--model", "constant_velocity", "--scene-id", ids[3] + "x"])
    assert wrong.exit_code != 0
    assert f"--scene-id '{ids[3]}x'" in str(wrong.exception) and ids[3] in str(wrong.exception)


@pytest.mark.slow
def test_seeds_write_one_run_each_and_pool_them(has_data, cli, tmp_path) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "runs"
    result = CliRunner().invoke(cli, ["evaluate", "--model", "noisy_log", "--scenes", "3", "--seeds", "0,1",
                                      "--out", str(out), "--worst-scenes", "2"])
    assert result.exit_code == 0, (result.output, result.exception)
    runs = [json.loads((out / f"seed_{s}" / "results.json").read_text()) for s in (0, 1)]
    assert [r["metadata"]["seed"] for r in runs] == [0, 1]
    rates = [r["metrics"]["failure_rate"] for r in runs]
    mean = sum(rates) / 2
    assert f"| failure rate | {mean:.4f} ({rates[0]:.4f} / {rates[1]:.4f}) |" in result.output
    assert "failure (mean of 2 runs) is spread over" in result.output
    # --json prints the same runs as one object and needs no --out
    printed = CliRunner().invoke(cli, ["evaluate", "--model", "noisy_log", "--scenes", "3", "--seeds", "0,1", "--json"])
    assert printed.exit_code == 0, (printed.output, printed.exception)
    summary = json.loads(printed.output[printed.output.index("{"):])
    assert summary["seeds"] == [0, 1] and [run["metrics"]["failure_rate"] for run in summary["runs"]] == rates
    assert summary["mean"]["failure_rate"] == pytest.approx(mean)
    assert summary["num_scenes"] == 3 and summary["metadata"]["model"] == "noisy_log"


def test_seeds_summary_matches_numpy() -> None:
    from trafficrlhf_sdk.evaluation.protocol import seeds_summary

    rates, realism = [0.1, 0.25, 0.16], [0.05, 0.07, 0.06]
    results = [{"metrics": {"failure_rate": rate, "realism_ctg": value, "reward_cost": None},
                "logged": {"failure_rate": 0.01}, "metadata": {"seed": seed, "model": "m"},
                "num_scenes": 4, "num_controlled_agents": 9}
               for seed, rate, value in zip((3, 5, 7), rates, realism)]
    summary = seeds_summary(results)
    assert summary["seeds"] == [3, 5, 7] and summary["logged"] == {"failure_rate": 0.01}
    assert set(summary["mean"]) == {"failure_rate", "realism_ctg"}  # a metric some run lacks is left out
    assert summary["mean"]["failure_rate"] == pytest.approx(np.mean(rates))
    assert summary["std"]["realism_ctg"] == pytest.approx(np.std(realism))
    assert summary["metadata"] == {"model": "m"} and json.dumps(summary)


def test_seeds_errors_come_before_any_work(cli, tmp_path) -> None:  # type: ignore[no-untyped-def]
    for args, expected in ((["--seeds", "0,x", "--out", str(tmp_path)], "distinct comma-separated integers"),
                           (["--seeds", "1,1", "--out", str(tmp_path)], "distinct comma-separated integers"),
                           (["--seeds", "0,1"], "add --out DIR")):
        result = CliRunner().invoke(cli, ["evaluate", "--model", "constant_velocity", *args])
        assert result.exit_code != 0 and expected in str(result.exception), (args, result.exception)
    assert not any(tmp_path.iterdir())


def test_model_options_reach_the_model_and_unknown_ones_are_named(has_data, cli) -> None:  # type: ignore[no-untyped-def]
    # noisy_log with no position noise replays the log: its failure rate is the log's own
    result = CliRunner().invoke(cli, ["evaluate", "--model", "noisy_log", "--scenes", "2", "--json",
                                      "--model-option", "position_noise_m=0"])
    assert result.exit_code == 0, (result.output, result.exception)
    report = json.loads(result.output[result.output.index("{"):])
    assert report["metadata"]["model_options"] == {"position_noise_m": 0}
    assert report["metrics"]["failure_rate"] == pytest.approx(report["logged"]["failure_rate"])
    wrong = CliRunner().invoke(cli, ["evaluate", "--model", "noisy_log", "--scenes", "1",
                                     "--model-option", "noise=2"])
    assert isinstance(wrong.exception, TrafficRLHFError)
    assert "'noise'" in str(wrong.exception) and "position_noise_m" in str(wrong.exception)


def test_compare_interval_reads_the_saved_realism_histograms(has_data, cli, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.evaluation.protocol import load_scene_histograms
    from trafficrlhf_sdk.evaluation.breakdown import realism_deviation_draws

    folders, reported = [], {}
    for model in ("constant_velocity", "noisy_log"):
        result = CliRunner().invoke(cli, ["evaluate", "--model", model, "--scenes", "4", "--seeds", "0,1",
                                          "--out", str(tmp_path / model)])
        assert result.exit_code == 0, (result.output, result.exception)
        runs = [json.loads((tmp_path / model / f"seed_{s}" / "results.json").read_text()) for s in (0, 1)]
        for s, run in enumerate(runs):
            counts = load_scene_histograms(str(tmp_path / model / f"seed_{s}" / "scene_histograms.npz"))
            for preset in ("ctg", "body"):
                assert counts[preset]["jerk"]["simulated"].shape == (4, 20)
                everything = realism_deviation_draws(counts[preset], np.ones((1, 4)))[0]
                assert everything == pytest.approx(run["metrics"][f"realism_{preset}"], abs=1e-12)
        reported[model] = {p: np.mean([r["metrics"][f"realism_{p}"] for r in runs]) for p in ("ctg", "body")}
        folders += [str(tmp_path / model / f"seed_{s}") for s in (0, 1)]
    out = CliRunner().invoke(cli, ["compare", *folders, "--interval"])
    assert out.exit_code == 0, (out.output, out.exception)
    for preset in ("ctg", "body"):  # the bootstrap's full-sample point is the deviation evaluate reported
        before, after = reported["constant_velocity"][preset], reported["noisy_log"][preset]
        assert f"| realism dev. ({preset}) | {before:.4f} | {after:.4f} | {100 * (after / before - 1):+.1f} % |" \
            in out.output
