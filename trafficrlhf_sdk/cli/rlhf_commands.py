"""``trafficrlhf rlhf``: iterative RLHF (generate -> label -> reward model -> align, round after round)."""

from __future__ import annotations

import click

from trafficrlhf_sdk.cli.app import cli, ray_options


@cli.command("rlhf")
@click.option("--config", "config_path", default=None, type=click.Path(dir_okay=False, path_type=str),
              help="TOML file of RLHFConfig fields (model, checkpoint, rounds, annotators, reward, align, ...).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=str),
              help="Folder of the run: feedback.sqlite and round_<r>/{campaigns,labels,reward_model,aligned}, each "
                   "step with its step.json; rerun with the same --out to resume.")
@click.option("--rounds", type=click.IntRange(min=1), default=None, help="Rounds [default: the config's, 2].")
@click.option("--overwrite", is_flag=True, help="Run again the steps --out finished with other settings (instead "
                                                "of refusing them).")
@ray_options("the candidates and the alignment's samples")
def rlhf_command(config_path: str | None, out_dir: str, rounds: int | None, overwrite: bool, workers: int,
                 ray_address: str | None) -> None:
    """Rounds of: candidates from the current policy, labels (stand-in annotators or people), a reward model
    retrained on every round's labels, and alignment of the base model against it."""
    from trafficrlhf_sdk.config_files import read_toml

    from pydantic import ValidationError

    from trafficrlhf_sdk.errors import DataFormatError
    from trafficrlhf_sdk.loop import RLHFConfig, rlhf

    fields: dict[str, object] = {}
    if config_path is not None:
        fields = read_toml(config_path)
    if rounds is not None:
        fields["rounds"] = rounds
    if workers or ray_address:
        fields["execution"] = {"workers": workers, "ray_address": ray_address}
    try:
        config = RLHFConfig(**fields)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise DataFormatError(f"--config {config_path!r}: {problems}") from None
    last = rlhf(config, out_dir, log=lambda line: click.echo(line), overwrite=overwrite)["rounds"][-1]
    click.echo(f"done: round {config.rounds - 1}'s reward model {last['reward_model']}, aligned model "
               f"{last['aligned']}")
