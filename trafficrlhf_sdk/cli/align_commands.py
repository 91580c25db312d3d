"""``trafficrlhf align``: fine-tune a registered traffic model against a reward model (stage III)."""

from __future__ import annotations

from typing import Any

import click

from trafficrlhf_sdk.cli.app import cli, parse_key_values, ray_options

__all__ = ["align_command"]


def _comma_list(text: str | None) -> tuple[str, ...] | None:
    """``"a, b,"`` -> ``("a", "b")``; None stays None (AlignConfig validates the names)."""
    return None if text is None else tuple(k.strip() for k in text.split(",") if k.strip())


@cli.command("align")
@click.option("--config", "config_path", default=None, type=click.Path(dir_okay=False, path_type=str),
              help="TOML recipe (model, checkpoint, reward, options, [align] fields); the options below override it.")
@click.option("--model", default=None, help="Registered traffic model [default: the one --checkpoint was saved by].")
@click.option("--checkpoint", default=None, help="Starting weights: a folder or a bundled checkpoint's name.")
@click.option("--reward-model", "reward_spec", default=None,
              help="Reward-model folder (`trafficrlhf rm train`), or builtin:NAME for a hand-written baseline "
                   "(`trafficrlhf plugins` lists them).")
@click.option("--reward-option", "reward_options", multiple=True, metavar="KEY=VALUE",
              help="Keyword argument of a built-in reward (JSON value), repeatable.")
@click.option("--alpha", type=click.FloatRange(min=0), default=None,
              help="Weight of the PPO surrogate [default: the paper's: ctg 0.1, bits 0.5, trafficgen 0.3].")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=str),
              help="Output folder: the aligned model (config.json + model.safetensors), logs/, checkpoints/.")
@click.option("--epochs", type=click.IntRange(min=1), default=None, help="Epochs [default: 70].")
@click.option("--guidance", default=None, help="Guidance used while sampling, e.g. no_collision.")
@click.option("--groups", default=None, help="Comma-separated parameter groups to train [default: all offered].")
@click.option("--model-option", "model_options", multiple=True, metavar="KEY=VALUE",
              help="Traffic-model option while training (JSON value), repeatable.")
@click.option("--scenes", "num_scenes", type=click.IntRange(min=1), default=None,
              help="Use the first N long-enough train scenes [default: all].")
@ray_options("each epoch's samples")
@click.option("--root", default=None, help="Data directory of the source.")
@click.option("--seed", type=int, default=None, help="Seed of every generator [default: 0].")
@click.option("--threads", type=click.IntRange(min=1), default=None, help="torch threads.")
@click.option("--resume", is_flag=True, help="Continue from the newest intact checkpoint in --out (an error when "
              "there is none).")
@click.option("--allow-changes", is_flag=True, help="With --resume, accept settings that differ from the "
              "checkpoint's; the change is recorded with the epoch it applies from.")
@click.option("--quiet", is_flag=True, help="No progress bar or per-epoch tables.")
def align_command(config_path: str | None, model: str | None, checkpoint: str | None, reward_spec: str | None,
                  reward_options: tuple[str, ...], alpha: float | None, out_dir: str, epochs: int | None,
                  guidance: str | None, groups: str | None, model_options: tuple[str, ...], num_scenes: int | None,
                  workers: int, ray_address: str | None, root: str | None, seed: int | None, threads: int | None,
                  resume: bool,
                  allow_changes: bool, quiet: bool) -> None:
    """PPO fine-tuning of a traffic model against a reward model: loss = imitation loss - alpha * PPO surrogate.

    Every AlignConfig field is reachable through --config (the committed models' recipes lie beside them in
    reference_models/). The aligned model lands in --out, so `trafficrlhf evaluate --checkpoint OUT` evaluates it.
    """
    from trafficrlhf_sdk.alignment.recipe import run_recipe
    from trafficrlhf_sdk.parallel import ExecutionConfig

    recipe = _recipe(config_path, model, checkpoint, reward_spec, reward_options, model_options, threads)
    execution = ExecutionConfig(workers=workers, ray_address=ray_address)
    summary = run_recipe(recipe, out_dir, execution=execution if execution.uses_ray else None, alpha=alpha,
                         epochs=epochs, guidance=guidance, groups=_comma_list(groups), num_scenes=num_scenes,
                         root=root, seed=seed, resume=resume or None, resume_allow_changes=allow_changes or None,
                         progress_bar=False if quiet else None)
    click.echo(f"aligned {summary['model']} for {summary['epochs']} epochs in {summary['wall_time_s']:.1f} s on "
               f"{summary['threads']} threads; mean reward {summary['reward_first']:.4f} -> "
               f"{summary['reward_last']:.4f}; saved to {out_dir}")


def _recipe(config_path: str | None, model: str | None, checkpoint: str | None, reward_spec: str | None,
            reward_options: tuple[str, ...], model_options: tuple[str, ...], threads: int | None) -> Any:
    """The recipe of ``--config`` (if any) with the command line's options over it."""
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe
    from trafficrlhf_sdk.errors import TrafficRLHFError

    recipe = (AlignRecipe.load(config_path, model=model, checkpoint=checkpoint, reward_model=reward_spec)
              if config_path else None)
    if reward_spec is None and recipe is None:
        raise TrafficRLHFError("no reward given: pass --reward-model FOLDER (or builtin:NAME), or --config RECIPE.")
    if model is None and checkpoint is None and (recipe is None or (recipe.model is None and not recipe.checkpoint)):
        raise TrafficRLHFError("no traffic model given: pass --model NAME or --checkpoint FOLDER (or --config).")
    base = recipe.model_dump() if recipe is not None else {"reward_model": reward_spec}
    given = {"model": model, "checkpoint": checkpoint, "reward_model": reward_spec, "threads": threads}
    base.update({key: value for key, value in given.items() if value is not None})
    base["reward_options"] = {**base.get("reward_options", {}),
                              **parse_key_values(reward_options, "--reward-option")}
    base["model_options"] = {**base.get("model_options", {}), **parse_key_values(model_options, "--model-option")}
    return AlignRecipe(**base)


def _parse_weights(text: str | None) -> list[float] | None:
    """``"1,2,1"`` -> ``[1.0, 2.0, 1.0]`` (None passes through)."""
    if text is None:
        return None
    try:
        return [float(part) for part in text.split(",")]
    except ValueError:
        raise click.BadParameter(f"got {text!r}; give comma-separated numbers such as 1,1,2.",
                                 param_hint="--weights") from None


@cli.command("average")
@click.argument("checkpoints", nargs=-1, required=True, type=click.Path(file_okay=False))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for the averaged config.json + model.safetensors (+ averaged_from.json).")
@click.option("--weights", default=None, help="One weight per checkpoint, comma-separated (default: equal).")
def average_command(checkpoints: tuple[str, ...], out_dir: str, weights: str | None) -> None:
    """Average the weights of aligned CHECKPOINTS (same model and architecture), e.g. several training seeds.

    The result loads like any checkpoint: `trafficrlhf evaluate --model MODEL --checkpoint OUT`.
    """
    from trafficrlhf_sdk.alignment.averaging import average_checkpoints

    average_checkpoints(checkpoints, out_dir, _parse_weights(weights))
    click.echo(f"averaged {len(checkpoints)} checkpoints into {out_dir}")


@cli.command("extrapolate")
@click.argument("aligned", type=click.Path(file_okay=False))
@click.option("--base", "base_dir", required=True, type=click.Path(file_okay=False),
              help="The checkpoint ALIGNED was fine-tuned from (e.g. the model's bundled checkpoint folder).")
@click.option("--factor", required=True, type=click.FloatRange(min=0),
              help="base + FACTOR x (aligned - base): 1 = ALIGNED, 2 = as far again past it, 0.5 = halfway back.")
@click.option("--add-direction", "directions", multiple=True, nargs=3,
              type=(click.Path(file_okay=False), click.Path(file_okay=False), float),
              metavar="FROM TO WEIGHT",
              help="Also add WEIGHT x (TO - FROM), e.g. the change of a second fine-tuning stage run from ALIGNED "
                   "(repeatable; negative weights subtract).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for config.json + model.safetensors (+ extrapolated_from.json).")
def extrapolate_command(aligned: str, base_dir: str, factor: float,
                        directions: tuple[tuple[str, str, float], ...], out_dir: str) -> None:
    """Move an ALIGNED checkpoint further along the direction alignment took from --base (ExPO).

    Choose --factor on held-out scenes; the result loads like any checkpoint:
    `trafficrlhf evaluate --model MODEL --checkpoint OUT`.
    """
    from trafficrlhf_sdk.alignment.averaging import extrapolate_checkpoint

    extrapolate_checkpoint(base_dir, aligned, out_dir, factor, directions)
    extra = "".join(f" + {w:g} x ({b} - {a})" for a, b, w in directions)
    click.echo(f"wrote base + {factor:g} x (aligned - base){extra} to {out_dir}")
