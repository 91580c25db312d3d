"""The stages of the RLHF pipeline as steps (:func:`~trafficrlhf_sdk.pipeline.step.run_step`): each one calls its
stage's library function, writes its folder and ``step.json``, and returns the recorded outputs when called again
with the same inputs.

=================  =========================================================  ==========================================
step               calls                                                      outputs
=================  =========================================================  ==========================================
generate_step      :func:`~trafficrlhf_sdk.feedback.campaign.create_campaign`  ``db``, ``campaign``, ``contexts``
label_step         :class:`~trafficrlhf_sdk.feedback.SyntheticAnnotator`       ``counts`` per annotator (or people's)
rank_step          :func:`~trafficrlhf_sdk.feedback.selection.rank_by_disagreement`  ``ranked`` items per campaign
reward_model_step  :func:`~trafficrlhf_sdk.reward.card.train_and_save`         ``folder``, ``metrics``, ``probes``
align_step         :func:`~trafficrlhf_sdk.alignment.recipe.run_recipe`        the run's summary and ``folder``
align_steps        several ``align_step`` side by side on Ray workers          one ``align_step`` result per job
evaluate_step      :func:`~trafficrlhf_sdk.evaluation.runs.evaluate_seeds`     ``metrics`` (mean over seeds), per seed
=================  =========================================================  ==========================================

Every step takes its output ``folder`` first, then what it runs with, then the keywords ``after`` (the steps it
reads from), ``overwrite`` and ``log`` of :func:`run_step` (``align_steps`` takes jobs, each a folder, a recipe and
its ``after``). A reward is a spec string wherever one is given (a
reward-model folder or ``builtin:NAME``), so a step's output folder is another step's input.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.pipeline.step import StepConfigError, StepResult, input_differences, run_step

if TYPE_CHECKING:
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe
    from trafficrlhf_sdk.evaluation.runs import EvaluationRequest
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig
    from trafficrlhf_sdk.feedback.synthetic import SyntheticAnnotatorConfig
    from trafficrlhf_sdk.parallel import ExecutionConfig
    from trafficrlhf_sdk.reward.config import RewardConfig

__all__ = ["AlignJob", "align_step", "align_steps", "evaluate_step", "generate_step", "label_step", "rank_step",
           "reward_model_step"]

Log = Callable[[str], None]
# the fields of a campaign an interrupted generation may not change (the contexts are filled in afterwards)
_FILLED_LATER = ("scene_ids", "num_contexts", "root", "provenance")
# AlignConfig fields that change how a run is shown or continued, not what it makes
_HOW_NOT_WHAT = ("progress_bar", "resume", "resume_allow_changes", "output_dir")


def _weights_digest(reference: str | None) -> str | None:
    """The SHA-256 of the weights a checkpoint or reward-model ``reference`` (a folder, or a bundled checkpoint's
    name) records in its ``config.json``; None for anything else (``builtin:`` rewards, a model's default
    weights). Steps put it among their inputs, so new weights under the same name redo the step instead of reusing
    a result of the old ones."""
    import json

    from trafficrlhf_sdk.plugins import resolve_checkpoint

    if not reference:
        return None
    try:
        with open(os.path.join(resolve_checkpoint(reference), "config.json"), encoding="utf-8") as handle:
            weights = json.load(handle).get("weights")
    except (TrafficRLHFError, OSError, ValueError, AttributeError):
        return None
    digest = weights.get("sha256") if isinstance(weights, dict) else None
    return digest if isinstance(digest, str) else None


# ----------------------------------------------------------------------------------------------------- feedback
def generate_step(folder: str, db: str, campaign: CampaignConfig, *, after: Sequence[StepResult] = (),
                  overwrite: bool = False, log: Log | None = None, execution: ExecutionConfig | None = None
                  ) -> StepResult:
    """Campaign ``campaign.name`` in feedback database ``db``: its contexts with N candidates each, made in-process
    or on ``execution``'s Ray workers (the same candidates).

    A generation stopped midway is completed: the campaign gets the contexts it lacks (each context is seeded by
    the campaign's seed and its scene, so the candidates are those of an uninterrupted run). Outputs: ``db``,
    ``campaign`` and ``contexts`` (how many it holds)."""
    inputs = {"db": db, "campaign": campaign.model_dump(mode="json")}

    def work() -> dict[str, Any]:
        from trafficrlhf_sdk.feedback.campaign import create_campaign, extend_campaign
        from trafficrlhf_sdk.feedback.store import FeedbackStore

        store = FeedbackStore(db)
        try:
            if campaign.name in {c.name for c in store.campaigns()}:
                _check_campaign(store.campaign(campaign.name).config, campaign, db)
                extend_campaign(store, campaign.name, scene_ids=campaign.scene_ids,
                                num_contexts=None if campaign.scene_ids else campaign.num_contexts,
                                root=campaign.root, execution=execution)
            else:
                create_campaign(store, campaign, execution=execution)
            contexts = len(store.context_keys(store.campaign(campaign.name)))
        finally:
            store.close()
        return {"db": db, "campaign": campaign.name, "contexts": contexts}

    return run_step("generate", folder, inputs, work, after=after, overwrite=overwrite, log=log)


def _check_campaign(stored: dict[str, Any], campaign: CampaignConfig, db: str) -> None:
    wanted = campaign.model_dump(mode="json")
    changes = input_differences({k: v for k, v in stored.items() if k in wanted and k not in _FILLED_LATER},
                                {k: v for k, v in wanted.items() if k in stored and k not in _FILLED_LATER})
    if changes:
        raise StepConfigError(f"campaign {campaign.name!r} in {db!r} was started with other settings: "
                              f"{'; '.join(changes[:8])}. A database keeps its campaigns: use another output "
                              "folder (or another campaign name) for these settings.")


def label_step(folder: str, db: str, campaign: str, annotators: Mapping[str, SyntheticAnnotatorConfig], *,
               limit: int | None = None, people: bool = False, poll_s: float = 10.0,
               after: Sequence[StepResult] = (), overwrite: bool = False, log: Log | None = None) -> StepResult:
    """Labels for ``campaign``: every stand-in annotator of ``annotators`` (name -> settings) labels up to
    ``limit`` items (all when None), in the order the campaign serves them; a labelling stopped midway goes on
    where it stopped. With ``people``, waits (polling every ``poll_s`` s) until people have labelled ``limit``
    items in the browser app. Outputs: ``campaign``, and ``counts`` per annotator (labelled, 'none realistic',
    ties, skipped, and ``before``: items it had labelled before this call) or ``labelled`` items for people."""
    inputs = {"db": db, "campaign": campaign, "limit": limit, "people": people,
              "annotators": {} if people else {k: v.model_dump(mode="json") for k, v in annotators.items()}}

    def work() -> dict[str, Any]:
        from trafficrlhf_sdk.feedback.store import FeedbackStore
        from trafficrlhf_sdk.feedback.synthetic import SyntheticAnnotator

        store = FeedbackStore(db)
        try:
            record = store.campaign(campaign)
            if people:
                wanted = limit or len(store.context_keys(record))
                if log is not None:
                    log(f"waiting for people to label {wanted} items of {campaign} (`trafficrlhf feedback serve "
                        f"--db {db}`); stop and rerun to resume")
                while len({lab.context_id for lab in store.labels(record)}) < wanted:
                    time.sleep(poll_s)
                return {"campaign": campaign, "labelled": len({lab.context_id for lab in store.labels(record)})}
            counts = {}
            for name, settings in annotators.items():
                annotator = SyntheticAnnotator(store, name, settings)
                done = _items_done(store, record, annotator.annotator.id)
                left = None if limit is None else max(0, limit - done)
                counts[name] = annotator.label(record, limit=left) if left != 0 else {"labeled": 0}
                counts[name]["before"] = done
        finally:
            store.close()
        return {"campaign": campaign, "counts": counts}

    return run_step("label", folder, inputs, work, after=after, overwrite=overwrite, log=log)


def _items_done(store: Any, campaign: Any, annotator_id: int) -> int:
    """Items of ``campaign`` the annotator has labelled or skipped."""
    labelled = {lab.context_id for lab in store.labels(campaign) if lab.annotator_id == annotator_id}
    skipped = {row["context_id"] for row in store.skips(campaign) if row["annotator_id"] == annotator_id}
    return len(labelled | skipped)


def rank_step(folder: str, db: str, campaigns: Sequence[str], reward_model: str, *,
              after: Sequence[StepResult] = (), overwrite: bool = False, log: Log | None = None) -> StepResult:
    """Active selection: the unlabelled items of ``campaigns`` are served in the order of the disagreement of
    the members of ensemble ``reward_model`` (a folder); one member leaves the campaign order. Outputs:
    ``ranked`` (items per campaign) and ``max_disagreement`` per campaign."""
    inputs = {"db": db, "campaigns": list(campaigns), "reward_model": reward_model}

    def work() -> dict[str, Any]:
        from trafficrlhf_sdk.feedback.selection import rank_by_disagreement
        from trafficrlhf_sdk.feedback.store import FeedbackStore
        from trafficrlhf_sdk.reward.model import RewardModel

        model = RewardModel.from_pretrained(reward_model).eval()
        members = list(getattr(model, "members", [])) or [model]
        ranked: dict[str, int] = {}
        top: dict[str, float] = {}
        if len(members) < 2:
            return {"ranked": ranked, "max_disagreement": top, "members": len(members)}
        store = FeedbackStore(db)
        try:
            for name in campaigns:
                scores = rank_by_disagreement(store, name, [m.score for m in members])
                ranked[name], top[name] = len(scores), max(scores.values(), default=0.0)
        finally:
            store.close()
        return {"ranked": ranked, "max_disagreement": top, "members": len(members)}

    return run_step("rank", folder, inputs, work, after=after, overwrite=overwrite, log=log)


# ------------------------------------------------------------------------------------------------------- reward
def reward_model_step(folder: str, config: RewardConfig, db: str, campaigns: Sequence[str], *,
                      val_fraction: float = 0.15, split_seed: int = 0, annotators: Sequence[str] = (),
                      contrast_scenes: int = 0, contrast_annotators: Sequence[str] = (), probe_scenes: int = 0,
                      probe_judges: Sequence[str] = (), source: str | None = None, root: str | None = None,
                      candidate_seconds: float = 4.0,
                      title: str | None = None, notes: Sequence[str] = (), after: Sequence[StepResult] = (),
                      overwrite: bool = False, log: Log | None = None) -> StepResult:
    """A reward model trained with ``config`` on the labels of ``campaigns`` in ``db`` (``val_fraction`` of the
    contexts held out, split by ``split_seed``; only ``annotators``' labels when given), plus contrast pairs from
    the logs of the last ``contrast_scenes`` train scenes of ``source`` (labelled by the stand-in profiles named in
    ``contrast_annotators``; none named: the log wins), probed on ``probe_scenes`` val scenes (and the stand-in
    profiles ``probe_judges`` with it);
    saved in ``folder`` with its card by :func:`~trafficrlhf_sdk.reward.card.train_and_save`. A training stopped
    midway continues from its newest epoch checkpoint in ``folder/checkpoints``, to the weights of an
    uninterrupted run.

    Outputs: ``folder``, the card's ``metrics`` and ``data``, ``dataset`` (pairs and contexts trained and
    validated on), ``preferences`` (contexts and pairs of the labels read) and ``probes``."""
    inputs = {"config": config.model_dump(mode="json", exclude={"progress", "num_threads"}), "db": db,
              "campaigns": list(campaigns), "val_fraction": val_fraction, "split_seed": split_seed,
              "annotators": list(annotators), "contrast_scenes": contrast_scenes, "probe_scenes": probe_scenes,
              **({"contrast_annotators": list(contrast_annotators)} if contrast_annotators else {}),
              **({"probe_judges": list(probe_judges)} if probe_judges else {}),
              "source": source, "root": root, "candidate_seconds": candidate_seconds, "title": title,
              "notes": list(notes)}

    def work() -> dict[str, Any]:
        from trafficrlhf_sdk.reward.card import train_and_save
        from trafficrlhf_sdk.reward.evaluation import load_preferences

        dataset, store = load_preferences(db, list(campaigns), None, annotators, val_fraction, split_seed)
        try:
            trained = train_and_save(config, dataset, folder, store=store, campaigns=campaigns,
                                     annotators=annotators, contrast_scenes=contrast_scenes, title=title,
                                     contrast_annotators=contrast_annotators,
                                     notes=notes, source=source, root=root,
                                     future_steps=round(candidate_seconds * 10), probe_scenes=probe_scenes,
                                     probe_judges=probe_judges,
                                     resume=None)  # an interrupted training continues from its newest epoch
        finally:
            if store is not None:
                store.close()
        return {"folder": folder, "metrics": trained.card["metrics"], "data": trained.card.get("data", {}),
                "dataset": trained.dataset_info, "probes": trained.probes,
                "preferences": {"contexts": dataset.num_contexts, "pairs": int(dataset.pairs.shape[0])}}

    return run_step("reward_model", folder, inputs, work, after=after, overwrite=overwrite, log=log)


# ---------------------------------------------------------------------------------------------------- alignment
def align_step(folder: str, recipe: AlignRecipe, *, after: Sequence[StepResult] = (), overwrite: bool = False,
               log: Log | None = None, execution: ExecutionConfig | None = None) -> StepResult:
    """``recipe``'s model aligned against its reward into ``folder``
    (:func:`~trafficrlhf_sdk.alignment.recipe.run_recipe`). Inside the step, alignment keeps its own finer
    resume: a run stopped midway continues from its newest epoch checkpoint in ``folder/checkpoints``
    (``AlignConfig.resume``). Outputs: the run's summary (epochs, rewards, wall time) and ``folder``."""
    inputs = recipe.model_dump(mode="json", exclude={"threads"})
    inputs["align"] = {k: v for k, v in inputs["align"].items() if k not in _HOW_NOT_WHAT}
    inputs["weights"] = {"checkpoint": _weights_digest(recipe.checkpoint),
                         "reward_model": _weights_digest(recipe.reward_model)}

    def work() -> dict[str, Any]:
        from trafficrlhf_sdk.alignment.recipe import run_recipe

        checkpoints = os.path.join(folder, "checkpoints")
        resume = os.path.isdir(checkpoints) and any(n.startswith("checkpoint-") for n in os.listdir(checkpoints))
        summary = run_recipe(recipe, folder, execution=execution if execution is not None and execution.uses_ray
                             else None, **({"resume": True} if resume else {}))
        return {**summary, "folder": folder}

    return run_step("align", folder, inputs, work, after=after, overwrite=overwrite, log=log)


@dataclass(frozen=True)
class AlignJob:
    """One alignment of :func:`align_steps`: its output folder, its recipe and the steps it reads from."""

    folder: str
    recipe: AlignRecipe
    after: Sequence[StepResult] = ()


def align_steps(jobs: Sequence[AlignJob], *, overwrite: bool = False, log: Log | None = None,
                execution: ExecutionConfig | None = None) -> list[StepResult]:
    """Several independent :func:`align_step` calls, results in job order.

    In-process they run one after another. On Ray they run side by side, one alignment per worker with the
    worker's torch threads (``threads_per_worker``; 1 gives the numbers of an in-process run with one thread; a
    recipe's ``threads`` is set to it), in the driver's working directory and ``TRAFFICRLHF_*`` environment; the
    jobs' log lines and SDK errors come back to the driver. On an existing cluster the workers must see the
    driver's files. (One alignment whose epochs' samples should spread over the workers is an
    :func:`align_step` with ``execution``.)"""
    log = log or (lambda line: None)
    if execution is None or not execution.uses_ray or not jobs:
        return [align_step(job.folder, job.recipe, after=job.after, overwrite=overwrite, log=log) for job in jobs]
    import contextlib

    from trafficrlhf_sdk.parallel import iter_tasks

    log(f"align: {len(jobs)} alignments side by side on Ray workers "
        f"({', '.join(os.path.basename(job.folder) for job in jobs)})")
    shared = {"overwrite": overwrite, "cwd": os.getcwd(), "threads": execution.threads_per_worker,
              "env": {k: v for k, v in os.environ.items() if k.startswith("TRAFFICRLHF_")}}
    done = []
    # closed before returning, so its workers are released to the next steps of the same Ray session
    with contextlib.closing(iter_tasks(_align_on_worker, shared, list(jobs), execution)) as results:
        for job, (result, lines) in zip(jobs, results, strict=True):
            for line in lines:
                log(line)
            if isinstance(result, TrafficRLHFError):
                raise result
            log(f"align: {'done before' if result.cached else 'done'} ({job.folder})")
            done.append(result)
    return done


def _align_on_worker(shared: dict[str, Any], job: AlignJob) -> tuple[StepResult | TrafficRLHFError, list[str]]:
    """One :func:`align_step` on a Ray worker, in the driver's working directory and data root, with the worker's
    torch threads; returns the step, or the SDK error it raised, and the lines it logged (a worker has nowhere to
    print them)."""
    os.chdir(shared["cwd"])
    os.environ.update(shared["env"])
    lines: list[str] = []
    recipe = job.recipe.model_copy(update={"threads": shared["threads"]})  # `threads` is not in the digest
    try:
        return align_step(job.folder, recipe, after=job.after, overwrite=shared["overwrite"], log=lines.append), lines
    except TrafficRLHFError as exc:
        return exc, lines


# --------------------------------------------------------------------------------------------------- evaluation
def evaluate_step(folder: str, request: EvaluationRequest, *, reward_models: Mapping[str, str] | None = None,
                  load: Callable[[], Any] | None = None, metrics: Sequence[str] | None = None, progress: bool = True,
                  after: Sequence[StepResult] = (), overwrite: bool = False, log: Log | None = None) -> StepResult:
    """Closed-loop evaluation of ``request`` (model, weights, guidance, scenes, rollouts) once per seed of
    ``request.seeds`` (:func:`~trafficrlhf_sdk.evaluation.runs.evaluate_seeds`), each run saved in
    ``folder/seed_<S>``.

    ``reward_models`` maps a name to a reward (a folder): the reward cost under each is computed on the same
    rollouts. ``load`` returns the request's scenes, or ``(scenes, scene_ids)``, called only when the step runs
    (several evaluations on the same scenes can share one loaded batch); None loads them from the request's
    source. Each run's ``results.json`` names its scenes where they are known, so runs compare scene by scene.
    ``metrics`` keeps only those names in the outputs (None: all).

    Outputs: ``metrics`` and ``logged`` (the mean over the seeds; a single seed's values as they are),
    ``reward_cost`` (name -> mean cost), ``seeds`` (each seed's metrics), ``num_scenes``,
    ``num_controlled_agents`` and ``wall_time_s``."""
    rewards = dict(reward_models or {})
    inputs = {"request": request.model_dump(mode="json", exclude={"execution", "reward_model"}),
              "reward_models": rewards, "metrics": None if metrics is None else list(metrics),
              "weights": {"checkpoint": _weights_digest(request.checkpoint),
                          "reward_models": {name: _weights_digest(path) for name, path in rewards.items()}}}
    if request.reward_model is not None:
        raise TrafficRLHFError(f"evaluate_step takes rewards as `reward_models` (name -> folder); got "
                               f"request.reward_model={request.reward_model!r}: pass "
                               f"reward_models={{'rm': {request.reward_model!r}}} instead.")

    def work() -> dict[str, Any]:
        import torch

        from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig
        from trafficrlhf_sdk.evaluation.runs import evaluate_seeds
        from trafficrlhf_sdk.metrics.reward_cost import RewardCostMetric
        from trafficrlhf_sdk.plugins import build_policy
        from trafficrlhf_sdk.reward.loading import load_reward

        def build(seed: int) -> Any:
            return build_policy(request.model, {**request.model_options, "checkpoint": request.checkpoint,
                                                "guidance": request.guidance, "seed": seed})

        began = time.perf_counter()
        torch.manual_seed(request.seeds[0])
        first = build(request.seeds[0])  # the model and the guidance in effect, named in each results.json
        model = request.model or str(getattr(first, "name", None) or type(first).__name__)
        guidance = getattr(getattr(first, "options", None), "guidance", request.guidance)
        loaded_scenes = load() if load is not None else request.load(log)
        scenes, scene_ids = loaded_scenes if isinstance(loaded_scenes, tuple) else (loaded_scenes, None)
        config = EvaluationConfig(simulation=request.simulation, batch_size=request.batch_size,
                                  rollouts=request.rollouts)
        execution = request.execution if request.execution.uses_ray else None
        metadata = {} if scene_ids is None else request.metadata(model, scene_ids, guidance or None)
        runs = evaluate_seeds(lambda seed: first if seed == request.seeds[0] else build(seed), scenes, request.seeds,
                              config, progress=progress, execution=execution, metadata=metadata)
        loaded = {name: load_reward(path) for name, path in rewards.items()}
        per_seed = []
        for seed, report in zip(request.seeds, runs.reports):
            costs = {name: RewardCostMetric(reward.step_rewards).compute(report.rollout).values["reward_cost"]
                     for name, reward in loaded.items()}
            report.save(os.path.join(folder, f"seed_{seed}"), plot=False)
            per_seed.append({"seed": seed, "metrics": _kept(report.values, metrics),
                             "logged": _kept(report.logged_values, metrics), "reward_cost": costs})
        first = runs.reports[0]
        return {"metrics": _mean([s["metrics"] for s in per_seed]), "logged": _mean([s["logged"] for s in per_seed]),
                "reward_cost": _mean([s["reward_cost"] for s in per_seed]), "seeds": per_seed,
                "num_scenes": first.num_scenes, "num_controlled_agents": first.num_controlled_agents,
                "wall_time_s": time.perf_counter() - began}

    return run_step("evaluate", folder, inputs, work, after=after, overwrite=overwrite, log=log)


def _kept(values: Mapping[str, Any], names: Sequence[str] | None) -> dict[str, Any]:
    return {k: v for k, v in values.items() if names is None or k in names}


def _mean(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The mean of every numeric key all ``rows`` hold; one row is returned as it is."""
    if len(rows) == 1:
        return dict(rows[0])
    keys = [k for k in rows[0] if all(isinstance(r.get(k), (int, float)) for r in rows)]
    return {k: sum(float(r[k]) for r in rows) / len(rows) for k in keys}
