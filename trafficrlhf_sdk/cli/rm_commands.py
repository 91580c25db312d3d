"""``trafficrlhf rm ...``: train a reward model from preferences, evaluate it, inspect a saved one."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shlex
import sys
from collections.abc import Iterator
from typing import Any

import click

from trafficrlhf_sdk.cli.app import cli, parse_key_values
from trafficrlhf_sdk.errors import TrafficRLHFError

__all__ = ["rm"]


def _echo_metrics(title: str, metrics: dict[str, Any]) -> None:
    click.echo(title)
    for key, value in metrics.items():
        shown = f"{value:.4f}" if isinstance(value, float) else value
        click.echo(f"  {key:<28} {shown}")


def _parse_options(pairs: tuple[str, ...]) -> dict[str, Any]:
    return dict(parse_key_values(pairs, "--architecture-option"))


@cli.group("rm")
def rm() -> None:
    """Reward models (stage II): train r_HF from preferences, evaluate it, inspect a saved one."""


@rm.command("train")
@click.option("--db", "db_path", default=None, help="Feedback database (SQLite) holding the campaign.")
@click.option("--campaign", "campaigns", multiple=True,
              help="Campaign whose labels train the model (with --db); repeat to pool several, e.g. the "
                   "campaigns of successive RLHF rounds.")
@click.option("--data", "data_dir", default=None, help="Instead of --db: a folder from `feedback export`.")
@click.option("--annotator", "annotators", multiple=True, help="Use only this annotator's labels (repeatable).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=str),
              help="Folder for config.json, model.safetensors, README.md and training_log.json.")
@click.option("--val-fraction", type=click.FloatRange(0, 1, max_open=True), default=0.15, show_default=True,
              help="Share of contexts (never pairs) held out for validation and early stopping.")
@click.option("--split-seed", type=int, default=0, show_default=True, help="Seed of the train/val split.")
@click.option("--epochs", type=click.IntRange(min=1), default=None, help="Maximum epochs [default: RewardConfig].")
@click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=None, help="Learning rate.")
@click.option("--weight-decay", type=click.FloatRange(min=0), default=None, help="AdamW weight decay.")
@click.option("--batch-size", type=click.IntRange(min=1), default=None, help="Contexts per optimiser step.")
@click.option("--margin", type=click.FloatRange(min=0), default=None, help="Bradley–Terry margin.")
@click.option("--center-coef", type=click.FloatRange(min=0), default=None, help="Reward-centring coefficient.")
@click.option("--patience", type=click.IntRange(min=1), default=None, help="Early-stopping patience (epochs).")
@click.option("--ensemble", type=click.IntRange(min=1), default=1, show_default=True,
              help="Members of an ensemble (their spread is the uncertainty).")
@click.option("--bootstrap/--no-bootstrap", default=True, show_default=True,
              help="Ensemble members train on contexts drawn with replacement (else all, with other seeds).")
@click.option("--half", is_flag=True, help="Store the weights in float16 (half the size; rounded before testing).")
@click.option("--architecture", default="ctg_mlp", show_default=True, help="Registered architecture.")
@click.option("--architecture-option", "arch_options", multiple=True, metavar="KEY=VALUE",
              help="Architecture option (JSON value), repeatable, e.g. hidden_sizes=[256,32].")
@click.option("--seed", type=int, default=0, show_default=True, help="Training seed.")
@click.option("--threads", type=click.IntRange(min=1), default=None, help="torch threads.")
@click.option("--device", default="cpu", show_default=True,
              help="Where the optimiser steps run: cpu, cuda, cuda:1, ... (featurization stays on the CPU).")
@click.option("--test-campaign", default=None, help="Held-out campaign (same --db) to evaluate and record in the card.")
@click.option("--test-annotator", "test_annotators", multiple=True, help="Its annotator(s), e.g. a noise-free one.")
@click.option("--tie-tolerance", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="Test pairs whose hidden realism differs by at most this count as ties (strict accuracy).")
@click.option("--contrast-scenes", type=click.IntRange(min=1), default=None, metavar="N",
              help="Add contrast items from the last N train scenes' logs: the log and the same future made "
                   "faster, slower, jerky, off its lane, tailgating or weaving, weighed by --contrast-weight. "
                   "Labelled by --contrast-annotator; without one, the log is preferred to each perturbation.")
@click.option("--contrast-annotator", "contrast_annotators", multiple=True, metavar="PROFILE",
              help="Stand-in profile (attentive, safety, flow, hurried) that labels the contrast items as campaign "
                   "items, picking the most realistic option with its own noise (repeatable).")
@click.option("--contrast-weight", type=click.FloatRange(min=0), default=None,
              help="Weight of the contrast pairs' loss [default: RewardConfig].")
@click.option("--title", default=None, help="Title of the model card.")
@click.option("--note", "notes", multiple=True, help="Markdown paragraph added to the model card (repeatable).")
@click.option("--resume", is_flag=True, help="Continue an interrupted run from the newest epoch checkpoint in "
              "--out/checkpoints, with the same options (--epochs may change); the result equals an uninterrupted "
              "run's.")
@click.option("--quiet", is_flag=True, help="No progress bar or per-epoch lines.")
def train_command(db_path: str | None, campaigns: tuple[str, ...], data_dir: str | None, annotators: tuple[str, ...],
                  out_dir: str, val_fraction: float, split_seed: int, epochs: int | None, lr: float | None,
                  weight_decay: float | None,
                  batch_size: int | None, margin: float | None, center_coef: float | None, patience: int | None,
                  ensemble: int, bootstrap: bool, half: bool, architecture: str, arch_options: tuple[str, ...],
                  seed: int, threads: int | None, device: str, test_campaign: str | None,
                  test_annotators: tuple[str, ...], tie_tolerance: float, contrast_scenes: int | None,
                  contrast_annotators: tuple[str, ...], contrast_weight: float | None, title: str | None,
                  notes: tuple[str, ...], resume: bool, quiet: bool) -> None:
    """Train a reward model with the Bradley–Terry loss and save it with its model card.

    Every epoch is checkpointed in OUT/checkpoints (removed when the model is saved): after Ctrl-C, run the same
    command with --resume."""
    from trafficrlhf_sdk.reward import RewardConfig
    from trafficrlhf_sdk.reward.card import train_and_save
    from trafficrlhf_sdk.reward.evaluation import load_preferences
    from trafficrlhf_sdk.reward.model import check_architecture_options

    check_architecture_options(architecture, _parse_options(arch_options))  # before reading any data
    dataset, store = load_preferences(db_path, campaigns, data_dir, annotators, val_fraction, split_seed)
    overrides = {"max_epochs": epochs, "learning_rate": lr, "weight_decay": weight_decay, "batch_size": batch_size,
                 "margin": margin, "center_rewards_coefficient": center_coef, "early_stopping_patience": patience,
                 "contrast_weight": contrast_weight}
    config = RewardConfig(architecture=architecture, architecture_config=_parse_options(arch_options),
                          ensemble_size=ensemble, bootstrap=bootstrap, seed=seed, num_threads=threads,
                          device=device, val_fraction=val_fraction,
                          progress=not quiet, **{k: v for k, v in overrides.items() if v is not None})
    # the command line that made this model, for the card
    commands = ["trafficrlhf " + shlex.join(sys.argv[1:])] if os.path.basename(sys.argv[0]) == "trafficrlhf" else []
    with _resume_hint_on_interrupt(out_dir):
        trained = train_and_save(config, dataset, out_dir, store=store, campaigns=campaigns if db_path else (),
                                 annotators=annotators, contrast_scenes=contrast_scenes, half=half,
                                 contrast_annotators=contrast_annotators, test_campaign=test_campaign,
                                 test_annotators=test_annotators,
                                 tie_tolerance=tie_tolerance, title=title, notes=notes, commands=commands,
                                 log=None if quiet else _echo_epoch, resume=resume,
                                 on_start=lambda info: _echo_start(architecture, info))
    result = trained.result
    _echo_metrics(f"trained in {result.train_seconds:.1f} s (best epochs {result.best_epochs}) -> {out_dir}",
                  trained.card["metrics"])


@contextlib.contextmanager
def _resume_hint_on_interrupt(out_dir: str) -> Iterator[None]:
    """On Ctrl-C, say which epoch checkpoint is kept and how to continue, then let the interrupt through."""
    try:
        yield
    except KeyboardInterrupt:
        from trafficrlhf_sdk.alignment.checkpointing import list_checkpoints
        from trafficrlhf_sdk.reward.card import CHECKPOINTS_FOLDER

        found = list_checkpoints(os.path.join(out_dir, CHECKPOINTS_FOLDER))
        if found:
            click.echo(f"interrupted: {os.path.basename(found[-1])} (epochs done) is kept in "
                       f"{os.path.join(out_dir, CHECKPOINTS_FOLDER)}; run the same command with --resume to "
                       "continue.", err=True)
        raise


def _echo_start(architecture: str, info: dict[str, Any]) -> None:
    click.echo(f"training {architecture} on {info['train_pairs']} pairs / {info['train_contexts']} contexts, "
               f"validating on {info['val_pairs']} pairs / {info['val_contexts']} contexts, "
               f"{info['contrast_pairs']} contrast pairs (featurized in {info['featurize_seconds']:.1f} s)")


def _echo_epoch(row: dict[str, float]) -> None:
    shown = {k: round(v, 4) for k, v in row.items()
             if k.startswith(("train_loss", "train_acc", "val_loss", "val_acc", "val_margin"))}
    click.echo(f"  member {int(row['member'])} epoch {int(row['epoch'])}: {shown} ({row['seconds']:.1f} s)")


@rm.command("eval")
@click.option("--model", "model_dir", required=True, help="Folder of a saved reward model.")
@click.option("--db", "db_path", default=None, help="Feedback database holding the campaign.")
@click.option("--campaign", default=None, help="Campaign whose labels are the test pairs (with --db).")
@click.option("--data", "data_dir", default=None, help="Instead of --db: a folder from `feedback export`.")
@click.option("--annotator", "annotators", multiple=True, help="Use only this annotator's labels (repeatable).")
@click.option("--subset", type=click.Choice(["all", "train", "val"]), default="all", show_default=True,
              help="Contexts to use: of an exported dataset, or (with --db) of the split --val-fraction makes; "
                   "`rm train` with the same --val-fraction/--split-seed never trained on the 'val' ones.")
@click.option("--val-fraction", type=click.FloatRange(0, 1, max_open=True), default=0.0, show_default=True,
              help="With --db: share of contexts marked 'val' (split by scene, as `rm train` does).")
@click.option("--split-seed", type=int, default=0, show_default=True, help="With --db: seed of that split.")
@click.option("--tie-tolerance", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="With --db: pairs whose hidden realism differs by at most this are ties (strict accuracy).")
@click.option("--probes", "probe_scenes", type=click.IntRange(min=1), default=None, metavar="N",
              help="Also probe the model on N held-out val scenes (two windows from each scene long enough): the "
                   "logged future must score above the same future made faster, slower, jerky, off its lane, "
                   "tailgating, weaving or stalling (pass rate per probe and member, over the windows the "
                   "perturbation changes).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def eval_command(model_dir: str, db_path: str | None, campaign: str | None, data_dir: str | None,
                 annotators: tuple[str, ...], subset: str, val_fraction: float, split_seed: int,
                 tie_tolerance: float, probe_scenes: int | None, as_json: bool) -> None:
    """Accuracy (share of pairs with r(S_w) > r(S_l)), margin and rewards on a campaign's preference pairs, and
    the probes on held-out logs (--probes)."""
    from trafficrlhf_sdk.reward import RewardModel
    from trafficrlhf_sdk.reward.evaluation import evaluate_model, load_preferences

    model = RewardModel.from_pretrained(model_dir).eval()
    result: dict[str, Any] = {}
    if db_path is not None or data_dir is not None or probe_scenes is None:
        dataset, store = load_preferences(db_path, campaign, data_dir, annotators, val_fraction, split_seed)
        if subset != "all":
            dataset = dataset.subset(subset)
        result["pairs"] = evaluate_model(model, dataset, store, tie_tolerance)
    if probe_scenes is not None:
        from trafficrlhf_sdk.reward.contrast import probe_reward_model, recorded_windows

        result["probes"] = probe_reward_model(model, recorded_windows("nuscenes_pred", "val", probe_scenes))
    not_finite = _not_finite(result)
    if not_finite:
        raise TrafficRLHFError(f"`rm eval` of {model_dir!r} gave no number for {', '.join(not_finite[:5])} (NaN): "
                               "the test pairs are empty after --subset/--annotator, or the model scores NaN; "
                               "check the selection (`feedback stats`) and the model (`rm info`).")
    if as_json:
        click.echo(json.dumps(result if "probes" in result else result["pairs"], indent=2))
        return
    if "pairs" in result:
        _echo_metrics(f"{model.architecture} from {model_dir} on {campaign or data_dir}", result["pairs"])
    for kind, entry in result.get("probes", {}).items():
        members = " / ".join(f"{rate:.2f}" for rate in entry["members"])
        click.echo(f"  probe {kind:<9} pass {entry['pass_rate']:.3f} on {entry['windows']} windows of "
                   f"{entry['scenes']} scenes"
                   + (f" (members {members})" if members else "") + f", mean gap {entry['mean_gap']:+.4f}")


def _not_finite(result: Any, prefix: str = "") -> list[str]:
    """Keys (dotted) of every float in ``result`` (nested dicts and lists) that is NaN or infinite."""
    if isinstance(result, dict):
        return [k for key, value in result.items() for k in _not_finite(value, f"{prefix}{key}.")]
    if isinstance(result, (list, tuple)):
        return [k for i, value in enumerate(result) for k in _not_finite(value, f"{prefix}{i}.")]
    return [prefix.rstrip(".")] if isinstance(result, float) and not math.isfinite(result) else []


@rm.command("info")
@click.argument("model_dir", required=False)
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def info_command(model_dir: str | None, as_json: bool) -> None:
    """Describe a saved reward model (architecture, size, data, metrics); without MODEL_DIR, list architectures."""
    from trafficrlhf_sdk.reward.card import describe_reward_model
    from trafficrlhf_sdk.reward.model import reward_model_architectures

    if model_dir is None:
        registry = reward_model_architectures()
        rows = [{"architecture": name, "plugin": registry.owner(name)} for name in registry.names()]
        click.echo(json.dumps(rows, indent=2) if as_json else
                   "\n".join(f"{row['architecture']}\t(plugin {row['plugin']})" for row in rows))
        return
    summary = describe_reward_model(model_dir)
    if as_json:
        click.echo(json.dumps(summary, indent=2))
    else:
        config = summary["config"]
        members = config.get("num_members") if summary["architecture"] == "ensemble" else None
        kind = (f"{summary['architecture']} of {members} x {config.get('member_architecture')}" if members
                else summary["architecture"])
        click.echo(f"{model_dir}: {kind} ({'registered' if summary['registered'] else 'NOT registered'}"
                   f"), {summary['num_parameters']:,} parameters, weights "
                   f"{'ok' if summary['weights_sha256_ok'] else 'DO NOT LOAD'}, SDK {summary['sdk_version']}")
        _echo_metrics("data", summary["data"])
        _echo_metrics("metrics", summary["metrics"])
    if "weights_problem" in summary:
        raise TrafficRLHFError(f"reward model {model_dir!r} does not load: {summary['weights_problem']}")
