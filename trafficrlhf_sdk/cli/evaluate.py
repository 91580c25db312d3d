"""``trafficrlhf evaluate``: closed-loop evaluation of a traffic model on logged scenes."""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING

import click

from trafficrlhf_sdk.cli.app import cli, parse_key_values
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.evaluation.compare import SHARED_ROWS

if TYPE_CHECKING:
    from rich.console import Console

    from trafficrlhf_sdk.evaluation.protocol import EvaluationReport

ROWS = (
    ("failure_rate", "failure rate (any)"),
    ("collision_rate", "  collision"),
    ("collision_rate_own", "    with an agent it drives"),
    ("collision_rate_replayed", "    with a replayed agent"),
    ("offroad_rate", "  off-road (centre)"),
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


def _chosen_scenes(available: list[str], wanted: tuple[str, ...], split: str) -> list[str]:
    """``wanted`` in the order given, each checked against the split's long-enough scenes."""
    import difflib

    known = set(available)
    for name in wanted:
        if name not in known:
            close = difflib.get_close_matches(name, available, n=3)
            hint = f" Did you mean {', '.join(close)}?" if close else ""
            raise TrafficRLHFError(f"--scene-id {name!r} is not a long-enough scene of split {split!r} "
                                   f"({len(available)} are; `trafficrlhf inspect` lists them).{hint}")
    return list(dict.fromkeys(wanted))


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
@click.option("--guidance", default=None, help="Guidance name(s), comma separated, for models that support it.")
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
@click.option("--rollouts", type=click.IntRange(min=1), default=1, show_default=True,
              help="K rollouts per scene. K >= 2 adds the realism meta-metric (WOSAC style; 8 is the usual K: compare "
                   "models only at equal K) and pools the other metrics over the K rollouts.")
@click.option("--duration", type=click.FloatRange(min=0.5), default=10.0, show_default=True,
              help="Seconds simulated after the 3 s of history; scenes shorter than 3 s + DURATION are skipped (and "
                   "counted). The paper's protocol is 10 s; a shorter one makes short scenes usable (e.g. ScenarioNet "
                   "exports), but its numbers compare only with runs of the same duration.")
@click.option("--workers", type=click.IntRange(min=0), default=0, show_default=True,
              help="Run the (rollout, batch) simulations on N Ray workers started for the run (pip install "
                   "'trafficrlhf-sdk[ray]'); 0 runs in-process. Same seeds give the same numbers either way.")
@click.option("--ray-address", default=None,
              help="Run on an existing Ray cluster at this address (e.g. auto or HOST:6379) instead of a local one.")
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
    import torch

    from trafficrlhf_sdk import get_scenario_source
    from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, evaluate_policy, seeds_summary
    from trafficrlhf_sdk.parallel import ExecutionConfig
    from trafficrlhf_sdk.plugins import build_policy
    from trafficrlhf_sdk.simulation.simulator import SimulationConfig

    if out_dir is not None:
        _check_out_dir(out_dir)
    if render_worst and not out_dir:
        raise TrafficRLHFError(f"--render-worst {render_worst} writes PNGs under --out, which is not set; add "
                               "--out DIR (or drop --render-worst).")
    seeds = _parse_seeds(seed_list, out_dir, as_json) if seed_list is not None else None
    extra_metrics = []
    if reward_model_dir is not None:  # load before simulating: a bad folder fails at once
        from trafficrlhf_sdk.metrics.reward_cost import RewardCostMetric
        from trafficrlhf_sdk.reward import RewardModel

        extra_metrics.append(RewardCostMetric(RewardModel.from_pretrained(reward_model_dir).step_rewards))
    if seeds:
        seed = seeds[0]
    torch.manual_seed(seed)
    # build the model first: a bad --model/--guidance fails before any data is read
    extra = parse_key_values(model_options, "--model-option")
    policy = build_policy(model, {**extra, "guidance": guidance, "checkpoint": checkpoint, "seed": seed})
    model = model or str(getattr(policy, "name", None) or type(policy).__name__)
    execution = ExecutionConfig(workers=workers, ray_address=ray_address)
    options: dict = {"root": root} if root else {}
    if duration != 10.0:
        options["min_future_s"] = duration
    scenario_source = get_scenario_source(source, **options)
    long_enough = scenario_source.scene_ids(split)
    scene_ids = _chosen_scenes(long_enough, scene_id, split) if scene_id else long_enough[:num_scenes]
    if not scene_ids:
        raise TrafficRLHFError(f"split {split!r} of source {source!r} has no scene long enough for a {duration:g} s "
                               "rollout; try a shorter --duration.")
    _report_short_scenes(scenario_source, split, len(long_enough), duration, as_json)
    if not scene_id and num_scenes > len(scene_ids):
        click.echo(f"note: --scenes {num_scenes} asked for more than the {len(scene_ids)} long-enough scenes of "
                   f"{source}/{split}; evaluating all {len(scene_ids)}.", err=True)
    scenario = scenario_source.load_batch(split, scene_ids=scene_ids, progress=True)
    # a source that lists without reading (a large ScenarioNet folder) can hand over scenes too short: say so
    last = torch.where(scenario.valid.any(1), torch.arange(scenario.num_steps), -1).amax(-1)
    short = last < scenario.current_index + round(duration / scenario.dt)
    if short.any():
        if bool(short.all()):
            raise TrafficRLHFError(f"all {len(scene_ids)} scenes are shorter than 3 s + {duration:g} s; try a shorter "
                                   "--duration.")
        click.echo(f"{int(short.sum())} of {len(scene_ids)} loaded scenes are shorter than 3 s + {duration:g} s and "
                   "are skipped; a shorter --duration keeps them.", err=True)
        scenario = scenario[(~short).nonzero().flatten()]
        scene_ids = [s for s, drop in zip(scene_ids, short.tolist()) if not drop]
    metadata = {"model": model, "source": source, "split": split, "guidance": guidance, "checkpoint": checkpoint,
                "reward_model": reward_model_dir, "model_options": extra, "late_agents": late_agents,
                "after_log_end": after_log_end, "scene_ids": list(scene_ids)}
    simulation = SimulationConfig(late_agents=late_agents, after_log_end=after_log_end,  # type: ignore[arg-type]
                                  duration_s=duration)
    metadata.update(rollouts=rollouts, duration_s=duration)
    if seeds:
        import os

        folders, results = [], []
        for index, run_seed in enumerate(seeds):
            if index:
                torch.manual_seed(run_seed)
                policy = build_policy(model, {**extra, "guidance": guidance, "checkpoint": checkpoint,
                                              "seed": run_seed})
            run = evaluate_policy(policy, scenario, EvaluationConfig(simulation=simulation, batch_size=batch_size,
                                                                   seed=run_seed, rollouts=rollouts),
                                  extra_metrics=extra_metrics, progress=True, metadata=metadata, execution=execution)
            results.append(run.to_json())
            if out_dir:
                folders.append(os.path.join(str(out_dir), f"seed_{run_seed}"))
                run.save(folders[-1])
                if render_worst:
                    _render_worst(run, render_worst, folders[-1])
        if as_json:
            click.echo(json.dumps(seeds_summary(results), indent=2))
        else:
            _print_seeds(folders, worst_scenes)
        return
    config = EvaluationConfig(simulation=simulation, batch_size=batch_size, seed=seed, rollouts=rollouts)
    report = evaluate_policy(policy, scenario, config, extra_metrics=extra_metrics, progress=True, metadata=metadata,
                             execution=execution)
    paths = report.save(out_dir) if out_dir else []
    if render_worst and out_dir:
        paths += _render_worst(report, render_worst, out_dir)
    if as_json:
        click.echo(json.dumps(report.to_json(), indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"{model} on {source}/{split}: {report.num_scenes} scenes, "
                        f"{report.num_controlled_agents} controlled agents, {duration:g} s closed loop"
                        + (f", {rollouts} rollouts per scene" if rollouts > 1 else ""))
    table.add_column("metric")
    table.add_column(model, justify="right")
    table.add_column("logged data", justify="right")
    for key, label in ROWS:
        if key in report.values:
            table.add_row(label, _fmt(report.values[key]), _fmt(report.logged_values.get(key)))
    console = Console()
    console.print(table)
    _print_concentration(console, [report.to_json()], worst_scenes)
    console.print(f"wall time {report.wall_time_s:.1f} s (closed loop {report.simulation_time_s:.1f} s) on "
                  f"{torch.get_num_threads()} threads")
    for path in paths:
        console.print(f"wrote {path}")


def _report_short_scenes(source: object, split: str, usable: int, duration: float, as_json: bool) -> None:
    """Say how many scenes of ``split`` are too short for ``duration`` (never drop them silently)."""
    listed = getattr(source, "all_scene_ids", None)
    if listed is None or as_json:
        return
    total = len(listed(split))
    if total > usable:
        click.echo(f"{total - usable} of {total} scenes of {split!r} are shorter than 3 s + {duration:g} s and are "
                   "skipped; a shorter --duration keeps more of them.", err=True)


def _check_out_dir(out_dir: str) -> None:
    """Refuse an ``--out`` that cannot take the results, before anything is simulated."""
    import os

    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise TrafficRLHFError(f"--out {out_dir!r} is a file, not a folder; pass a folder (it is created if needed).")
    parent = os.path.abspath(out_dir)
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent) or not os.access(parent, os.W_OK | os.X_OK):
        raise TrafficRLHFError(f"--out {out_dir!r} cannot be written ({parent!r} is not a writable folder); pass a "
                               "folder you can write to.")


def _parse_seeds(text: str, out_dir: str | None, as_json: bool) -> list[int]:
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
    return seeds


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


def _render_worst(report: EvaluationReport, top: int, out_dir: str) -> list[str]:
    """PNGs of the ``top`` scenes carrying most of the failure rate, named ``<rank>_<scene>.png``."""
    import os

    from trafficrlhf_sdk.evaluation.failures import first_failures, save_failure_png
    from trafficrlhf_sdk.evaluation.breakdown import pooled_per_scene, worst_scenes

    result, rollout = report.to_json(), report.rollout
    if rollout is None:
        raise ValueError("the report holds no rollout to draw; make it with evaluate_policy.")
    scene_ids = result["metadata"]["scene_ids"]
    failures = first_failures(rollout)
    rows = [row for row in worst_scenes(pooled_per_scene([result]), top) if row.value > 0]
    return [save_failure_png(rollout, scene_ids.index(row.scene_id),
                             os.path.join(out_dir, "worst_scenes", f"{rank:02d}_{row.scene_id}.png"), failures=failures)
            for rank, row in enumerate(rows, start=1)]
