"""``trafficrlhf evaluate``: closed-loop evaluation of a traffic model on logged scenes."""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING

import click

from trafficrlhf_sdk.cli.app import cli, parse_key_values, ray_options
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.evaluation.compare import SHARED_ROWS

if TYPE_CHECKING:
    from rich.console import Console

    from trafficrlhf_sdk.evaluation.runs import EvaluationOutcome

ROWS = (
    ("failure_rate", "failure rate (any)"),
    ("collision_rate", "  collision"),
    ("collision_rate_own", "    with an agent it drives"),
    ("collision_rate_replayed", "    with a replayed agent"),
    ("offroad_rate", "  off-road (centre)"),
    ("failure_rate_turning", "  agents turning in the log"),
    ("failure_rate_straight", "  agents driving straight"),
    ("failure_rate_corners", "failure rate (box corners)"),
    ("realism_ctg", "realism deviation, ctg"),
    ("realism_ctg_lon_acc", "  lon. acceleration"),
    ("realism_ctg_lat_acc", "  lat. acceleration"),
    ("realism_ctg_jerk", "  jerk"),
    ("realism_ctg_speed", "  speed (m/s; not in the mean)"),
    ("realism_body", "realism deviation, body"),
    ("realism_body_lon_acc", "  lon. acceleration"),
    ("realism_body_lat_acc", "  lat. acceleration"),
    ("realism_body_jerk", "  jerk"),
    ("realism_body_speed", "  speed (m/s; not in the mean)"),
) + SHARED_ROWS


def _fmt(value: float | None) -> str:
    return "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.4f}"


@cli.command("evaluate")
@click.option("--model", "model", default=None,
              help="Registered traffic model or built-in policy (see `trafficrlhf plugins`) [default: the one "
                   "--checkpoint was saved by].")
@click.option("--source", default="nuscenes_pred", show_default=True, help="Registered scenario source.")
@click.option("--split", default="val", show_default=True, help="Split of the source.")
@click.option("--root", default=None, help="Data directory of the source (default: ../shared/data/...).")
@click.option("--scenes", "num_scenes", type=click.IntRange(min=1), default=100, show_default=True,
              help="First N long-enough scenes of the split, sorted by name.")
@click.option("--scene-id", "scene_id", multiple=True,
              help="Evaluate only this scene (repeatable), e.g. one that `--worst-scenes` listed; overrides --scenes.")
@click.option("--guidance", default=None,
              help="Guidance name(s), comma separated, for models that support it [default: none, or the guidance a "
                   "bundled checkpoint's card was measured with; `none` turns that off].")
@click.option("--checkpoint", default=None,
              help="Weights: a folder, or a bundled checkpoint's name such as ctg-aligned (`trafficrlhf plugins`).")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("--seeds", "seed_list", default=None,
              help="Comma-separated seeds, e.g. 0,1,2,3,4,5: one run per seed (in --out/seed_S), then their mean "
                   "and each seed's value (one seed moves a failure rate by several hundredths). Overrides --seed.")
@click.option("--batch-size", type=click.IntRange(min=1), default=50, show_default=True,
              help="Scenes per simulated batch.")
@click.option("--out", "out_dir", default=None, help="Directory for results.json and histograms.png.")
@click.option("--reward-model", "reward_model_dir", default=None,
              help="Saved reward model (`trafficrlhf rm train`): adds the reward-cost metric.")
@click.option("--worst-scenes", type=click.IntRange(min=0), default=0, show_default=True,
              help="Also list the N scenes that carry most of the failure rate (it is a mean over scenes of "
                   "per-scene shares, so a few small scenes can dominate it).")
@click.option("--render-worst", type=click.IntRange(min=0), default=0, show_default=True,
              help="Draw the N scenes with the largest failure share as PNGs in --out/worst_scenes/: the simulated "
                   "run over the log at its first failure.")
@click.option("--model-option", "model_options", multiple=True, metavar="KEY=VALUE",
              help="Traffic-model option (JSON value), repeatable, e.g. stationary_rule=every_replan or "
                   "plan_samples=8 (the adapter's Options class lists them).")
@click.option("--late-agents", type=click.Choice(["drop", "replay"]), default="drop", show_default=True,
              help="Agents that appear in the log after the rollout starts: left out (drop, upstream CTG) or "
                   "replayed from the log as context and collision partners (replay).")
@click.option("--after-log-end", type=click.Choice(["end", "continue"]), default="end", show_default=True,
              help="A driven agent whose logged track ends before the rollout does: removed from the scene from "
                   "then on (end) or driven to the end of the rollout (continue, upstream).")
@click.option("--rollouts", type=click.IntRange(min=1, max=64), default=1, show_default=True,
              help="K rollouts per scene, at most 64 (all are held in memory). K >= 2 adds the realism meta-metric "
                   "(WOSAC style; 8 is the usual K: compare models only at equal K) and pools the other metrics over "
                   "the K rollouts.")
@click.option("--duration", type=click.FloatRange(min=1.0), default=10.0, show_default=True,
              help="Seconds simulated after the 3 s of history, at least 1 (the realism metrics need three samples "
                   "0.5 s apart); scenes shorter than 3 s + DURATION are skipped (and counted). The paper's protocol "
                   "is 10 s; a shorter one makes short scenes usable (e.g. ScenarioNet exports), but its numbers "
                   "compare only with runs of the same duration.")
@ray_options("the (rollout, batch) simulations")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON instead of a table.")
def evaluate_command(model: str | None, source: str, split: str, root: str | None, num_scenes: int,
                     scene_id: tuple[str, ...], guidance: str | None,
                     checkpoint: str | None, seed: int, seed_list: str | None, batch_size: int, out_dir: str | None,
                     reward_model_dir: str | None, worst_scenes: int, render_worst: int, model_options: tuple[str, ...],
                     late_agents: str, after_log_end: str, rollouts: int, duration: float, workers: int,
                     ray_address: str | None, as_json: bool) -> None:
    """Simulate 10 s from logged scenes (replanning at 2 Hz) and report failure rate and realism deviation.

    The same metrics are computed on the logged data of the same scenes, for reference.
    """
    from trafficrlhf_sdk.evaluation.runs import EvaluationRequest, run_evaluation
    from trafficrlhf_sdk.parallel import ExecutionConfig
    from trafficrlhf_sdk.simulation.simulator import SimulationConfig

    seeds = _parse_seeds(seed_list, out_dir, as_json) if seed_list is not None else (seed,)
    request = EvaluationRequest(
        model=model, checkpoint=checkpoint, guidance=guidance,
        model_options=parse_key_values(model_options, "--model-option"), source=source, split=split, root=root,
        num_scenes=num_scenes, scene_ids=scene_id, seeds=seeds, batch_size=batch_size, rollouts=rollouts,
        simulation=SimulationConfig(late_agents=late_agents, after_log_end=after_log_end,  # type: ignore[arg-type]
                                    duration_s=duration),
        reward_model=reward_model_dir, execution=ExecutionConfig(workers=workers, ray_address=ray_address))
    outcome = run_evaluation(request, out_dir, render_worst, log=lambda line: click.echo(line, err=True),
                             seed_folders=seed_list is not None)
    if as_json:
        runs = outcome.runs
        click.echo(json.dumps(runs.summary() if seed_list is not None else runs.reports[0].to_json(), indent=2))
    elif seed_list is not None:
        _print_seeds(outcome.folders, worst_scenes)
    else:
        _print_run(outcome, source, split, duration, rollouts, worst_scenes)


def _print_run(outcome: EvaluationOutcome, source: str, split: str, duration: float, rollouts: int,
               worst_scenes: int) -> None:
    """The run's metrics beside the logged data's, where its failures are, its wall time and the files written."""
    import torch
    from rich.console import Console
    from rich.table import Table

    report = outcome.runs.reports[0]
    table = Table(title=f"{outcome.label} on {source}/{split}: {report.num_scenes} scenes, "
                        f"{report.num_controlled_agents} controlled agents, {duration:g} s closed loop"
                        + (f", {rollouts} rollouts per scene" if rollouts > 1 else ""))
    table.add_column("metric")
    table.add_column(outcome.label, justify="right")
    table.add_column("logged data", justify="right")
    for key, label in ROWS:
        if key in report.values:
            table.add_row(label, _fmt(report.values[key]), _fmt(report.logged_values.get(key)))
    console = Console()
    console.print(table)
    _print_concentration(console, [report.to_json()], worst_scenes)
    console.print(f"wall time {report.wall_time_s:.1f} s (closed loop {report.simulation_time_s:.1f} s) on "
                  f"{torch.get_num_threads()} threads")
    for path in outcome.paths:
        console.print(f"wrote {path}")


def _parse_seeds(text: str, out_dir: str | None, as_json: bool) -> tuple[int, ...]:
    """``--seeds`` as a list of distinct ints; without ``--json`` it needs ``--out`` (the table reads the folders)."""
    try:
        seeds = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        seeds = []
    if not seeds or len(set(seeds)) != len(seeds):
        raise TrafficRLHFError(f"--seeds {text!r}: give distinct comma-separated integers, e.g. --seeds 0,1,2.")
    if not out_dir and not as_json:
        raise TrafficRLHFError(f"--seeds {text} writes one folder per seed under --out, which is not set; "
                               "add --out DIR (or --json to print the runs instead).")
    return tuple(seeds)


def _print_seeds(folders: list[str], worst_scenes: int) -> None:
    """The runs' mean and per-seed values (``trafficrlhf compare``), then where their pooled failures are."""
    from rich.console import Console

    from trafficrlhf_sdk.evaluation.compare import comparison_table, read_results

    click.echo(comparison_table(folders))
    _print_concentration(Console(), [read_results(folder) for folder in folders], worst_scenes)
    click.echo(f"wrote {len(folders)} runs: {', '.join(folders)}")


def _print_concentration(console: Console, results: list[dict], top: int) -> None:
    """One line on how concentrated the failure rate is (pooled over ``results``, runs of the same scenes), and
    the ``top`` scenes carrying most of it."""
    from rich.table import Table

    from trafficrlhf_sdk.evaluation.breakdown import pooled_per_scene, scenes_carrying, worst_scenes

    per_scene = pooled_per_scene(results)
    failing = sum(1 for _, value in per_scene.values() if value > 0)
    pooled = f" (mean of {len(results)} runs)" if len(results) > 1 else ""
    console.print(f"failure{pooled} is spread over {failing} of {len(per_scene)} scenes; "
                  f"{scenes_carrying(per_scene, 0.5)} carry half of it, {scenes_carrying(per_scene, 0.8)} carry 80 %")
    if top == 0:
        return
    metrics = {key: {scene: value for scene, (_, value) in pooled_per_scene(results, key).items()}
               for key in ("collision_rate", "offroad_rate")}
    rows = worst_scenes(per_scene, top)
    table = Table(title=f"the {top} scenes with the largest failure share (share: of the sum over scenes)")
    table.add_column("scene", no_wrap=True, min_width=max((len(row.scene_id) for row in rows), default=5))
    for name in ("agents", "failure", "collision", "off-road", "share", "cumulative"):
        table.add_column(name, justify="right")
    for row in rows:
        table.add_row(row.scene_id, str(row.controlled_agents), f"{row.value:.3f}",
                      f"{metrics['collision_rate'][row.scene_id]:.3f}", f"{metrics['offroad_rate'][row.scene_id]:.3f}",
                      f"{100 * row.share:.1f} %", f"{100 * row.cumulative_share:.1f} %")
    console.print(table)
