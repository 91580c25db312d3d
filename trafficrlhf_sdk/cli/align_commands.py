"""``trafficrlhf align``: fine-tune a registered traffic model against a reward model (stage III)."""

from __future__ import annotations

import json
import os
import time

import click

from trafficrlhf_sdk.cli import cli

__all__ = ["align_command"]

def _comma_list(text: str | None) -> tuple[str, ...] | None:
    """``"a, b,"`` -> ``("a", "b")``; None stays None (AlignConfig validates the names)."""
    return None if text is None else tuple(k.strip() for k in text.split(",") if k.strip())


def _parse_lead(text: str | None) -> tuple[int, int] | None:
    """``"LO,HI"`` -> ``(LO, HI)`` steps (None passes through)."""
    if text is None:
        return None
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        return int(parts[0]), int(parts[1])
    except ValueError:
        raise click.BadParameter(f"got {text!r}; give two step counts LO,HI such as 10,20.",
                                 param_hint="--failure-lead") from None


def _parse_perturb(text: str | None) -> dict[str, float]:
    """``"METRES,RADIANS"`` -> the AlignConfig fields ``perturb_lateral_m`` / ``perturb_yaw_rad`` ({} for None)."""
    if text is None:
        return {}
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        lateral, yaw = float(parts[0]), float(parts[1])
    except ValueError:
        raise click.BadParameter(f"got {text!r}; give a shift in metres and a turn in radians such as 1.0,0.15.",
                                 param_hint="--perturb") from None
    return {"perturb_lateral_m": lateral, "perturb_yaw_rad": yaw}


@cli.command("align")
@click.option("--model", "model", required=True, help="Registered traffic model (see `trafficrlhf plugins`).")
@click.option("--reward-model", "reward_spec", required=True,
              help="Saved reward model folder (`trafficrlhf rm train`), or a built-in reward builtin:NAME "
                   "(`trafficrlhf plugins` lists them; baselines and ablations).")
@click.option("--reward-option", "reward_options", multiple=True, metavar="KEY=VALUE",
              help="Keyword argument of a built-in reward (JSON value), repeatable, e.g. kinematics_weight=1.0.")
@click.option("--alpha", type=click.FloatRange(min=0), default=None,
              help="Weight of the PPO surrogate [default: the paper's value: ctg 0.1, bits 0.5, trafficgen 0.3].")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=str),
              help="Output folder: the aligned model (loadable with `evaluate --checkpoint`), logs/, checkpoints/.")
@click.option("--checkpoint", default=None, help="Starting weights (default: the model's bundled checkpoint).")
@click.option("--epochs", type=click.IntRange(min=1), default=None, help="Epochs [default: AlignConfig, 70].")
@click.option("--contexts", type=click.IntRange(min=1), default=None, help="Contexts per epoch.")
@click.option("--samples", type=click.IntRange(min=2), default=None, help="Samples per context.")
@click.option("--ppo-epochs", type=click.IntRange(min=1), default=None, help="PPO passes per epoch.")
@click.option("--minibatch", type=click.IntRange(min=1), default=None, help="Contexts per optimizer step.")
@click.option("--lr", type=click.FloatRange(min=0), default=None, help="Learning rate.")
@click.option("--lr-schedule", type=click.Choice(["constant", "linear"]), default=None,
              help="Learning rate over the epochs: constant, or linear decay towards 0 [default: constant].")
@click.option("--clip-range", type=click.FloatRange(min=0, min_open=True), default=None, help="PPO clip range.")
@click.option("--kl-coef", type=click.FloatRange(min=0), default=None, help="KL weight to the starting model.")
@click.option("--target-kl", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Early-stop an epoch's PPO passes above 1.5 x this approximate KL.")
@click.option("--imitation-coef", type=click.FloatRange(min=0), default=None, help="Weight of the imitation loss.")
@click.option("--imitation-contexts", type=click.Choice(["rollout", "log"]), default=None,
              help="Windows the imitation loss learns from: the epoch's contexts (rollout, default) or fresh "
                   "windows drawn uniformly from the training log (log).")
@click.option("--winner-coef", type=click.FloatRange(min=0), default=None,
              help="Weight of the imitation loss on each context's best sample (per agent with --credit agent): "
                   "reward-ranked fine-tuning beside PPO [default: 0, off].")
@click.option("--winner-min-gap", type=click.FloatRange(min=0), default=None,
              help="Imitate a best sample only when its reward beats the worst by more than this [default: 0].")
@click.option("--guidance", default=None, help="Guidance used while sampling, e.g. no_collision.")
@click.option("--closed-loop", "closed_loop", type=click.FloatRange(0, 1), default=None,
              help="Share of contexts whose history the current model simulates itself (default 0).")
@click.option("--failure-contexts", "failure_fraction", type=click.FloatRange(0, 1), default=None,
              help="Share of contexts cut just before the current model's own closed-loop failures (default 0).")
@click.option("--perturbed-contexts", "perturb_fraction", type=click.FloatRange(0, 1), default=None,
              help="Share of contexts from the log with the controlled agents' histories shifted and turned off "
                   "their logged paths (default 0).")
@click.option("--perturb", default=None, metavar="METRES,RADIANS",
              help="Largest sideways shift and heading change of a perturbed context [default: 1.0,0.15].")
@click.option("--failure-scenes", type=click.IntRange(min=1), default=None,
              help="Training scenes driven per epoch to find those failures [default: 16].")
@click.option("--failure-refresh", "failure_refresh", type=click.IntRange(min=1), default=None,
              help="Drive the failure scenes every K epochs only; the epochs between reuse that run [default: 1].")
@click.option("--failure-lead", default=None, metavar="LO,HI",
              help="A failure-focused context starts LO..HI steps before the failure [default: 5,15].")
@click.option("--failure-kinds", default=None, metavar="KINDS",
              help="Failures that failure-focused contexts are cut before: collision, offroad or collision,offroad "
                   "[default: collision,offroad].")
@click.option("--credit", type=click.Choice(["scene", "agent"]), default=None,
              help="One advantage per sample (scene, the paper) or per sampled agent (agent) [default: scene].")
@click.option("--counterfactual-credit", is_flag=True,
              help="With --credit agent: score each agent's samples with the other sampled agents held to sample 0.")
@click.option("--selection-credit", is_flag=True,
              help="Credit what the planner executes: each sample's best-of-K return under the adapter's selection "
                   "scores (BITS).")
@click.option("--anchor-coef", type=click.FloatRange(min=0), default=None,
              help="Weight of a KL anchor to the starting model on uniform log contexts sampled each epoch (keeps "
                   "the driving on ordinary roads) [default: 0, off].")
@click.option("--anchor-samples", type=click.IntRange(min=1), default=None,
              help="Futures per anchor context [default: 2].")
@click.option("--passing-anchor-coef", type=click.FloatRange(min=0), default=None,
              help="With --credit agent: weight of a KL anchor to the starting model on the agents none of whose "
                   "samples fails; their advantages become 0 [default: 0, off].")
@click.option("--passing-margins", is_flag=True,
              help="With --passing-anchor-coef: an agent passes only if no sample comes near a failure either.")
@click.option("--reference-checkpoint", type=click.Path(file_okay=False), default=None,
              help="Hold the KL terms (--kl-coef, --anchor-coef, --passing-anchor-coef) to this checkpoint, built "
                   "with the same --model-option values, instead of to --checkpoint (e.g. a second stage anchored "
                   "to the base) [default: the starting model].")
@click.option("--advantage-scale", type=click.Choice(["group", "batch"]), default=None,
              help="Divide centred rewards by each group's std (group) or by one std over the rollout (batch: a "
                   "group pushes as much as its rewards differ) [default: group].")
@click.option("--speed-neutral-advantages", is_flag=True,
              help="Remove from each group's rewards the part explained linearly by the samples' mean speed.")
@click.option("--denoising-steps", type=click.IntRange(min=1), default=None,
              help="Train the surrogate on the first N denoising steps only (diffusion models) [default: all].")
@click.option("--pessimism", type=click.FloatRange(min=0), default=None,
              help="With an ensemble reward model: reward = mean - PESSIMISM x std over its members.")
@click.option("--reward-horizon", type=click.IntRange(min=1), default=None,
              help="Steps each sample is scored over (extended at constant velocity past the model's horizon; "
                   "fewer than the horizon scores the first steps only).")
@click.option("--continuation", "continuation_steps", type=click.IntRange(min=0), default=None, metavar="STEPS",
              help="Score each sample by what follows in closed loop: execute its first --continuation-executed "
                   "steps, then let the current model drive STEPS more (2 Hz replanning) [default: 0, open loop].")
@click.option("--continuation-executed", "continuation_executed", type=click.IntRange(min=1), default=None,
              help="Steps of each sample executed before the continuation [default: 5].")
@click.option("--continuation-weight", type=click.FloatRange(0, 1), default=None,
              help="Share of the continuation's score in the reward (the rest: the open-loop sample's) "
                   "[default: 1].")
@click.option("--log-reference", type=click.Choice(["log", "context"]), default=None,
              help="What rewards that use the log compare with: the logged window, or each context's own "
                   "continuation (how runs before session 11 were trained) [default: log].")
@click.option("--holdout-every", type=click.IntRange(min=2), default=None,
              help="Never train on every k-th scene of the split (a held-out set spread over it; "
                   "scripts/align_dev_eval.py --holdout-every k evaluates them).")
@click.option("--eval-every", type=click.IntRange(min=1), default=None,
              help="Drive the --holdout-every scenes in closed loop every N epochs and log the failure rate.")
@click.option("--eval-seeds", type=click.IntRange(min=1), default=None,
              help="Sampling seeds per held-out evaluation [default: 2].")
@click.option("--keep-best", is_flag=True,
              help="End with the weights of the lowest held-out failure rate (needs --eval-every).")
@click.option("--groups", default=None, help="Comma-separated parameter groups to train (default: all offered).")
@click.option("--model-option", "model_options", multiple=True, metavar="KEY=VALUE",
              help="Traffic-model option while training (JSON value), repeatable, e.g. train_on_selection=true "
                   "for BITS.")
@click.option("--scenes", "num_scenes", type=click.IntRange(min=1), default=None,
              help="Use the first N long-enough train scenes (default: all).")
@click.option("--mirror-scenes", is_flag=True,
              help="Also train on every training scene mirrored (twice the roads; held-out scenes stay as recorded).")
@click.option("--source", default=None, help="Scenario source [default: nuscenes_pred].")
@click.option("--root", default=None, help="Data directory of the source.")
@click.option("--save-every", type=click.IntRange(min=1), default=None, help="Checkpoint every N epochs.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every generator.")
@click.option("--threads", type=click.IntRange(min=1), default=None, help="torch threads.")
@click.option("--resume", is_flag=True, help="Continue from the newest checkpoint in --out.")
@click.option("--quiet", is_flag=True, help="No progress bar or per-epoch tables.")
def align_command(model: str, reward_spec: str, reward_options: tuple[str, ...], alpha: float | None, out_dir: str,
                  checkpoint: str | None,
                  epochs: int | None, contexts: int | None, samples: int | None, ppo_epochs: int | None,
                  minibatch: int | None, lr: float | None, lr_schedule: str | None, clip_range: float | None,
                  kl_coef: float | None,
                  target_kl: float | None, imitation_coef: float | None, imitation_contexts: str | None,
                  winner_coef: float | None,
                  winner_min_gap: float | None, guidance: str | None,
                  closed_loop: float | None, failure_fraction: float | None, perturb_fraction: float | None,
                  perturb: str | None, failure_scenes: int | None,
                  failure_refresh: int | None, failure_lead: str | None, failure_kinds: str | None,
                  credit: str | None, counterfactual_credit: bool, selection_credit: bool,
                  anchor_coef: float | None, anchor_samples: int | None, passing_anchor_coef: float | None,
                  passing_margins: bool, reference_checkpoint: str | None,
                  advantage_scale: str | None, speed_neutral_advantages: bool,
                  denoising_steps: int | None, pessimism: float | None,
                  reward_horizon: int | None, continuation_steps: int | None, continuation_executed: int | None,
                  continuation_weight: float | None, log_reference: str | None, holdout_every: int | None,
                  eval_every: int | None,
                  eval_seeds: int | None, keep_best: bool, groups: str | None,
                  model_options: tuple[str, ...],
                  num_scenes: int | None, mirror_scenes: bool, source: str | None, root: str | None,
                  save_every: int | None, seed: int,
                  threads: int | None, resume: bool, quiet: bool) -> None:
    """PPO fine-tuning of MODEL against a reward model: loss = imitation loss - alpha * PPO surrogate.

    The aligned weights land in --out (config.json + model.safetensors), so
    `trafficrlhf evaluate --model MODEL --checkpoint OUT` evaluates them.
    """
    import torch

    from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer, paper_alpha
    from trafficrlhf_sdk.plugins import build_policy
    from trafficrlhf_sdk.reward.loading import load_reward

    if threads is not None:
        torch.set_num_threads(threads)
    from trafficrlhf_sdk.cli import parse_key_values

    reward = load_reward(reward_spec, parse_key_values(reward_options, "--reward-option"))
    if pessimism is not None:
        from trafficrlhf_sdk.reward.builtin import PessimisticReward

        reward = PessimisticReward(reward, pessimism)

    from trafficrlhf_sdk.errors import TrafficRLHFError

    option_values = parse_key_values(model_options, "--model-option")
    adapter = build_policy(model, {**option_values, "checkpoint": checkpoint, "seed": seed})
    reference = None
    if reference_checkpoint is not None:
        try:
            reference = build_policy(model, {**option_values, "checkpoint": reference_checkpoint, "seed": seed})
        except TrafficRLHFError as err:
            raise TrafficRLHFError(f"--reference-checkpoint {reference_checkpoint!r}: {err}") from err
    if not hasattr(adapter, "parameter_groups"):
        raise TrafficRLHFError(f"{model!r} is not a trainable traffic model (no parameter groups).")
    options = {
        "epochs": epochs, "contexts_per_epoch": contexts, "samples_per_context": samples, "ppo_epochs": ppo_epochs,
        "minibatch_contexts": minibatch, "learning_rate": lr, "lr_schedule": lr_schedule, "clip_range": clip_range,
        "kl_coef": kl_coef,
        "target_kl": target_kl, "imitation_coef": imitation_coef, "imitation_contexts": imitation_contexts,
        "winner_coef": winner_coef,
        "winner_min_gap": winner_min_gap, "guidance": guidance, "num_scenes": num_scenes,
        "closed_loop_fraction": closed_loop, "reward_horizon": reward_horizon, "failure_fraction": failure_fraction,
        "failure_refresh_every": failure_refresh, "failure_scenes": failure_scenes,
        "perturb_fraction": perturb_fraction, **_parse_perturb(perturb),
        "failure_lead_steps": _parse_lead(failure_lead),
        "failure_kinds": _comma_list(failure_kinds), "credit": credit,
        "counterfactual_credit": counterfactual_credit or None, "log_reference": log_reference,
        "selection_credit": selection_credit or None, "speed_neutral_advantages": speed_neutral_advantages or None,
        "advantage_scale": advantage_scale, "anchor_coef": anchor_coef, "anchor_samples": anchor_samples,
        "passing_anchor_coef": passing_anchor_coef, "passing_margins": passing_margins or None,
        "denoising_steps": denoising_steps, "continuation_steps": continuation_steps,
        "continuation_executed_steps": continuation_executed, "continuation_weight": continuation_weight,
        "source": source, "root": root, "save_every": save_every, "holdout_every": holdout_every,
        "eval_every": eval_every, "eval_seeds": eval_seeds, "keep_best": keep_best or None,
        "mirror_scenes": mirror_scenes or None,
        "groups": _comma_list(groups),
    }
    config = AlignConfig(
        alpha=paper_alpha(model) if alpha is None else alpha, seed=seed, output_dir=out_dir, resume=resume,
        progress_bar=not quiet, log_formats=("csv", "tensorboard") if quiet else ("stdout", "csv", "tensorboard"),
        **{k: v for k, v in options.items() if v is not None},
    )
    torch.manual_seed(seed)
    start = time.perf_counter()
    trainer = AlignTrainer(adapter, reward, config, reference=reference)
    history = trainer.train()
    wall = time.perf_counter() - start
    summary = {"model": model, "reward_model": reward_spec, "alpha": config.alpha, "epochs": len(history),
               "groups": list(trainer.group_names), "reference_checkpoint": reference_checkpoint,
               "wall_time_s": wall, "threads": torch.get_num_threads(),
               "reward_first": history[0]["reward_mean"] if history else None,
               "reward_last": history[-1]["reward_mean"] if history else None,
               "best_epoch": trainer.held_out.best_epoch if config.keep_best and trainer.held_out else None}
    with open(os.path.join(out_dir, "align_summary.json"), "w", encoding="utf-8") as handle:
        json.dump(summary, handle, indent=2)
    click.echo(f"aligned {model} for {len(history)} epochs in {wall:.1f} s on {torch.get_num_threads()} threads; "
               f"mean reward {summary['reward_first']:.4f} -> {summary['reward_last']:.4f}; saved to {out_dir}")
    if summary["best_epoch"] is not None:
        best = trainer.held_out.best_failure_rate  # type: ignore[union-attr]
        click.echo(f"kept the weights of epoch {summary['best_epoch']} (held-out failure rate {best:.4f})")


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

    Choose --factor on held-out scenes (scripts/extrapolation_sweep.py); the result loads like any checkpoint:
    `trafficrlhf evaluate --model MODEL --checkpoint OUT`.
    """
    from trafficrlhf_sdk.alignment.averaging import extrapolate_checkpoint

    extrapolate_checkpoint(base_dir, aligned, out_dir, factor, directions)
    extra = "".join(f" + {w:g} x ({b} - {a})" for a, b, w in directions)
    click.echo(f"wrote base + {factor:g} x (aligned - base){extra} to {out_dir}")


@cli.command("graft")
@click.argument("part", type=click.Path(file_okay=False))
@click.option("--body", "body_dir", required=True, type=click.Path(file_okay=False),
              help="The checkpoint that gives every tensor outside --prefix (e.g. a fully fine-tuned model).")
@click.option("--prefix", "prefixes", multiple=True, default=("steer.",), show_default=True,
              help="Tensor-name prefix taken from PART (repeatable).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for config.json (PART's) + model.safetensors (+ grafted_from.json).")
def graft_command(part: str, body_dir: str, prefixes: tuple[str, ...], out_dir: str) -> None:
    """Put PART's module (its tensors under --prefix, e.g. a CTG steering head) onto --body's weights.

    Both must be checkpoints of one adapter and architecture outside the prefix; the result loads like any
    checkpoint: `trafficrlhf evaluate --model MODEL --checkpoint OUT`.
    """
    from trafficrlhf_sdk.alignment.averaging import graft_checkpoint

    graft_checkpoint(body_dir, part, out_dir, prefixes)
    click.echo(f"wrote {body_dir} with the {', '.join(prefixes)} tensors of {part} to {out_dir}")
