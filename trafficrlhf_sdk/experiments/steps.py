"""The SDK stages the paper experiments are made of, each resumable: a cached closed-loop evaluation, an
alignment run, a labelled feedback campaign and a trained reward model.

Every step writes its output under the experiment folder and is skipped when that output is already there, so an
interrupted ``trafficrlhf experiment paper`` resumes where it stopped. Nothing here reimplements a stage: the
evaluation is :func:`~trafficrlhf_sdk.evaluation.protocol.evaluate_policy`, alignment is
:func:`~trafficrlhf_sdk.alignment.recipe.run_recipe`, feedback is
:func:`~trafficrlhf_sdk.feedback.campaign.create_campaign` with
:class:`~trafficrlhf_sdk.feedback.SyntheticAnnotator` profiles, reward models come from
:class:`~trafficrlhf_sdk.reward.RewardTrainer`.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from trafficrlhf_sdk.errors import DataNotFoundError
from trafficrlhf_sdk.experiments.report import clean_json

if TYPE_CHECKING:
    from trafficrlhf_sdk.experiments.config import PaperConfig

__all__ = ["ExperimentRun", "align", "evaluate", "labelled_campaign", "resolve_path", "train_reward_model"]

SUMMARY_METRICS = ("failure_rate", "collision_rate", "offroad_rate", "realism_ctg", "realism_body", "realism_meta",
                   "speed_ratio", "stopped_share", "guidance_speed_limit", "guidance_target_speed",
                   "guidance_goal_waypoint")


def resolve_path(path: str) -> str:
    """``path`` as given when it exists, else relative to the folder above the installed SDK (the repository
    root of a source checkout, where the bundled reward models live); an error naming both otherwise."""
    if os.path.exists(path):
        return os.path.abspath(path)
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # trafficrlhf_sdk/
    beside = os.path.join(os.path.dirname(package), path)
    if os.path.exists(beside):
        return beside
    raise DataNotFoundError(f"{path!r} does not exist here nor at {beside!r}; give the reward-model folder's path.")


@dataclass
class ExperimentRun:
    """What every table of one experiment shares: its configuration, folder, log, the evaluation scenes (loaded
    once) and the reward models it scores with (loaded once)."""

    config: PaperConfig
    out_dir: str
    log: Callable[[str], None] = print
    _scenes: Any = None
    _rewards: dict[str, Any] = field(default_factory=dict)

    @property
    def scenes(self) -> Any:
        """The first ``config.scenes`` long-enough val scenes of the source, sorted by name."""
        if self._scenes is None:
            from trafficrlhf_sdk.plugins import get_scenario_source

            source = get_scenario_source(self.config.source, **self._root())
            ids = source.scene_ids("val")[: self.config.scenes]
            self.log(f"loading {len(ids)} val scenes of {self.config.source}")
            self._scenes = source.load_batch("val", scene_ids=ids)
        return self._scenes

    def _root(self) -> dict[str, Any]:
        return {"root": self.config.root} if self.config.root else {}

    def reward(self, path: str) -> Any:
        """The reward model saved in ``path`` (eval mode), loaded once."""
        if path not in self._rewards:
            from trafficrlhf_sdk.reward.loading import load_reward

            self._rewards[path] = load_reward(path)
        return self._rewards[path]

    def folder(self, *parts: str) -> str:
        """``out_dir/parts...``, created."""
        path = os.path.join(self.out_dir, *parts)
        os.makedirs(path, exist_ok=True)
        return path


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_")


def evaluate(run: ExperimentRun, label: str, model: str, checkpoint: str | None, guidance: str | None,
             reward_models: dict[str, str] | None = None, model_options: dict[str, Any] | None = None
             ) -> dict[str, Any]:
    """Closed-loop evaluation of one model on the run's scenes, cached in ``out_dir/evaluations/``.

    ``reward_models`` maps a name to a reward-model folder: the reward cost under each (the paper's sum of
    (1 - r_t) / 2 over the 2 Hz steps, :class:`~trafficrlhf_sdk.metrics.reward_cost.RewardCostMetric`) is
    computed on the same rollouts. Returns ``{"metrics": {...}, "reward_cost": {name: cost}, ...}``; a cached
    result is reused when it was made with the same model, weights, guidance, scenes, rollouts and seed and holds
    every requested reward cost.
    """
    import torch

    from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, evaluate_policy
    from trafficrlhf_sdk.metrics.reward_cost import RewardCostMetric
    from trafficrlhf_sdk.plugins import build_policy

    cfg = run.config
    reward_models = dict(reward_models or {})
    key = {"model": model, "checkpoint": checkpoint, "guidance": guidance, "model_options": model_options or {},
           "scenes": cfg.scenes, "source": cfg.source, "rollouts": cfg.rollouts, "seed": cfg.seed}
    path = os.path.join(run.folder("evaluations"), _slug(f"{label}__{guidance}") + ".json")
    cached = _read(path)
    if cached is not None and cached.get("key") == key and set(reward_models) <= set(cached["reward_cost"]):
        return cached
    run.log(f"evaluating {label} ({guidance or 'no guidance'}) on {cfg.scenes} val scenes, {cfg.rollouts} "
            "rollout(s) each")
    torch.manual_seed(cfg.seed)
    policy = build_policy(model, {**(model_options or {}), "checkpoint": checkpoint, "guidance": guidance,
                                  "seed": cfg.seed})
    began = time.perf_counter()
    report = evaluate_policy(policy, run.scenes, EvaluationConfig(batch_size=cfg.batch_size, seed=cfg.seed,
                                                                  rollouts=cfg.rollouts), progress=cfg.progress)
    costs = {}
    for name, folder in reward_models.items():
        reward = run.reward(folder)
        costs[name] = RewardCostMetric(reward.step_rewards).compute(report.rollout).values["reward_cost"]
    result = {"key": key, "label": label, "metrics": {k: v for k, v in report.values.items() if k in
                                                      SUMMARY_METRICS},
              "logged": {k: v for k, v in report.logged_values.items() if k in SUMMARY_METRICS},
              "reward_cost": costs, "num_scenes": report.num_scenes,
              "num_controlled_agents": report.num_controlled_agents,
              "wall_time_s": time.perf_counter() - began}
    _write(path, result)
    return result


def align(run: ExperimentRun, name: str, model: str, checkpoint: str | None, reward_model: str,
          fields: dict[str, Any], aggregation: str = "mean", model_options: dict[str, Any] | None = None
          ) -> dict[str, Any]:
    """Align ``model`` from ``checkpoint`` against ``reward_model`` with the AlignConfig ``fields``
    (:func:`~trafficrlhf_sdk.alignment.recipe.run_recipe`) into ``out_dir/models/<name>``; skipped when that folder
    already holds a finished run, resumed from its newest checkpoint when it holds an interrupted one. Returns the
    run's summary plus its ``folder``."""
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe, run_recipe

    folder = os.path.join(run.out_dir, "models", name)
    done = _read(os.path.join(folder, "align_summary.json"))
    if done is None:
        cfg = run.config
        settings = {"guidance": cfg.guidance, "seed": cfg.seed, "progress_bar": cfg.progress,
                    **({"source": cfg.source} if cfg.source != "nuscenes_pred" else {}),
                    **({"root": cfg.root} if cfg.root else {}), **fields}
        checkpoints = os.path.join(folder, "checkpoints")
        # an interrupted run: continue from its newest checkpoint
        resume = os.path.isdir(checkpoints) and any(n.startswith("checkpoint-") for n in os.listdir(checkpoints))
        recipe = AlignRecipe(model=model, checkpoint=checkpoint, reward_model=reward_model,
                             model_options=model_options or {}, reward_aggregation=aggregation,  # type: ignore[arg-type]
                             align=settings)
        run.log(f"aligning {name}: {model} from {checkpoint or 'its bundled weights'} against {reward_model} "
                f"({settings.get('epochs')} epochs at most, groups {settings.get('groups') or 'all'})")
        done = run_recipe(recipe, folder, **({"resume": True} if resume else {}))
        run.log(f"aligned {name} in {done['wall_time_s']:.0f} s ({done['epochs']} epochs)")
    return {**done, "folder": folder}


def labelled_campaign(run: ExperimentRun, store: Any, name: str, model: str, num_contexts: int, split: str,
                      annotators: dict[str, Any], guidance: str | None, model_options: dict[str, Any] | None = None,
                      candidate_models: list[str] | None = None, candidates: int = 5, seconds: float = 4.0) -> None:
    """Campaign ``name`` over the first ``num_contexts`` long-enough scenes of ``split`` (created, or extended by
    the scenes it lacks after an interruption), then labelled by every stand-in annotator of ``annotators``
    (name -> SyntheticAnnotatorConfig) on the items it has not labelled yet."""
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig, create_campaign, extend_campaign
    from trafficrlhf_sdk.feedback.synthetic import SyntheticAnnotator

    cfg = run.config
    existing = {c.name for c in store.campaigns()}
    if name in existing:
        report = extend_campaign(store, name, num_contexts=num_contexts, root=cfg.root)
        if report.added:
            run.log(f"campaign {name}: {len(report.added)} contexts added")
    else:
        run.log(f"campaign {name}: up to {num_contexts} {split} contexts x {candidates} candidates of {seconds:g} s "
                f"({', '.join(dict.fromkeys(candidate_models or [model]))})")
        create_campaign(store, CampaignConfig(
            name=name, model=model, guidance=guidance, model_options=model_options or {}, source=cfg.source,
            split=split, root=cfg.root, num_contexts=num_contexts, num_candidates=candidates,
            candidate_seconds=seconds, seed=cfg.seed, candidate_models=candidate_models))
    for annotator, settings in annotators.items():
        counts = SyntheticAnnotator(store, annotator, settings).label(name)
        if counts.get("labeled"):
            run.log(f"campaign {name}: {annotator} labelled {counts['labeled']} items")


def train_reward_model(run: ExperimentRun, folder: str, dataset: Any, settings: dict[str, Any],
                       contrast: Any = None, title: str = "") -> dict[str, Any]:
    """A reward model trained on ``dataset`` (and ``contrast`` pairs) with the RewardConfig ``settings``, saved in
    ``folder`` with its model card; skipped when ``folder`` holds one. Returns its card's metrics and data."""
    from trafficrlhf_sdk.reward import RewardConfig, RewardTrainer

    card_path = os.path.join(folder, "config.json")
    saved = _read(card_path)
    if saved is None:
        config = RewardConfig(**{"seed": run.config.seed, "progress": False, **settings})
        run.log(f"training reward model {os.path.basename(folder)} ({config.architecture}, "
                f"{config.ensemble_size} member(s), {config.max_epochs} epochs at most)")
        trainer = RewardTrainer(config, train_dataset=dataset, contrast_dataset=contrast)
        result = trainer.train()
        result.model.save_pretrained(folder, {"title": title, "metrics": dict(result.metrics),
                                              "data": trainer.dataset_info})
        saved = _read(card_path) or {}
    return {"metrics": saved.get("metrics", {}), "data": saved.get("data", {}), "folder": folder}


def _read(path: str) -> dict[str, Any] | None:
    if not os.path.isfile(path):
        return None
    with open(path, encoding="utf-8") as handle:
        return json.load(handle)


def _write(path: str, value: dict[str, Any]) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as handle:
        json.dump(clean_json(value), handle, indent=2, default=str)
    os.replace(tmp, path)
