"""The ``trafficrlhf`` command line: commands, JSON output and the one-line error policy of ``main``."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from collections.abc import Callable, Iterator

import click
import pytest
from click.testing import CliRunner, Result
from PIL import Image

from trafficrlhf_sdk import __version__
from trafficrlhf_sdk.cli import cli, get_cli, main
from trafficrlhf_sdk.errors import DataNotFoundError
from trafficrlhf_sdk.scenario import SourceConfig

HAS_NUSCENES_PLUGIN = importlib.util.find_spec("trafficrlhf_nuscenes_pred") is not None
needs_plugin = pytest.mark.skipif(not HAS_NUSCENES_PLUGIN, reason="the nuscenes_pred plugin is not installed")
EXECUTABLE = Path(sys.executable).with_name("trafficrlhf")


def invoke(*args: str, env: dict[str, str] | None = None) -> Result:
    """Run the group in-process (click's standalone mode) and return the result."""
    return CliRunner().invoke(get_cli(), list(args), env=env, catch_exceptions=False)


def run_main(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """Run :func:`main` like the console script: exit code, stdout, stderr."""
    with pytest.raises(SystemExit) as exit_info:
        main(list(args))
    captured = capsys.readouterr()
    code = exit_info.value.code
    return (0 if code is None else int(code)), captured.out, captured.err


AddCommand = Callable[[str, Callable[[], None]], None]


@pytest.fixture
def temporary_command() -> Iterator[AddCommand]:
    """Add commands to the group for one test and remove them afterwards."""
    added: list[str] = []

    def add(name: str, body: Callable[[], None]) -> None:
        cli.add_command(click.Command(name, callback=body))
        added.append(name)

    yield add
    for name in added:
        cli.commands.pop(name, None)


# ------------------------------------------------------------------------------------------------ basics
def test_version_and_help() -> None:
    result = invoke("--version")
    assert result.exit_code == 0
    assert result.stdout.strip() == f"trafficrlhf {__version__}"
    result = invoke("--help")
    assert result.exit_code == 0
    for command in ("plugins", "sources", "inspect", "render"):
        assert command in result.stdout


def test_main_returns_zero_for_help(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_main(capsys, "--help")
    assert code == 0 and "Usage: trafficrlhf" in out


@needs_plugin
def test_plugins_json_lists_nuscenes_pred() -> None:
    result = invoke("plugins", "--json")
    assert result.exit_code == 0
    data = json.loads(result.stdout)
    assert "nuscenes_pred" in [row["name"] for row in data["plugins"]]
    assert set(data["registries"]) >= {"scenario_sources", "traffic_models", "metrics",
                                       "reward_model_architectures", "annotation_frontends"}
    sources = {item["name"]: item["plugin"] for item in data["registries"]["scenario_sources"]["components"]}
    assert sources["nuscenes_pred"] == "nuscenes_pred"


@needs_plugin
def test_plugins_table() -> None:
    result = invoke("plugins")
    assert result.exit_code == 0
    assert "Loaded plugins" in result.stdout and "nuscenes_pred" in result.stdout
    assert "scenario source" in result.stdout


@needs_plugin
def test_sources_reports_missing_data_per_source(tmp_path: Path) -> None:
    result = invoke("sources", "--json", env={"TRAFFICRLHF_DATA": str(tmp_path)})
    assert result.exit_code == 0
    row = {r["name"]: r for r in json.loads(result.stdout)}["nuscenes_pred"]
    assert row["plugin"] == "nuscenes_pred"
    assert row["root"] == os.path.join(str(tmp_path), "nuscenes_pred")
    assert row["root_exists"] is False and row["splits"] is None
    assert "not found" in row["error"]
    table = invoke("sources", env={"TRAFFICRLHF_DATA": str(tmp_path)})
    assert table.exit_code == 0 and "missing:" in table.stdout


# ------------------------------------------------------------------------------------------ error policy
@needs_plugin
def test_missing_root_is_one_line_error_in_a_subprocess() -> None:
    if not EXECUTABLE.exists():
        pytest.skip(f"console script not installed at {EXECUTABLE}")
    proc = subprocess.run([str(EXECUTABLE), "inspect", "nuscenes_pred", "--split", "val", "--root", "/nonexistent"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("Error:") and "/nonexistent" in lines[0]
    assert "Traceback" not in proc.stderr and proc.stdout == ""


@needs_plugin
def test_unknown_source_lists_registered_sources(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run_main(capsys, "inspect", "no_such_source", "--split", "val")
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("Error: ")
    assert "no_such_source" in err and "nuscenes_pred" in err


def test_usage_error_keeps_click_message(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_main(capsys, "inspect")
    assert code == 2
    assert "Usage: trafficrlhf inspect" in err and "Missing argument 'SOURCE'" in err
    code, _, err = run_main(capsys, "no-such-command")
    assert code == 2 and "No such command" in err


def test_expected_errors_are_one_line(capsys: pytest.CaptureFixture[str], temporary_command: AddCommand) -> None:
    def sdk_error() -> None:
        raise DataNotFoundError("data not found: looked for '/x/y'.\nSecond line of advice.")

    def validation_error() -> None:
        SourceConfig(dt=-1.0, bogus=1)  # type: ignore[call-arg]

    def os_error() -> None:
        open("/nonexistent/file.txt", encoding="utf-8")

    temporary_command("t-sdk", sdk_error)
    temporary_command("t-pydantic", validation_error)
    temporary_command("t-os", os_error)
    for name, expected in (("t-sdk", "/x/y"), ("t-pydantic", "dt"), ("t-os", "/nonexistent/file.txt")):
        code, _, err = run_main(capsys, name)
        assert code == 2, (name, err)
        assert err.startswith("Error: ") and err.count("\n") == 1, (name, err)
        assert expected in err and "Traceback" not in err
    _, _, err = run_main(capsys, "t-pydantic")
    assert "bogus" in err  # every validation problem is named on the one line


def test_unexpected_error_and_debug_mode(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
                                         temporary_command: AddCommand) -> None:
    def boom() -> None:
        raise RuntimeError("boom")

    temporary_command("t-boom", boom)
    monkeypatch.delenv("TRAFFICRLHF_DEBUG", raising=False)
    code, _, err = run_main(capsys, "t-boom")
    assert code == 1
    assert err == "Error: internal error: RuntimeError: boom (set TRAFFICRLHF_DEBUG=1 for the traceback)\n"
    monkeypatch.setenv("TRAFFICRLHF_DEBUG", "1")
    with pytest.raises(RuntimeError, match="boom"):
        main(["t-boom"])


def test_keyboard_interrupt_exits_130(capsys: pytest.CaptureFixture[str], temporary_command: AddCommand) -> None:
    def interrupted() -> None:
        raise KeyboardInterrupt

    temporary_command("t-interrupt", interrupted)
    code, _, err = run_main(capsys, "t-interrupt")
    assert code == 130 and "Interrupted" in err and "Traceback" not in err


def test_plugin_commands_are_attached_once(monkeypatch: pytest.MonkeyPatch) -> None:
    import trafficrlhf_sdk.cli.app as cli_module

    from trafficrlhf_sdk.plugins import get_plugin_manager

    calls = []
    hook = get_plugin_manager().hook
    monkeypatch.setattr(cli_module, "_plugin_commands_added", False)
    monkeypatch.setattr(hook, "register_commands", lambda cli: calls.append(cli))
    assert get_cli() is cli and get_cli() is cli
    assert calls == [cli]


# ------------------------------------------------------------------------------------------ real data
@needs_plugin
def test_inspect_json(data_root: str) -> None:
    result = invoke("inspect", "nuscenes_pred", "--split", "val", "--scenes", "5", "--json")
    assert result.exit_code == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["scenes"]["loaded"] == 5 and report["scenes"]["long_enough"] >= 5
    assert len(report["scene_ids"]) == 5 and report["scene_ids"] == sorted(report["scene_ids"])
    assert report["agents"]["total"] > 0 and report["agents"]["per_scene_max"] >= report["agents"]["per_scene_mean"]
    assert 0 < report["controlled_agents"]["total"] <= report["agents"]["total"]
    assert report["dt_s"] == [0.1] and report["history_s"]["min"] == pytest.approx(3.0)
    assert report["future_s"]["min"] >= 10.0 - 1e-6
    assert set(report["agent_types"]) == {"VEHICLE"}
    assert 0 < report["mean_speed_mps"] < 30
    table = invoke("inspect", "nuscenes_pred", "--split", "val", "--scenes", "2")
    assert table.exit_code == 0 and "2 loaded of" in table.stdout


@needs_plugin
def test_inspect_ids_and_bad_split(data_root: str, capsys: pytest.CaptureFixture[str]) -> None:
    result = invoke("inspect", "nuscenes_pred", "--split", "val", "--ids")
    ids = result.stdout.split()
    assert ids and ids == sorted(ids) and all(i.startswith("scene-") for i in ids)
    code, _, err = run_main(capsys, "inspect", "nuscenes_pred", "--split", "nope")
    assert code == 2 and "available splits" in err and err.count("\n") == 1


@needs_plugin
def test_render_writes_png(data_root: str, tmp_path: Path) -> None:
    from trafficrlhf_sdk import get_scenario_source

    scene_id = get_scenario_source("nuscenes_pred").scene_ids("val")[0]
    out = tmp_path / "tmp" / "x.png"
    result = invoke("render", "nuscenes_pred", scene_id, "-o", str(out), "--split", "val")
    assert result.exit_code == 0, result.stderr
    assert result.stdout.strip() == str(out)
    assert out.stat().st_size > 10_000
    with Image.open(out) as image:
        assert image.format == "PNG" and min(image.size) > 300


@needs_plugin
def test_render_unknown_scene_and_bad_step(data_root: str, tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_main(capsys, "render", "nuscenes_pred", "scene-9999", "-o", str(tmp_path / "x.png"))
    assert code == 2 and err.count("\n") == 1
    assert "scene-9999" in err and "trafficrlhf inspect nuscenes_pred --split val --ids" in err
    from trafficrlhf_sdk import get_scenario_source

    scene_id = get_scenario_source("nuscenes_pred").scene_ids("val")[0]
    code, _, err = run_main(capsys, "render", "nuscenes_pred", scene_id, "-o", str(tmp_path / "x.png"),
                            "--step", "100000")
    assert code == 2 and "`step` must be in" in err
    assert not (tmp_path / "x.png").exists()


def test_compare_plot_places_each_run_by_its_failure_and_speed_change_from_the_first(tmp_path) -> None:
    """`compare --plot` writes a PNG of failure change against speed change, both relative to the first folder
    (seed runs averaged); draws named alike but for a seed suffix share a group; a base without failures is one
    clear error."""
    import json

    from click.testing import CliRunner
    from PIL import Image

    from trafficrlhf_sdk.cli import get_cli
    from trafficrlhf_sdk.evaluation.compare import SEED_SUFFIX, tradeoff_points

    def write(folder, failure: float, speed: float, seed: int = 0) -> None:  # type: ignore[no-untyped-def]
        folder.mkdir(parents=True)
        (folder / "results.json").write_text(json.dumps({
            "metrics": {"failure_rate": failure, "speed_ratio": speed}, "metadata": {"model": "m", "seed": seed},
            "simulation_time_s": 1.0, "num_scenes": 1, "num_controlled_agents": 2}))

    write(tmp_path / "base" / "seed_0", 0.08, 1.0)
    write(tmp_path / "base" / "seed_1", 0.12, 1.1, seed=1)  # base: failure 0.10, speed 1.05
    write(tmp_path / "recipe_s0", 0.04, 1.05)
    write(tmp_path / "recipe_s1", 0.02, 0.945)
    write(tmp_path / "other", 0.10, 0.84)
    folders = [str(tmp_path / name) for name in ("base", "recipe_s0", "recipe_s1", "other")]
    points = tradeoff_points(folders)
    assert [p[0] for p in points] == ["recipe_s0", "recipe_s1", "other"]
    assert [round(p[1], 6) for p in points] == [-0.6, -0.8, 0.0]
    assert [round(p[2], 6) for p in points] == [0.0, -0.1, -0.2]
    assert {SEED_SUFFIX.sub("", p[0]) for p in points} == {"recipe", "other"}
    png = tmp_path / "tradeoff.png"
    out = CliRunner().invoke(get_cli(), ["compare", *folders, "--plot", str(png), "--target", "-60",
                                         "--speed-band", "5"])
    assert out.exit_code == 0, out.output
    assert Image.open(png).size[0] > 300
    write(tmp_path / "clean", 0.0, 1.0)
    bad = CliRunner().invoke(get_cli(), ["compare", str(tmp_path / "clean"), folders[1], "--plot", str(png)])
    assert bad.exit_code != 0 and "relative changes need both above 0" in str(bad.exception)
    band = CliRunner().invoke(get_cli(), ["compare", *folders, "--speed-band", "5"])
    assert band.exit_code == 2 and "--speed-band 5 only acts with --plot" in band.output
    alone = CliRunner().invoke(get_cli(), ["compare", folders[0], "--plot", str(png)])
    assert alone.exit_code == 2 and "pass at least two" in alone.output


def test_compare_builds_a_table_from_evaluate_runs(tmp_path) -> None:
    """`compare` reads results.json of several runs into one markdown table; a missing folder is one clear error."""
    from click.testing import CliRunner

    from trafficrlhf_sdk.cli import get_cli

    import json

    for name, rate in (("a", 0.25), ("b", 0.5)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps({
            "metrics": {"failure_rate": rate},
            "metadata": {"model": name, "guidance": "no_collision" if name == "b" else None},
            "simulation_time_s": 1.0, "num_scenes": 2, "num_controlled_agents": 3}))
    runner = CliRunner()
    result = runner.invoke(get_cli(), ["compare", str(tmp_path / "a"), str(tmp_path / "b")])
    assert result.exit_code == 0, result.output
    assert "| metric | a | b + no_collision |" in result.output
    assert "| failure rate | 0.2500 | 0.5000 |" in result.output
    missing = runner.invoke(get_cli(), ["compare", str(tmp_path / "nope")])
    assert missing.exit_code != 0
    # the same policy at three seeds shares one column: the mean, then each seed's value
    for seed, rate in ((0, 0.1), (1, 0.2), (2, 0.6)):
        (tmp_path / f"c{seed}").mkdir()
        (tmp_path / f"c{seed}" / "results.json").write_text(json.dumps({
            "metrics": {"failure_rate": rate}, "metadata": {"model": "c", "seed": seed, "scene_ids": ["s1"]},
            "simulation_time_s": 1.0, "num_scenes": 1, "num_controlled_agents": 3}))
    pooled = runner.invoke(get_cli(), ["compare", str(tmp_path / "a"), *(str(tmp_path / f"c{s}") for s in range(3))])
    assert pooled.exit_code == 0, pooled.output
    assert "| metric | a | c, seeds 0 / 1 / 2 |" in pooled.output
    assert "| failure rate | 0.2500 | 0.3000 (0.1000 / 0.2000 / 0.6000) |" in pooled.output
