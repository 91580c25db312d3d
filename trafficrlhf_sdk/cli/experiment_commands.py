"""``trafficrlhf experiment``: experiments regenerated from the SDK's own stages (``paper``: the paper's tables)."""

from __future__ import annotations

import click

from trafficrlhf_sdk.cli.app import cli, ray_options


@cli.group("experiment")
def experiment_group() -> None:
    """Regenerate published experiments with this SDK."""


@experiment_group.command("paper")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=str),
              help="Folder of the run: <table>/result.{json,md,png}, summary.md, and the evaluations, models, "
                   "campaigns and reward models as pipeline steps; rerun with the same --out to resume.")
@click.option("--quick", is_flag=True, help="The small form CI runs: 4 scenes, one-epoch alignments, tiny feedback "
                                            "and reward models (about 5 min on 2 cores).")
@click.option("--only", default=None, help="Comma-separated subset of table1,table2,table3,table4,figure3 [default: "
                                           "all].")
@click.option("--config", "config_path", default=None, type=click.Path(dir_okay=False, path_type=str),
              help="TOML file of PaperConfig fields (scenes, rollouts, recipes, feedback sizes, ...); --quick starts "
                   "from the small form.")
@click.option("--scenes", type=click.IntRange(min=1), default=None, help="Val scenes [default: 100; --quick: 4].")
@click.option("--threads", type=click.IntRange(min=1), default=None, help="torch threads [default: torch's].")
@click.option("--overwrite", is_flag=True, help="Run again the steps --out finished with other settings (instead "
                                                "of refusing them).")
@ray_options("the evaluations' rollouts, the campaigns' candidates and a table's alignments (side by side, one per "
             "worker, on the worker's one thread)",
             numbers="The numbers are those of an in-process run with --threads 1.")
def paper_command(out_dir: str, quick: bool, only: str | None, config_path: str | None, scenes: int | None,
                  threads: int | None, overwrite: bool, workers: int, ray_address: str | None) -> None:
    """Tables 1-4 and Figure 3 of the paper (arXiv 2309.00709) on nuScenes val scenes, with stand-in annotators
    and learned reward models: markdown, JSON and PNG per table, with commands, seeds and wall times."""
    from trafficrlhf_sdk.config_files import read_toml

    from pydantic import ValidationError

    from trafficrlhf_sdk.errors import DataFormatError
    from trafficrlhf_sdk.experiments.paper import TABLES, PaperConfig, run_paper

    fields: dict[str, object] = {}
    if config_path is not None:
        fields = read_toml(config_path)
    if only is not None:
        names = [part.strip() for part in only.split(",") if part.strip()]
        unknown = [n for n in names if n not in TABLES]
        if unknown or not names:
            raise click.BadParameter(f"{only!r}: use some of {', '.join(TABLES)}, comma-separated.",
                                     param_hint="--only")
        fields["only"] = tuple(names)
    for key, value in (("scenes", scenes), ("threads", threads)):
        if value is not None:
            fields[key] = value
    if workers or ray_address:
        fields["execution"] = {"workers": workers, "ray_address": ray_address}
    try:
        config = PaperConfig.quick(**fields) if quick else PaperConfig(**fields)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise DataFormatError(f"experiment paper: {problems}") from None
    outcome = run_paper(config, out_dir, log=lambda line: click.echo(line), overwrite=overwrite)
    click.echo(f"wrote {len(outcome['results'])} result(s) under {out_dir} in {outcome['wall_time_s']:.0f} s")


@experiment_group.command("ladder")
@click.option("--model", default=None,
              help="The model whose shipped ladder recipe (docs/recipes/<model>-ladder.toml) every row runs "
                   "[default: ctg, unless --config names a recipe].")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=str),
              help="Folder of the run: ladder.{md,json,png} and every step (feedback, reward model, rows, "
                   "evaluations); rerun with the same --out to resume.")
@click.option("--config", "config_path", default=None, type=click.Path(dir_okay=False, path_type=str),
              help="TOML file of LadderConfig fields (recipe, feedback sizes, reward settings, scenes, seeds).")
@click.option("--reward-model", default=None, help="A learned reward-model folder for rows (c) and (d) instead of "
                                                   "training one on stand-in labels.")
@click.option("--overwrite", is_flag=True, help="Run again the steps --out finished with other settings.")
@ray_options("the rows' alignments side by side (one per worker), the evaluations' rollouts and the campaigns' "
             "candidates", numbers="Each alignment on a worker runs on one thread: the numbers of an in-process "
             "run with OMP_NUM_THREADS=1.")
def ladder_command(model: str | None, out_dir: str, config_path: str | None, reward_model: str | None,
                   overwrite: bool, workers: int, ray_address: str | None) -> None:
    """The alignment ladder: one model and fine-tuning recipe, rewarded by (a) the built-in failure reward, (b) the
    stand-in's judgment, (c) a reward model learned from its labels, (d) (c) with alpha = 0; each row evaluated in
    closed loop, so the gap each link of the feedback chain loses is measured."""
    from trafficrlhf_sdk.config_files import load_config, read_toml
    from trafficrlhf_sdk.experiments.ladder import LadderConfig, run_ladder

    fields: dict[str, object] = {}
    own = read_toml(config_path, "--config").get("recipe") if config_path is not None else None
    if own is None:
        fields["recipe"] = f"docs/recipes/{model or 'ctg'}-ladder.toml"
    elif model is not None:
        raise click.UsageError(f"--model {model} and --config {config_path!r} (recipe = {own!r}) both choose the "
                               "recipe; drop --model to run the config's recipe, or remove the config's `recipe` line.")
    if reward_model is not None:
        fields["reward_model"] = reward_model
    config = (load_config(LadderConfig, config_path, **fields) if config_path is not None
              else LadderConfig(**fields))  # type: ignore[arg-type]
    from trafficrlhf_sdk.parallel import ExecutionConfig

    execution = ExecutionConfig(workers=workers, ray_address=ray_address)
    rows = run_ladder(config, out_dir, log=lambda line: click.echo(line), overwrite=overwrite, execution=execution)
    click.echo(f"wrote {out_dir}/ladder.md ({len(rows) - ('agreement' in rows)} rows)")
