"""The paper experiments' conventions over the pipeline's steps (:mod:`trafficrlhf_sdk.pipeline`): where each step's
folder lies under the experiment folder, and the settings every table shares (scenes, seed, guidance, source).

Nothing here runs a stage or caches on its own: an evaluation is an
:func:`~trafficrlhf_sdk.pipeline.stages.evaluate_step` in ``DIR/evaluations/<label>__<guidance>__<rewards>``, an
alignment an :func:`~trafficrlhf_sdk.pipeline.stages.align_step` in ``DIR/models/<name>`` (a table's alignments
side by side on Ray, :func:`~trafficrlhf_sdk.pipeline.stages.align_steps`), a labelled campaign a
:func:`~trafficrlhf_sdk.pipeline.stages.generate_step` and a
:func:`~trafficrlhf_sdk.pipeline.stages.label_step` beside the table's ``feedback.sqlite``, and a reward model a
:func:`~trafficrlhf_sdk.pipeline.stages.reward_model_step`. So an interrupted ``trafficrlhf experiment paper``
resumes where it stopped, and a rerun with other settings is refused, naming the setting.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from trafficrlhf_sdk.experiments.config import resolve_path

if TYPE_CHECKING:
    from trafficrlhf_sdk.experiments.config import PaperConfig
    from trafficrlhf_sdk.pipeline.step import StepResult

__all__ = ["ExperimentRun", "align_all", "align_recipe", "evaluate", "labelled_campaign", "read_recipe",
           "resolve_path", "train_reward_model"]

SUMMARY_METRICS = ("failure_rate", "collision_rate", "offroad_rate", "realism_ctg", "realism_body", "realism_meta",
                   "speed_ratio", "stopped_share", "guidance_speed_limit", "guidance_target_speed",
                   "guidance_goal_waypoint")


def read_recipe(path: str) -> Any:
    """The :class:`~trafficrlhf_sdk.alignment.recipe.AlignRecipe` in TOML file ``path`` (relative to the working
    directory or to the repository, as :func:`resolve_path`)."""
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe

    return AlignRecipe.load(resolve_path(path))


@dataclass
class ExperimentRun:
    """What every table of one experiment shares: its configuration, folder, log and the evaluation scenes (loaded
    once, when an evaluation first needs them); ``overwrite`` redoes steps finished with other settings instead of
    refusing them; ``ran`` counts the steps that did work (were not cached)."""

    config: PaperConfig
    out_dir: str
    log: Callable[[str], None] = print
    overwrite: bool = False
    ran: int = 0
    _scenes: Any = None
    _scene_ids: list[str] | None = None

    @property
    def scenes(self) -> Any:
        """The first ``config.scenes`` long-enough val scenes of the source, sorted by name."""
        if self._scenes is None:
            from trafficrlhf_sdk.plugins import get_scenario_source

            source = get_scenario_source(self.config.source, **self._root())
            ids = source.scene_ids("val")[: self.config.scenes]
            self.log(f"loading {len(ids)} val scenes of {self.config.source}")
            self._scenes, self._scene_ids = source.load_batch("val", scene_ids=ids), list(ids)
        return self._scenes

    @property
    def scene_ids(self) -> list[str]:
        """The names of :attr:`scenes`, in their order."""
        self.scenes  # noqa: B018 (loads them once)
        assert self._scene_ids is not None
        return self._scene_ids

    def _root(self) -> dict[str, Any]:
        return {"root": self.config.root} if self.config.root else {}

    def folder(self, *parts: str) -> str:
        """``out_dir/parts...``, created."""
        path = os.path.join(self.out_dir, *parts)
        os.makedirs(path, exist_ok=True)
        return path

    @property
    def steps(self) -> dict[str, Any]:
        """The keywords every step of the run takes (its log, overwrite)."""
        return {"log": self.log, "overwrite": self.overwrite}

    def count(self, step: StepResult) -> StepResult:
        """``step``, counted in ``ran`` when it did work."""
        self.ran += not step.cached
        return step


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_")


def evaluate(run: ExperimentRun, label: str, model: str, checkpoint: str | None, guidance: str | None,
             reward_models: dict[str, str] | None = None, model_options: dict[str, Any] | None = None,
             after: Sequence[StepResult] = ()) -> StepResult:
    """Closed-loop evaluation of one model on the run's scenes with the run's seed and rollouts, in
    ``out_dir/evaluations/<label>__<guidance>__<reward names>``.

    ``reward_models`` maps a name to a reward-model folder: the reward cost under each (the paper's sum of
    (1 - r_t) / 2 over the 2 Hz steps) is computed on the same rollouts. Outputs ``metrics``, ``logged``,
    ``reward_cost`` ({name: cost}), ``num_scenes``, ``num_controlled_agents``, ``wall_time_s``."""
    from trafficrlhf_sdk.evaluation.runs import EvaluationRequest
    from trafficrlhf_sdk.pipeline.stages import evaluate_step

    cfg = run.config
    rewards = dict(reward_models or {})
    request = EvaluationRequest(model=model, checkpoint=checkpoint, guidance=guidance,
                                model_options=model_options or {}, source=cfg.source, split="val", root=cfg.root,
                                num_scenes=cfg.scenes, seeds=(cfg.seed,), batch_size=cfg.batch_size,
                                rollouts=cfg.rollouts, execution=cfg.execution)
    folder = os.path.join(run.out_dir, "evaluations", _slug(f"{label}__{guidance}__{'+'.join(sorted(rewards))}"))

    def scenes() -> Any:
        run.log(f"evaluating {label} ({guidance or 'no guidance'}) on {cfg.scenes} val scenes, {cfg.rollouts} "
                "rollout(s) each")
        return run.scenes, run.scene_ids

    return run.count(evaluate_step(folder, request, reward_models=rewards, load=scenes, metrics=SUMMARY_METRICS,
                                   progress=cfg.progress, after=after, **run.steps))


def align_recipe(run: ExperimentRun, model: str, checkpoint: str | None, reward_model: str, fields: dict[str, Any],
                 aggregation: str = "mean", model_options: dict[str, Any] | None = None) -> Any:
    """The :class:`~trafficrlhf_sdk.alignment.recipe.AlignRecipe` that aligns ``model`` from ``checkpoint`` against
    ``reward_model`` with the AlignConfig ``fields`` (the run's guidance, seed, source and progress bar unless
    ``fields`` set them)."""
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe

    cfg = run.config
    settings = {"guidance": cfg.guidance, "seed": cfg.seed, "progress_bar": cfg.progress,
                **({"source": cfg.source} if cfg.source != "nuscenes_pred" else {}),
                **({"root": cfg.root} if cfg.root else {}), **fields}
    return AlignRecipe(model=model, checkpoint=checkpoint, reward_model=reward_model,
                       model_options=model_options or {}, reward_aggregation=aggregation,  # type: ignore[arg-type]
                       align=settings)


def align_all(run: ExperimentRun, named: Sequence[tuple[str, Any]], after: Sequence[StepResult] = ()
              ) -> list[StepResult]:
    """Independent alignments ``(name, recipe)`` into ``out_dir/models/<name>``: one after another in-process, side
    by side on the run's Ray workers (:func:`~trafficrlhf_sdk.pipeline.stages.align_steps`). Results in order."""
    from trafficrlhf_sdk.pipeline.stages import AlignJob, align_steps

    cfg = run.config
    jobs = [AlignJob(os.path.join(run.out_dir, "models", name), recipe, tuple(after)) for name, recipe in named]
    done = align_steps(jobs, execution=cfg.execution if cfg.execution.uses_ray else None, **run.steps)
    for (name, recipe), step in zip(named, done, strict=True):
        run.count(step)
        if not step.cached:
            run.log(f"aligned {name} ({recipe.model} from {recipe.checkpoint or 'its bundled weights'} against "
                    f"{recipe.reward_model}) in {step['wall_time_s']:.0f} s ({step['epochs']} epochs)")
    return done


def labelled_campaign(run: ExperimentRun, folder: str, name: str, model: str, num_contexts: int, split: str,
                      annotators: Mapping[str, Any], guidance: str | None, model_options: dict[str, Any] | None = None,
                      candidate_models: list[str] | None = None, candidates: int = 5,
                      seconds: float = 4.0) -> StepResult:
    """Campaign ``name`` in ``folder/feedback.sqlite`` over the first ``num_contexts`` long-enough scenes of
    ``split``, labelled by every stand-in annotator of ``annotators`` (name -> SyntheticAnnotatorConfig); the
    steps lie in ``folder/campaigns/<name>`` and ``folder/labels/<name>``. Returns the labelling step."""
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig
    from trafficrlhf_sdk.pipeline.stages import generate_step, label_step

    cfg = run.config
    db = os.path.join(folder, "feedback.sqlite")
    campaign = CampaignConfig(name=name, model=model, guidance=guidance, model_options=model_options or {},
                              source=cfg.source, split=split, root=cfg.root, num_contexts=num_contexts,
                              num_candidates=candidates, candidate_seconds=seconds, seed=cfg.seed,
                              candidate_models=candidate_models)
    made = run.count(generate_step(os.path.join(folder, "campaigns", name), db, campaign, execution=cfg.execution,
                                   **run.steps))
    if not made.cached:
        run.log(f"campaign {name}: {made['contexts']} {split} contexts x {candidates} candidates of {seconds:g} s "
                f"({', '.join(dict.fromkeys(candidate_models or [model]))})")
    labelled = run.count(label_step(os.path.join(folder, "labels", name), db, name, annotators, after=[made],
                                    **run.steps))
    for annotator, counts in labelled.get("counts", {}).items():
        if not labelled.cached and counts.get("labeled"):
            run.log(f"campaign {name}: {annotator} labelled {counts['labeled']} items")
    return labelled


def train_reward_model(run: ExperimentRun, folder: str, labels: StepResult, settings: dict[str, Any],
                       title: str = "") -> StepResult:
    """A reward model trained with the RewardConfig ``settings`` (seed: the run's) on the labels of campaign
    step ``labels`` (15 % of its contexts held out) plus the run's contrast pairs, saved in ``folder`` with its
    card. Outputs its ``folder``, card ``metrics`` and ``data``, and ``preferences`` (contexts and pairs)."""
    from trafficrlhf_sdk.pipeline.stages import reward_model_step
    from trafficrlhf_sdk.reward.config import RewardConfig

    cfg = run.config
    config = RewardConfig(**{"seed": cfg.seed, "progress": False, **settings})
    db = os.path.join(os.path.dirname(os.path.dirname(labels.folder)), "feedback.sqlite")
    trained = run.count(reward_model_step(
        folder, config, db, [labels["campaign"]], val_fraction=0.15, split_seed=cfg.seed,
        contrast_scenes=cfg.contrast_scenes, source=cfg.source, root=cfg.root, candidate_seconds=cfg.feedback_seconds,
        title=title, after=[labels], **run.steps))
    if not trained.cached:
        run.log(f"trained reward model {os.path.basename(folder)} ({config.architecture}, {config.ensemble_size} "
                f"member(s)): val accuracy {trained['metrics'].get('val_accuracy', float('nan')):.3f}")
    return trained
