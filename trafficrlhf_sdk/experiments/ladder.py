"""The alignment ladder: one model, one fine-tuning recipe, four rewards, so each link of the feedback chain is
measured on its own.

=====  ==========================================================  ==============================================
row    reward                                                      what the gap to the row above measures
=====  ==========================================================  ==============================================
(a)    ``builtin:failure``: the failure reward, no prior            (the reference: what the fine-tuner reaches with
                                                                    a reward known to be right)
(b)    ``builtin:judgment``: the stand-in's judgment, per agent     the annotator: what its judgment gives at best
(c)    a reward model learned from the stand-ins' labels            the reward model: what learning the judgment
                                                                    from noisy choices loses
(d)    (c) with ``alpha = 0``                                       the control: what the reward adds at all
=====  ==========================================================  ==============================================

Every row starts from the recipe's checkpoint and runs the recipe's :class:`~trafficrlhf_sdk.alignment.AlignConfig`
unchanged (only the reward differs, and ``alpha`` in row (d)); each is evaluated in closed loop over the same
scenes and seeds as the base. For the reward model the ladder also measures its agreement with the noise-free
stand-in on candidates of the policy itself, at the start (the base) and at the end (row (c)'s model): the share of
candidate pairs of the same context it orders as the judgment does.

With ``rounds`` above 1 the learned path iterates as the RLHF loop does (a reward model is accurate near the
data it saw, and the fine-tuned policy drives where the first one saw none): round ``r`` aligns the base against
round ``r - 1``'s reward model, draws ``round_contexts`` train contexts from that policy's own closed-loop driving,
cut shortly before its failures (``CampaignConfig.contexts = 'closed_loop'``), has the same stand-ins label them,
and retrains the reward model on every label so far; rows (c) and (d) use the last round's reward model.

Each row runs ``draws`` times, with training seeds ``seed``, ``seed + 1``, ... of the recipe (a fine-tuning run is
one draw of its recipe, and draws of the same recipe differ by tens of points), and is reported as the mean over
its draws with a t-interval over them; each link's loss is the difference of two rows, paired by training seed.

Everything runs as steps of :mod:`trafficrlhf_sdk.pipeline` under the output folder, so an interrupted ladder
resumes where it stopped. It writes ``ladder.md`` (the table), ``ladder.json`` and ``ladder.png``.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.experiments.config import resolve_path
from trafficrlhf_sdk.parallel import ExecutionConfig, ray_session
from trafficrlhf_sdk.reward.config import RewardConfig

if TYPE_CHECKING:
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe
    from trafficrlhf_sdk.pipeline.step import StepResult

__all__ = ["LADDER_ROWS", "LadderConfig", "run_ladder"]

LADDER_ROWS = {
    "a": ("built-in failure reward", "builtin:failure"),
    "b": ("stand-in judgment as reward", "builtin:judgment"),
    "c": ("learned reward model", None),
    "d": ("learned reward model, alpha = 0", None),
}
"""Row key -> (label, reward spec; None: the learned reward model)."""

METRICS = ("failure_rate", "collision_rate", "offroad_rate", "realism_ctg", "realism_body", "realism_meta",
           "speed_ratio", "stopped_share")


class LadderConfig(BaseModel):
    """What the ladder runs (``trafficrlhf experiment ladder --model M``)."""

    model_config = ConfigDict(extra="forbid")

    recipe: str = Field(description="The fine-tuning recipe every row shares (a TOML `AlignRecipe`; its reward is "
                                    "replaced row by row), relative to the working directory or the repository.")
    reward_model: str | None = Field(None, description="A learned reward-model folder for rows (c) and (d); None: "
                                     "train one on stand-in labels of the base model's candidates (below) and, "
                                     "with `rounds` above 1, of each round's policy.")
    campaigns: tuple[tuple[int, int], ...] = Field(
        ((200, 1), (400, 11), (442, 21)), min_length=1,
        description="The labelled train campaigns of the learned reward model, as (contexts, campaign seed): each "
                    "takes the first N long-enough train scenes (442 at most) and draws its own candidates, so "
                    "several campaigns label more contexts than there are scenes (the default: 1,042, those of "
                    "`reference_models/reward/ctg_ladder`).")
    candidates: int = Field(5, ge=2, le=9, description="Candidates per context (N).")
    seconds: float = Field(4.0, gt=0, description="Length of each candidate (s).")
    annotators: tuple[str, ...] = Field(("attentive", "safety", "flow"), min_length=1,
                                        description="Stand-in profiles that label every context.")
    agreement_seed: int = Field(0, ge=0, description="Campaign seed of the val contexts of the agreement check.")
    reward: RewardConfig = Field(default_factory=lambda: RewardConfig(learning_rate=1e-3, weight_decay=0.0,
                                                                      max_epochs=60),
                                 description="How the learned reward model trains.")
    contrast_scenes: int = Field(0, ge=0, description="Contrast items from the logs of the last N train scenes, "
                                 "labelled by the same stand-in profiles (0: none; the reward model then learns "
                                 "the labels of the model's candidates alone).")
    rounds: int = Field(1, ge=1, description="Rounds of the learned path: each round after the first labels "
                        "closed-loop contexts of the policy aligned against the previous round's reward model and "
                        "retrains it on every label so far (see the module docstring). Above 1 the reward model is "
                        "trained here, so `reward_model` must be unset.")
    round_contexts: int = Field(442, ge=1, description="Train contexts labelled in each round after the first: the "
                                "first N train scenes long enough for the closed-loop drive before the candidates "
                                "(fewer when fewer are); campaign seed of round r: the largest of `campaigns` + "
                                "10 r. Unused with `rounds` = 1.")
    probe_scenes: int = Field(40, ge=0, description="Val scenes the reward model's probes run on.")
    scenes: int = Field(100, ge=1, description="Val scenes of the closed-loop evaluation.")
    seeds: tuple[int, ...] = Field((0, 1, 2), min_length=1, description="Evaluation seeds.")
    rollouts: int = Field(1, ge=1, description="Rollouts per scene (2 or more add the realism meta-metric).")
    agreement_contexts: int = Field(60, ge=0, description="Val contexts of the policy's own candidates on which "
                                    "the reward model's agreement with the stand-in is measured (0: skip).")
    draws: int = Field(3, ge=1, description="Training draws of every row: draw i runs the recipe with the training "
                       "seed (the recipe's seed + i), so each row is reported as its mean over draws with their "
                       "spread; draw 0 is the recipe unchanged.")

    @model_validator(mode="after")
    def _check(self) -> LadderConfig:
        if self.rounds > 1 and self.reward_model is not None:
            raise ValueError(f"rounds={self.rounds} trains the reward model here each round, but reward_model "
                             f"(--reward-model) = {self.reward_model!r} is given; set rounds = 1 to use that model, "
                             "or leave reward_model unset.")
        return self


def run_ladder(config: LadderConfig, out_dir: str, log: Callable[[str], None] = print,
               overwrite: bool = False, execution: ExecutionConfig | None = None) -> dict[str, Any]:
    """Run (or resume) the ladder into ``out_dir``; returns the rows as written to ``ladder.json``.

    With ``execution`` on Ray, one Ray session serves the whole ladder: the rows' alignments (every row and draw is
    independent of the others once the reward model exists) run side by side, one per worker with the worker's
    torch threads (``threads_per_worker``, 1 by default: the numbers of an in-process run with ``--threads 1``),
    and the evaluations' rollouts and the campaigns' candidates run on the workers too. On an existing cluster
    (``ray_address``) the workers must see the driver's working directory and data on a shared file system."""
    on_ray = execution if execution is not None and execution.uses_ray else None
    with ray_session(on_ray or ExecutionConfig()):
        return _run_ladder(config, out_dir, log, overwrite, on_ray)


def _run_ladder(config: LadderConfig, out_dir: str, log: Callable[[str], None], overwrite: bool,
                on_ray: ExecutionConfig | None) -> dict[str, Any]:
    from trafficrlhf_sdk.experiments.steps import read_recipe
    from trafficrlhf_sdk.evaluation.runs import EvaluationRequest
    from trafficrlhf_sdk.feedback.synthetic import PROFILES
    from trafficrlhf_sdk.pipeline import evaluate_step, generate_step, label_step, reward_model_step

    steps = {"overwrite": overwrite, "log": log}
    recipe = read_recipe(config.recipe)
    guidance = recipe.align.guidance
    os.makedirs(out_dir, exist_ok=True)
    db = os.path.join(out_dir, "feedback.sqlite")

    def evaluate(label: str, checkpoint: str | None, after: list[Any]) -> Any:
        request = EvaluationRequest(model=recipe.model, checkpoint=checkpoint, guidance=guidance or "none",
                                    model_options=recipe.model_options, num_scenes=config.scenes,
                                    seeds=config.seeds, rollouts=config.rollouts,
                                    **({"execution": on_ray} if on_ray is not None else {}))
        return evaluate_step(os.path.join(out_dir, "evaluations", label), request, metrics=METRICS, after=after,
                             **steps)

    rows: dict[str, Any] = {"base": {"label": "base", "evaluation": evaluate("base", recipe.checkpoint, [])}}
    reward_model = config.reward_model
    learned: list[Any] = []
    if reward_model is None:
        reward_model, learned = _learn_reward_model(config, recipe, db, out_dir, steps, generate_step, label_step,
                                                    reward_model_step, PROFILES, on_ray)
    else:  # a given reward model: its weights stand in for the step that would have trained it
        reward_model = resolve_path(reward_model)
        learned = [_given_reward_model(reward_model)]
    # With alpha = 0 and no imitation term, what is left of the objective (the KL and the passing anchor to the
    # starting weights) is zero with a zero gradient there, so the weights never move: row (d) is the start itself.
    still = recipe.align.imitation_coef == 0
    jobs = []
    for draw in range(config.draws):
        seed = recipe.align.seed + draw
        for key, (_, spec) in LADDER_ROWS.items():
            if key == "d" and still:
                continue
            fields: dict[str, Any] = {"alpha": 0.0} if key == "d" else {}
            if draw:  # draw 0 is the recipe as written (and keeps its folders and digests)
                fields["seed"] = seed
            row = recipe.model_copy(update={"reward_model": spec or reward_model,
                                            "align": recipe.align.model_copy(update=fields)})
            # rows (a) and (b) read no learned reward: a retrained reward model leaves them done
            jobs.append(_AlignJob(key, draw, seed, os.path.join(out_dir, "rows", key + _suffix(draw, seed)), row,
                                  [] if spec else learned))
    aligned = _align_rows(jobs, overwrite, log, on_ray)
    for key, (label, spec) in LADDER_ROWS.items():
        if key == "d" and still:
            start = {"folder": recipe.checkpoint, "epochs": 0}
            rows[key] = {"label": f"{label}: the start", "reward": reward_model,
                         "note": "Row (d) is the starting model itself, not trained: with alpha = 0 the recipe "
                                 "has no term left but the KL and the passing anchor to the starting weights, "
                                 "which are zero with a zero gradient there.",
                         "align": start, "evaluation": rows["base"]["evaluation"],
                         "draws": [{"seed": recipe.align.seed + draw, "align": start,
                                    "evaluation": rows["base"]["evaluation"]} for draw in range(config.draws)]}
            continue
        draws = [{"seed": job.seed, "align": _summary(aligned[job.folder]),
                  "evaluation": evaluate(f"row_{key}{_suffix(job.draw, job.seed)}", aligned[job.folder]["folder"],
                                         [aligned[job.folder]])}
                 for job in jobs if job.key == key]
        rows[key] = {"label": label, "reward": spec or reward_model, "align": draws[0]["align"],
                     "evaluation": draws[0]["evaluation"], "draws": draws}
    if config.agreement_contexts:
        end = next(job for job in jobs if job.key == "c" and job.draw == 0)
        rows["agreement"] = {
            moment: _agreement(config, recipe, checkpoint, reward_model, db, out_dir, moment, steps, generate_step,
                               policy, on_ray)
            for moment, checkpoint, policy in (("start", recipe.checkpoint, []),
                                               ("end", rows["c"]["align"]["folder"], [aligned[end.folder]]))}
    _write(rows, config, out_dir)
    return rows


@dataclass(frozen=True)
class _AlignJob:
    """One row's alignment in one draw."""

    key: str
    draw: int
    seed: int
    folder: str
    recipe: AlignRecipe
    after: list[StepResult]


def _suffix(draw: int, seed: int) -> str:
    """The folder suffix of a draw: none for draw 0 (the recipe as written), ``_seed<S>`` for the others."""
    return f"_seed{seed}" if draw else ""


def _align_rows(jobs: list[_AlignJob], overwrite: bool, log: Callable[[str], None],
                execution: ExecutionConfig | None) -> dict[str, StepResult]:
    """Every job's alignment step, by folder: one after another in-process, or side by side on Ray workers
    (:func:`~trafficrlhf_sdk.pipeline.align_steps`; the control row (d) last, so the rows that move come first)."""
    import trafficrlhf_sdk.pipeline as pipeline

    order = jobs if execution is None else sorted(jobs, key=lambda job: (job.key == "d", job.draw, job.key))
    done = pipeline.align_steps([pipeline.AlignJob(job.folder, job.recipe, job.after) for job in order],
                                overwrite=overwrite, log=log, execution=execution)
    return {job.folder: result for job, result in zip(order, done, strict=True)}


def _learn_reward_model(config: LadderConfig, recipe: Any, db: str, out_dir: str, steps: dict[str, Any],
                        generate_step: Any, label_step: Any, reward_model_step: Any, profiles: dict[str, Any],
                        execution: ExecutionConfig | None) -> tuple[str, list[Any]]:
    """The product path: the base model's candidates on train contexts, stand-in labels, a reward model; with
    ``rounds`` above 1, then each round's closed-loop contexts of the policy the previous reward model aligned."""
    import trafficrlhf_sdk.pipeline as pipeline
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig

    annotators = {name: profiles[name] for name in config.annotators}
    labelled, names = [], []

    def label(campaign: CampaignConfig, after: list[Any]) -> None:
        folder = os.path.join(out_dir, "feedback", campaign.name)
        generated = generate_step(os.path.join(folder, "generate"), db, campaign, after=after, execution=execution,
                                  **steps)
        labelled.append(label_step(os.path.join(folder, "label"), db, campaign.name, annotators, after=[generated],
                                   **steps))
        names.append(campaign.name)

    for i, (contexts, seed) in enumerate(config.campaigns):
        label(CampaignConfig(name=f"ladder-train-{i}", model=recipe.model, guidance=recipe.align.guidance,
                             model_options={**recipe.model_options, "checkpoint": recipe.checkpoint},
                             split="train", num_contexts=contexts, num_candidates=config.candidates,
                             candidate_seconds=config.seconds, seed=seed), [])
    trained = None
    round_seed = max(seed for _, seed in config.campaigns)
    for r in range(config.rounds):
        if r > 0:  # the previous round's policy drives; its contexts are cut shortly before its own failures
            assert trained is not None
            row = recipe.model_copy(update={"reward_model": trained["folder"]})
            policy = pipeline.align_step(os.path.join(out_dir, "rounds", f"round_{r - 1}", "aligned"), row,
                                         after=[trained], execution=execution, **steps)
            label(CampaignConfig(name=f"ladder-round-{r}", model=recipe.model, guidance=recipe.align.guidance,
                                 model_options={**recipe.model_options, "checkpoint": policy["folder"]},
                                 split="train", num_contexts=config.round_contexts, num_candidates=config.candidates,
                                 candidate_seconds=config.seconds, seed=round_seed + 10 * r,
                                 contexts="closed_loop"), [policy])
        folder = os.path.join(out_dir, "reward_model") if r == 0 else \
            os.path.join(out_dir, "rounds", f"round_{r}", "reward_model")
        trained = reward_model_step(folder, config.reward, db, list(names), contrast_scenes=config.contrast_scenes,
                                    contrast_annotators=config.annotators if config.contrast_scenes else (),
                                    probe_scenes=config.probe_scenes, candidate_seconds=config.seconds,
                                    after=list(labelled),
                                    title=f"{recipe.model} reward model of the alignment ladder"
                                          + (f" (round {r})" if r else ""), **steps)
    assert trained is not None
    return trained["folder"], [trained]


def _weights(reward_model: str) -> dict[str, str]:
    """SHA-256 of each ``.safetensors`` file of a reward-model folder (empty for anything else)."""
    from trafficrlhf_sdk.models.checkpoint import sha256_file

    if not os.path.isdir(reward_model):
        return {}
    return {name: sha256_file(os.path.join(reward_model, name))
            for name in sorted(os.listdir(reward_model)) if name.endswith(".safetensors")}


def _given_reward_model(reward_model: str) -> Any:
    """A reward model given to the ladder, as the step rows (c) and (d) follow: other weights in the same folder
    make them run again."""
    from trafficrlhf_sdk.pipeline.step import StepResult, inputs_digest

    return StepResult("reward_model", reward_model, inputs_digest({"weights": _weights(reward_model)}),
                      {"folder": reward_model})


def _agreement(config: LadderConfig, recipe: Any, checkpoint: str | None, reward_model: str, db: str, out_dir: str,
               moment: str, steps: dict[str, Any], generate_step: Any, policy: list[Any],
               execution: ExecutionConfig | None) -> dict[str, Any]:
    """The reward model's agreement with the noise-free stand-in on val candidates of ``checkpoint`` (made by the
    ``policy`` step, if any). Both are redone when the policy or the reward model's weights change."""
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig
    from trafficrlhf_sdk.feedback.store import FeedbackStore
    from trafficrlhf_sdk.pipeline.step import run_step
    from trafficrlhf_sdk.reward.loading import load_reward
    from trafficrlhf_sdk.reward.oracle import judgment_agreement

    campaign = CampaignConfig(name=f"ladder-agreement-{moment}", model=recipe.model, guidance=recipe.align.guidance,
                              model_options={**recipe.model_options, "checkpoint": checkpoint}, split="val",
                              num_contexts=config.agreement_contexts, num_candidates=config.candidates,
                              candidate_seconds=config.seconds, seed=config.agreement_seed)
    folder = os.path.join(out_dir, "agreement", moment)
    generated = generate_step(os.path.join(folder, "generate"), db, campaign, after=policy, execution=execution,
                              **steps)

    def work() -> dict[str, Any]:
        store = FeedbackStore(db)
        try:
            return judgment_agreement(load_reward(reward_model), store, campaign.name)
        finally:
            store.close()

    weights = _weights(reward_model)
    inputs = {"campaign": campaign.name, "reward_model": reward_model, **({"weights": weights} if weights else {})}
    return dict(run_step("agreement", folder, inputs, work, after=[generated], **steps).outputs)


def _summary(aligned: Any) -> dict[str, Any]:
    outputs = dict(aligned.outputs)
    return {k: outputs[k] for k in ("folder", "epochs", "wall_time_s", "reward_first", "reward_last",
                                    "heldout_realism_first", "heldout_realism_last") if k in outputs}


def _plain_row(row: dict[str, Any]) -> dict[str, Any]:
    """A row with its evaluation steps' outputs in place of the steps (what ``ladder.json`` holds): ``align`` and
    ``evaluation`` are draw 0's, ``draws`` every draw's and ``mean`` the metrics' means over the draws."""
    plain = {**row, "evaluation": dict(row["evaluation"].outputs)}
    if "draws" in row:
        plain["draws"] = [{**d, "evaluation": dict(d["evaluation"].outputs)} for d in row["draws"]]
        plain["mean"] = _mean_metrics(plain)
    return plain


def _mean_metrics(row: dict[str, Any]) -> dict[str, float]:
    """The row's metrics, each the mean over its draws (the base: its one evaluation)."""
    runs = [d["evaluation"]["metrics"] for d in row.get("draws") or [row]]
    return {name: sum(float(r.get(name, float("nan"))) for r in runs) / len(runs) for name in runs[0]}


def _changes(row: dict[str, Any], base_failure: float) -> list[float]:
    """Each draw's failure-rate change against the base, in percent."""
    return [100 * (d["evaluation"]["metrics"]["failure_rate"] / max(base_failure, 1e-9) - 1)
            for d in row.get("draws") or [row]]


@functools.lru_cache(maxsize=64)
def _t_quantile(p: float, df: int) -> float:
    """The ``p`` quantile of Student's t with ``df`` degrees of freedom (``0.5 < p < 1``), by bisection on its
    distribution function (the density integrated with Simpson's rule); within 1e-4 of the exact value for the
    two-sided 90-99 % intervals used here (``p`` up to 0.995)."""
    import math

    if not 0.5 < p < 1 or df < 1:
        raise ValueError(f"_t_quantile needs 0.5 < p < 1 and df >= 1; got p={p}, df={df}.")
    log_norm = math.lgamma((df + 1) / 2) - math.lgamma(df / 2) - 0.5 * math.log(df * math.pi)

    def cdf_above_half(x: float, n: int = 2000) -> float:  # P(0 < T < x)
        h = x / n
        total = 0.0
        for i in range(n + 1):
            weight = 1 if i in (0, n) else (4 if i % 2 else 2)
            total += weight * math.exp(log_norm - (df + 1) / 2 * math.log1p((i * h) ** 2 / df))
        return total * h / 3

    low, high = 0.0, 1.0
    while cdf_above_half(high) < p - 0.5:
        high *= 2
    for _ in range(40):
        mid = (low + high) / 2
        low, high = (mid, high) if cdf_above_half(mid) < p - 0.5 else (low, mid)
    return (low + high) / 2


def _mean_interval(values: list[float]) -> tuple[float, float, float] | None:
    """Mean of ``values`` (one per draw) and its 95 % t-interval over draws; None for a single value."""
    import statistics

    if len(values) < 2:
        return None
    mean = statistics.fmean(values)
    half = _t_quantile(0.975, len(values) - 1) * statistics.stdev(values) / len(values) ** 0.5
    return mean, mean - half, mean + half


def _over_draws(values: list[float]) -> str:
    """``values`` (one per draw, in points) as their mean and 95 % t-interval over draws."""
    interval = _mean_interval(values)
    if interval is None:
        return f"{values[0]:+.1f}"
    return f"{interval[0]:+.1f} ({interval[1]:+.1f} to {interval[2]:+.1f})"


def _write(rows: dict[str, Any], config: LadderConfig, out_dir: str) -> None:
    """``ladder.json``, ``ladder.md`` and ``ladder.png``."""
    plain = {k: (v if k == "agreement" else _plain_row(v)) for k, v in rows.items()}
    with open(os.path.join(out_dir, "ladder.json"), "w") as fh:
        json.dump(plain, fh, indent=2, default=str)
    base = plain["base"]["evaluation"]["metrics"]
    keys = [k for k in plain if k not in ("base", "agreement")]
    draws = max((len(plain[k].get("draws") or [1]) for k in keys), default=1)
    over = "over draws (t)" if draws > 1 else "over scenes"
    lines = [f"# Alignment ladder ({config.recipe})", "",
             f"{config.scenes} val scenes, seeds {', '.join(map(str, config.seeds))}; every row runs the same "
             "fine-tuning recipe from the same start, only the reward differs"
             + (f"; each row is the mean of {draws} training draws (seeds "
                f"{', '.join(str(d['seed']) for d in plain[keys[0]]['draws'])})" if draws > 1 else "")
             + (f"; the learned reward model is round {config.rounds - 1}'s (closed-loop contexts of the policy "
                "each round aligned)." if config.rounds > 1 and not config.reward_model else "."), "",
             f"| row | failure (change) | each draw's change | 95 % interval {over} | collision | off-road | "
             "realism ctg / body | speed / log | stopped |", "|---|---|---|---|---|---|---|---|---|"]
    for key, row in plain.items():
        if key == "agreement":
            continue
        m = _mean_metrics(row)
        changes = [] if key == "base" else _changes(row, base["failure_rate"])
        change = f" ({100 * (m['failure_rate'] / max(base['failure_rate'], 1e-9) - 1):+.1f} %)" if changes else ""
        if not changes:
            interval = ""
        else:
            over_draws = _mean_interval(changes)
            interval = (f"{over_draws[1]:+.1f} % to {over_draws[2]:+.1f} %" if over_draws is not None
                        else _failure_interval(out_dir, "base", f"row_{key}"))
        each = " / ".join(f"{c:+.1f}" for c in changes) + (" %" if changes else "")
        lines.append(f"| {'' if key == 'base' else f'({key}) '}{row['label']} | {m['failure_rate']:.4f}{change} | "
                     f"{each} | {interval} | "
                     f"{m.get('collision_rate', float('nan')):.4f} | {m.get('offroad_rate', float('nan')):.4f} | "
                     f"{m.get('realism_ctg', float('nan')):.4f} / {m.get('realism_body', float('nan')):.4f} | "
                     f"{m.get('speed_ratio', float('nan')):.3f} | {m.get('stopped_share', float('nan')):.3f} |")
    lines += ["", row["note"]] if (row := plain.get("d", {})).get("note") else []
    links = [("the annotator", "a", "b"), ("the reward model", "b", "c"), ("the reward itself", "c", "d")]
    if all(k in plain for _, *pair in links for k in pair):
        lines += ["", "What each link of the chain loses: the failure change of the lower row minus that of the "
                  "upper one, in points" + (", mean over draws paired by training seed (95 % t-interval)"
                                            if draws > 1 else "") + ":", ""]
        for name, upper, lower in links:
            gaps = [b - a for a, b in zip(_changes(plain[upper], base["failure_rate"]),
                                          _changes(plain[lower], base["failure_rate"]))]
            lines.append(f"- {name}, ({upper}) to ({lower}): {_over_draws(gaps)}")
    if "agreement" in plain:
        a = plain["agreement"]
        lines += ["", "Reward model against the noise-free stand-in on the policy's own val candidates: "
                  f"{a['start']['agreement']:.3f} at the start ({a['start']['pairs']} pairs), "
                  f"{a['end']['agreement']:.3f} at the end ({a['end']['pairs']} pairs"
                  + (", row (c) of the first draw" if draws > 1 else "") + ")."]
        by_gap = a["end"].get("by_gap") or {}
        if by_gap:
            lines += ["", "At the end, on the pairs whose realism differs by more than a gap (pairs, agreement): "
                      + "; ".join(f"{gap}: {v['pairs']}, {v['agreement']:.3f}" for gap, v in by_gap.items()) + "."]
        terms = a["end"].get("by_term") or {}
        if terms:
            order = sorted(terms, key=lambda name: -terms[name]["pairs"])
            lines += ["", "At the end, by the judgment term that decides a pair (pairs, agreement): "
                      + "; ".join(f"{name} {terms[name]['pairs']}, {terms[name]['agreement']:.3f}" for name in order)
                      + "."]
    with open(os.path.join(out_dir, "ladder.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    _plot(plain, os.path.join(out_dir, "ladder.png"))


def _failure_interval(out_dir: str, before: str, after: str) -> str:
    """The failure rate's change from evaluation ``before`` to ``after`` (each pooled over its seeds) as a 95 %
    paired bootstrap interval over scenes; empty when their results do not name their scenes."""
    from trafficrlhf_sdk.evaluation.breakdown import paired_change_interval, pooled_per_scene
    from trafficrlhf_sdk.evaluation.compare import read_results, run_folders

    try:
        runs = [[read_results(f) for f in run_folders(os.path.join(out_dir, "evaluations", label))]
                for label in (before, after)]
        ci = paired_change_interval(*(pooled_per_scene(r, "failure_rate") for r in runs))
    except (TrafficRLHFError, ValueError, ZeroDivisionError):
        return ""
    return f"{100 * ci.low:+.1f} % to {100 * ci.high:+.1f} %"


def _plot(rows: dict[str, Any], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in rows if k != "agreement"]
    names = ["base" if k == "base" else f"({k}) {rows[k]['label']}" for k in keys]
    failure = [_mean_metrics(rows[k])["failure_rate"] for k in keys]
    draws = [[d["evaluation"]["metrics"]["failure_rate"] for d in rows[k].get("draws") or []] for k in keys]
    fig, ax = plt.subplots(figsize=(8, 3.4))
    ax.barh(range(len(keys)), failure, color=["#888888", "#4c72b0", "#55a868", "#c44e52", "#8172b2"][: len(keys)])
    for i, runs in enumerate(draws):  # each training draw of a row, over its bar
        if len(runs) > 1:
            ax.plot(runs, [i] * len(runs), "o", color="black", markersize=3.5, alpha=0.8)
    ax.set_yticks(range(len(keys)), names)
    ax.invert_yaxis()
    ax.set_xlabel("failure rate (closed loop, mean over evaluation seeds)")
    most = max(len(runs) for runs in draws)
    if most > 1:
        ax.set_title(f"bars: mean of {most} training draws; dots: each draw", fontsize=9)
    for i, value in enumerate(failure):
        ax.text(max([value, *draws[i]]), i, f"  {value:.3f}", va="center", fontsize=8)
    ax.set_xlim(0, 1.15 * max(max([v, *r]) for v, r in zip(failure, draws)))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
