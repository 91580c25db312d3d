"""A reward model's card and its whole training run: train from preferences, test, write the folder.

``trafficrlhf rm train`` is :func:`train_and_save` plus printing; ``rm info`` is :func:`describe_reward_model`.
The card (``metrics``, ``data``, ``title``, ``notes``, ``commands``) goes into ``config.json`` and ``README.md``
through :meth:`RewardModel.save_pretrained`.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from trafficrlhf_sdk.errors import TrafficRLHFError

__all__ = ["CHECKPOINTS_FOLDER", "TrainedRewardModel", "describe_reward_model", "model_card", "train_and_save"]

CHECKPOINTS_FOLDER = "checkpoints"  # inside the output folder, while a training run is unfinished


def model_card(metrics: dict[str, Any], model: Any, *, dataset: Any = None, campaigns: Sequence[str] = (),
               annotators: Sequence[str] = (), test_metrics: dict[str, Any] | None = None,
               test_campaign: str | None = None, test_annotators: Sequence[str] = (), title: str | None = None,
               notes: Sequence[str] = (), commands: Sequence[str] = ()) -> dict[str, Any]:
    """The card of a trained reward model.

    Args:
        metrics: the training metrics (``TrainingResult.metrics``).
        model: the trained :class:`RewardModel` (its ``card_info["data"]`` is the base of ``data``).
        dataset: the training :class:`PreferenceDataset`, when it came from ``campaigns`` of a database: its
            scenes are recorded.
        campaigns, annotators: the campaigns and annotators (all when empty) whose labels trained it.
        test_metrics: metrics on a held-out campaign, recorded as ``test_<name>``.
        test_campaign, test_annotators: that campaign and its annotators.
        title, notes: the card's title and Markdown paragraphs.
        commands: the command lines that made the model.
    """
    card: dict[str, Any] = {"metrics": dict(metrics)}
    base = dict(model.card_info.get("data", {}))
    if test_metrics is not None:
        card["metrics"].update({f"test_{k}": v for k, v in test_metrics.items()})
        card["data"] = {**base, "test_campaign": test_campaign, "test_annotators": list(test_annotators) or "all"}
    if campaigns:
        card.setdefault("data", base)
        card["data"].update({"campaign": campaigns[0] if len(campaigns) == 1 else list(campaigns),
                             "annotators": list(annotators) or "all"})
        if dataset is not None:
            card["data"]["scenes"] = sorted({f"{k['source']}/{k['split']}" for k in dataset.context_keys})
    if title:
        card["title"] = title
    if notes:
        card["notes"] = "\n\n".join(notes)
    if commands:
        card["commands"] = list(commands)
    return card


@dataclass
class TrainedRewardModel:
    """What :func:`train_and_save` made: the model, its training result and card, and where it lies."""

    model: Any
    result: Any
    card: dict[str, Any]
    out_dir: str
    dataset_info: dict[str, Any] = field(default_factory=dict)
    probes: dict[str, Any] | None = None


def train_and_save(config: Any, dataset: Any, out_dir: str, *, store: Any = None, campaigns: Sequence[str] = (),
                   annotators: Sequence[str] = (), contrast_scenes: int | None = None,
                   contrast_annotators: Sequence[str] = (), contrast_kinds: Sequence[str] | None = None,
                   half: bool = False,
                   test_campaign: str | None = None, test_annotators: Sequence[str] = (), tie_tolerance: float = 0.0,
                   title: str | None = None, notes: Sequence[str] = (), commands: Sequence[str] = (),
                   log: Callable[[dict[str, float]], None] | None = None,
                   on_start: Callable[[dict[str, Any]], None] | None = None, source: str | None = None,
                   root: str | None = None, future_steps: int = 40, probe_scenes: int = 0,
                   probe_judges: Sequence[str] = (), resume: bool | None = False) -> TrainedRewardModel:
    """Train a reward model on ``dataset`` with ``config`` (a :class:`RewardConfig`), test it on a held-out
    campaign, and write ``out_dir``: ``config.json`` + ``model.safetensors`` + ``README.md`` (the card) and
    ``training_log.json``.

    ``store`` is the feedback database ``campaigns`` come from (needed by ``test_campaign``, read from the same
    database). ``contrast_scenes`` N adds contrast items from the last N train scenes' logs, labelled by the
    stand-in profiles named in ``contrast_annotators`` (:data:`~trafficrlhf_sdk.feedback.synthetic.PROFILES`),
    or, when none is named, as "log ≻ perturbation" (:func:`~trafficrlhf_sdk.reward.contrast.contrast_dataset`),
    each log against its copies perturbed as ``contrast_kinds`` say (None: the default
    :data:`~trafficrlhf_sdk.reward.contrast.CONTRAST_KINDS`). ``half`` stores
    float16 weights, rounded before testing so the card's test metrics are those of the saved weights.
    ``on_start`` hears the trainer's ``dataset_info`` (pairs, contexts, featurizing time) before training;
    ``log`` hears each epoch's row.

    The recorded driving comes from scenario source ``source`` (default: the dataset's) in data directory
    ``root``: contrast windows of ``future_steps`` steps, and with ``probe_scenes`` N the probes on N val scenes
    (:func:`~trafficrlhf_sdk.reward.contrast.probe_reward_model`), recorded in the card as ``probe_<kind>`` (the
    pass rate) and returned as ``probes``. ``probe_judges`` names stand-in profiles whose own noise-free judgment
    takes the same probes (``judges`` in each kind's entry, ``probe_<kind>_judges`` in the card: their mean pass
    rate), so a weak probe tells a reward model that missed what its annotators see from annotators that do not
    see it.

    Every epoch is checkpointed in ``out_dir/checkpoints`` (removed once the model is saved); ``resume`` continues
    an interrupted run from there, with the same final weights as an uninterrupted one. ``resume=None`` continues
    when checkpoints are there and starts otherwise (for pipeline steps, whose inputs already match the run's);
    ``False`` refuses a folder holding checkpoints rather than overwrite them.
    """
    import torch

    from trafficrlhf_sdk.reward.evaluation import evaluate_model, load_preferences
    from trafficrlhf_sdk.reward.trainer import RewardTrainer

    if test_campaign is not None and store is None:
        raise TrafficRLHFError(f"--test-campaign {test_campaign!r} needs --db (the campaign is read from the same "
                               "database); pass the database the training campaigns come from.")
    from trafficrlhf_sdk.reward.contrast import CONTRAST_KINDS, contrast_dataset, probe_reward_model, recorded_windows

    if source is None and (contrast_scenes or probe_scenes):
        source = str(dataset.context_keys[0].get("source") or "nuscenes_pred")
    from trafficrlhf_sdk.feedback.synthetic import PROFILES

    unknown = sorted(set(contrast_annotators) - set(PROFILES))
    if unknown:
        raise TrafficRLHFError(f"--contrast-annotator {unknown}: not stand-in profiles; use some of "
                               f"{', '.join(PROFILES)}.")
    unknown = sorted(set(probe_judges) - set(PROFILES))
    if unknown:
        raise TrafficRLHFError(f"`probe_judges` {unknown}: not stand-in profiles; use some of "
                               f"{', '.join(PROFILES)}.")
    if contrast_annotators and not contrast_scenes:
        raise TrafficRLHFError(f"--contrast-annotator {list(contrast_annotators)} labels contrast items, but there "
                               "are none; add --contrast-scenes N (recorded train scenes that give the items).")
    contrast = None
    if contrast_scenes:
        judges = {name: PROFILES[name] for name in contrast_annotators} or None
        contrast = contrast_dataset(recorded_windows(source, "train", contrast_scenes, root, from_end=True,
                                                     future_steps=future_steps),
                                    kinds=CONTRAST_KINDS if contrast_kinds is None else tuple(contrast_kinds),
                                    annotators=judges)
    checkpoints = os.path.join(out_dir, CHECKPOINTS_FOLDER)
    if resume is None:
        from trafficrlhf_sdk.alignment.checkpointing import list_checkpoints

        resume = bool(list_checkpoints(checkpoints))
    trainer = RewardTrainer(config, train_dataset=dataset, log=log, contrast_dataset=contrast,
                            checkpoint_dir=checkpoints)
    info = {**trainer.dataset_info, "featurize_seconds": trainer.featurize_seconds}
    if on_start is not None:
        on_start(info)
    result = trainer.train(resume=resume)
    model = result.model
    if half:  # round to float16 now, so the test metrics below are those of the weights that are saved
        model.half().float()
    test_metrics = None
    if test_campaign is not None:
        test, _ = load_preferences(store.path, test_campaign, None, test_annotators)
        test_metrics = evaluate_model(model, test, store, tie_tolerance)
    card = model_card(result.metrics, model, dataset=dataset if campaigns else None, campaigns=campaigns,
                      annotators=annotators, test_metrics=test_metrics, test_campaign=test_campaign,
                      test_annotators=test_annotators, title=title, notes=notes, commands=commands)
    if contrast is not None:
        card.setdefault("data", {})["contrast"] = {
            "scenes": contrast_scenes, "pairs": int(contrast.pairs.shape[0]),
            "kinds": list(contrast.metadata["kinds"]),
            "decided_by": list(contrast_annotators) or "the log wins every pair"}
    probes = None
    if probe_scenes:
        windows = recorded_windows(source, "val", probe_scenes, root)
        probes = probe_reward_model(model.eval(), windows)
        card["metrics"].update({f"probe_{kind}": entry["pass_rate"] for kind, entry in probes.items()})
        if probe_judges:
            from trafficrlhf_sdk.reward.oracle import JudgmentReward

            judged = [probe_reward_model(JudgmentReward(name), windows) for name in probe_judges]
            for kind, entry in probes.items():
                entry["judges"] = sum(j[kind]["pass_rate"] for j in judged) / len(judged)
                card["metrics"][f"probe_{kind}_judges"] = entry["judges"]
    model.save_pretrained(out_dir, card, dtype=torch.float16 if half else None)
    with open(os.path.join(out_dir, "training_log.json"), "w", encoding="utf-8") as handle:
        json.dump({"history": result.history, "best_epochs": result.best_epochs,
                   "train_seconds": result.train_seconds, "featurize_seconds": result.featurize_seconds}, handle,
                  indent=2)
    shutil.rmtree(checkpoints, ignore_errors=True)  # the run is complete: nothing left to resume
    return TrainedRewardModel(model, result, card, out_dir, info, probes)


def describe_reward_model(model_dir: str) -> dict[str, Any]:
    """What ``rm info`` reports on a saved reward model: ``path``, ``architecture``, ``registered``,
    ``num_parameters``, ``weights_sha256_ok``, ``sdk_version``, ``config``, ``data`` and ``metrics``, plus
    ``weights_problem`` (one line) when it does not load.

    "ok" means it loads: SHA-256, tensor names, shapes and dtypes, finite values. When the plugin that builds the
    architecture is missing, only the weights file and its SHA-256 are checked."""
    from trafficrlhf_sdk.models.checkpoint import sha256_file
    from trafficrlhf_sdk.reward.model import load_reward_model, reward_model_architectures
    from trafficrlhf_sdk.reward.serialization import read_config
    from trafficrlhf_sdk.scenario.io import safe_load_file

    registry = reward_model_architectures()
    config = read_config(model_dir)
    problem = None
    try:
        if config["architecture"] in registry:
            load_reward_model(model_dir)
        else:
            weights = os.path.join(model_dir, str(config.get("weights", {}).get("file", "model.safetensors")))
            safe_load_file(weights)
            if sha256_file(weights) != config.get("weights", {}).get("sha256"):
                problem = f"{weights!r} does not match the SHA-256 recorded in config.json"
    except TrafficRLHFError as exc:
        problem = " ".join(str(exc).split())
    summary = {"path": model_dir, "architecture": config["architecture"],
               "registered": config["architecture"] in registry, "num_parameters": config.get("num_parameters"),
               "weights_sha256_ok": problem is None, "sdk_version": config.get("sdk_version"),
               "config": config["config"], "data": {k: v for k, v in config.get("data", {}).items() if k != "metadata"},
               "metrics": config.get("metrics", {})}
    if problem is not None:
        summary["weights_problem"] = problem
    return summary
