"""``trafficrlhf compare``: one markdown table from several ``trafficrlhf evaluate --out`` folders."""

from __future__ import annotations

import click

from trafficrlhf_sdk.cli.app import cli


@cli.command("compare")
@click.argument("folders", nargs=-1, required=True)
@click.option("--scene-changes", type=click.IntRange(min=0), default=0, show_default=True,
              help="Also list the N scenes whose failure rate changed most from the first model to the last.")
@click.option("--interval", is_flag=True,
              help="Also print the relative change from the first model to the last in the failure, collision and "
                   "off-road rates and the realism deviations, with a paired bootstrap interval over scenes.")
@click.option("--level", type=click.FloatRange(0.5, 1.0, max_open=True), default=None,
              help="With --interval: the interval's coverage (default 0.95).")
@click.option("--target", type=click.FloatRange(-100.0, 1000.0), default=None,
              help="With --interval: a relative change in percent (e.g. -70); adds the share of bootstrap draws at "
                   "or below it. With --plot: drawn as a line.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None, metavar="PNG",
              help="Also write a PNG of each folder's failure-rate change against its change in speed / logged "
                   "speed, relative to the first folder; folders named alike but for a seed suffix (_s0, _s1) share "
                   "a colour. With --target, its line is drawn.")
@click.option("--speed-band", type=click.FloatRange(0.0, 100.0, min_open=True), default=None, metavar="PERCENT",
              help="With --plot: draw the speed changes of +-PERCENT (the product's limit is 5).")
def compare_command(folders: tuple[str, ...], scene_changes: int, interval: bool, level: float | None,
                    target: float | None, plot_path: str | None, speed_band: float | None) -> None:
    """Print a markdown table comparing the evaluation runs in FOLDERS (each holds a results.json, or is an
    `evaluate --seeds` folder whose seed_<S> runs are read)."""
    if level is not None and not interval:
        raise click.BadParameter(f"--level {level:g} only acts with --interval; add --interval.", param_hint="--level")
    if target is not None and not interval and plot_path is None:
        raise click.BadParameter(f"--target {target:g} only acts with --interval or --plot; add one.",
                                 param_hint="--target")
    if speed_band is not None and plot_path is None:
        raise click.BadParameter(f"--speed-band {speed_band:g} only acts with --plot; add --plot PNG.",
                                 param_hint="--speed-band")
    if plot_path is not None and len(folders) < 2:
        raise click.BadParameter(f"--plot {plot_path} compares folders with the first; pass at least two.",
                                 param_hint="--plot")
    from trafficrlhf_sdk.evaluation.compare import compare_report

    click.echo(compare_report(list(folders), scene_changes, interval, 0.95 if level is None else level,
                              None if target is None else target / 100.0))
    if plot_path is not None:
        from trafficrlhf_sdk.evaluation.compare import tradeoff_plot

        written = tradeoff_plot(list(folders), plot_path, None if target is None else target / 100.0,
                                None if speed_band is None else speed_band / 100.0)
        click.echo(f"wrote {written}")


@cli.command("report")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=str))
@click.option("--run", "runs", multiple=True, required=True, metavar="LABEL=FOLDER",
              help="An evaluation folder (`trafficrlhf evaluate --out`) and its label, repeatable; the base first.")
@click.option("--reward-model", "reward_model_dir", default=None, help="The loop's reward model folder.")
@click.option("--align", "align_dir", default=None, help="The loop's `trafficrlhf align --out` folder.")
@click.option("--title", default="TrafficRLHF loop", show_default=True, help="Title of the report.")
def report_command(out_dir: str, runs: tuple[str, ...], reward_model_dir: str | None, align_dir: str | None,
                   title: str) -> None:
    """Write OUT_DIR/report.md (+ PNGs): reward model, training curve, closed-loop metrics, worst scenes."""
    from trafficrlhf_sdk.evaluation.report import write_report

    pairs = []
    for run in runs:
        label, sep, folder = run.partition("=")
        if not sep or not label or not folder:
            raise click.BadParameter(f"expected LABEL=FOLDER, got {run!r}", param_hint="--run")
        pairs.append((label, folder))
    click.echo(f"wrote {write_report(out_dir, pairs, reward_model_dir, align_dir, title)}")
