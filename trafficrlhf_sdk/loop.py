"""Iterative RLHF: rounds of generate on the current policy -> label -> retrain the reward model -> align.

:func:`rlhf` (``trafficrlhf rlhf --config FILE.toml --out DIR``) runs the whole loop of the paper, repeated on
the policy it produces (iterated RLHF: a reward model is accurate near the data it saw, so each round collects
preferences where the newest policy drives):

1. **generate**: campaigns ``round<r>`` (and ``round<r>_unguided``) of ``contexts_per_round x candidate_pool``
   training contexts, each with N candidates from the current policy (the base in round 0, the previous round's
   aligned model after), with and without guidance (``unguided_share``), and the logged future hidden behind
   "none realistic";
2. **select** (rounds after the first): the items where the previous reward-model ensemble disagrees most are
   served first (:func:`~trafficrlhf_sdk.feedback.selection.rank_by_disagreement`), and ``contexts_per_round``
   of them are labelled;
3. **label**: by stand-in annotator profiles, or by people in the browser app (``people=True``: the loop waits
   until every served item has a label, and can be stopped and resumed meanwhile);
4. **reward model**: retrained on every round's labels (plus, with ``contrast_scenes``, contrast items from
   recorded driving that the same stand-in profiles label), saved with its model card and probe results;
5. **align**: the base model (every round starts from it, which is robust to a reward model's errors) is aligned
   against the new reward model with the alignment recipe.

Each stage is a step of :mod:`trafficrlhf_sdk.pipeline` with its folder under ``DIR/round_<r>/`` (``campaigns/<name>``,
``rank``, ``labels/<name>``, ``reward_model``, ``aligned``) and its ``step.json``; a rerun returns the finished steps
at once, so an interrupted loop resumes where it stopped, and a rerun with other settings is refused naming the
setting that differs (``overwrite=True``, ``--overwrite``: run those steps again). The campaigns of every round
live in ``DIR/feedback.sqlite``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from trafficrlhf_sdk.alignment.config import AlignConfig
from trafficrlhf_sdk.config_files import ONLY_SET_FIELDS, set_fields
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.parallel import ExecutionConfig, ray_session
from trafficrlhf_sdk.pipeline.step import StepResult
from trafficrlhf_sdk.reward.config import RewardConfig

__all__ = ["RLHFConfig", "rlhf"]

PROBE_PASS = 0.9  # a reward model should rank the log above each perturbation at least this often


class RLHFConfig(BaseModel):
    """One iterative RLHF run (``trafficrlhf rlhf --config FILE.toml``)."""

    model_config = ConfigDict(extra="forbid")

    model: str = Field("ctg", description="Registered traffic model.")
    checkpoint: str | None = Field(None, description="Base weights (a folder or a bundled checkpoint's name); "
                                                     "every round is aligned from them.")
    model_options: dict[str, Any] = Field(default_factory=dict, description="Adapter options of the model that is "
                                          "aligned (e.g. a zero-effect head to train); round 0's candidates come "
                                          "from the base without them.")
    guidance: str | None = Field("no_collision", description="Guidance of the candidates and of alignment.")
    rounds: int = Field(2, ge=1, description="Rounds of generate -> label -> reward model -> align.")
    contexts_per_round: int = Field(40, ge=2, description="Contexts labelled per round. Each round draws its "
                                    "scenes in order after the previous round's; past the last train scene it "
                                    "starts again from the first, and a scene drawn again gets new candidates (its "
                                    "own campaign and seed), so a round may label more contexts than there are "
                                    "scenes.")
    candidate_pool: int = Field(2, ge=1, description="Rounds after the first generate this many times more "
                                "contexts and label those the reward-model ensemble disagrees on most.")
    candidates: int = Field(5, ge=2, le=9, description="N candidate futures per context.")
    seconds: float = Field(4.0, gt=0, le=30, description="Length of each candidate (s).")
    unguided_share: float = Field(0.5, ge=0, le=1, description="Share of the contexts whose candidates are drawn "
                                  "without guidance (candidate sets that differ where it matters).")
    contexts: Literal["log", "closed_loop"] = Field("log", description="Where candidates start: after the "
                                                    "logged history, or after the round's policy drove the scene "
                                                    "itself, cut shortly before its first failure (preferences "
                                                    "where the policy gets into trouble).")
    annotators: list[str] = Field(default_factory=lambda: ["attentive", "safety", "flow"],
                                  description="Stand-in annotator profiles that label every round.")
    people: bool = Field(False, description="Wait for people to label each round in the browser app "
                                            "(`trafficrlhf feedback serve`) instead of stand-in annotators.")
    reward: Annotated[RewardConfig, ONLY_SET_FIELDS] = Field(
        default_factory=lambda: RewardConfig(ensemble_size=3, max_epochs=30),
        description="RewardConfig fields of the reward model (table [reward]; `seed` defaults to this config's).")
    contrast_scenes: int = Field(0, ge=0, description="Recorded train scenes (from the end of the split) whose "
                                 "logs, beside perturbed copies, make contrast items that the stand-in profiles "
                                 "label like any item (see `contrast_labels`); 0: none, the reward model learns "
                                 "the campaigns' labels alone.")
    contrast_labels: Literal["annotators", "log"] = Field(
        "annotators", description="Who decides each contrast item: the stand-in profiles of `annotators`, like any "
        "item (with `people`, the log wins), or 'log': the log wins every pair (which reproduces "
        "reference_models/reward/ctg_loop). The stand-ins label the contrast items with their profiles' own seeds, "
        "so every round reads the same contrast labels.")
    probe_scenes: int = Field(50, ge=0, description="Held-out val scenes the reward model is probed on; 0: none.")
    align: Annotated[AlignConfig, ONLY_SET_FIELDS] = Field(
        default_factory=AlignConfig, description="AlignConfig fields of the alignment stage (table [align]; "
                                                 "`guidance` and `seed` default to this config's).")
    reward_aggregation: Literal["mean", "worst", "lcb"] = Field("mean", description="How the fine-tuner reads the "
                                                                "ensemble: the members' mean, the worst member, or "
                                                                "mean - reward_pessimism x std.")
    reward_pessimism: float = Field(1.0, ge=0, description="k of the 'lcb' aggregation.")
    source: str = Field("nuscenes_pred", description="Scenario source (its 'train' split).")
    root: str | None = Field(None, description="Data directory of the source.")
    seed: int = Field(0, description="Seed of campaigns, annotators, reward models and alignment.")
    execution: ExecutionConfig = Field(default_factory=ExecutionConfig, description="Where the candidates and the "
                                       "alignment's samples are made: in-process or on Ray workers, with the same "
                                       "numbers; `trafficrlhf rlhf --workers N`.")


def rlhf(config: RLHFConfig, out_dir: str, log: Callable[[str], None] = print, poll_s: float = 10.0,
         overwrite: bool = False) -> dict[str, Any]:
    """Run (or resume) the loop of ``config`` in ``out_dir``; see the module docstring.

    Returns ``{"rounds": [...]}``, one entry per round: ``campaigns``, ``reward_model`` (folder), ``probes``,
    ``reward_metrics``, ``aligned`` (folder) and ``align`` (the alignment summary)."""
    from trafficrlhf_sdk.plugins import get_scenario_source

    os.makedirs(out_dir, exist_ok=True)
    db = os.path.join(out_dir, "feedback.sqlite")
    source = get_scenario_source(config.source, **({"root": config.root} if config.root else {}))
    train = source.scene_ids("train")
    if config.contrast_scenes:
        train = train[: max(0, len(train) - config.contrast_scenes)]  # the contrast logs stay out of campaigns
    with ray_session(config.execution):  # one Ray for every step of the run (nothing in-process)
        return _rounds(config, out_dir, db, train, log, poll_s, overwrite)


def _rounds(config: RLHFConfig, out_dir: str, db: str, train: list[str], log: Callable[[str], None],
            poll_s: float, overwrite: bool) -> dict[str, Any]:
    """The loop's rounds over the ``train`` scenes left for campaigns (see :func:`rlhf`)."""
    rounds: list[dict[str, Any]] = []
    labels: list[StepResult] = []  # every round's labelling so far: the reward model reads them all
    reward: StepResult | None = None
    used = 0
    for r in range(config.rounds):
        folder = os.path.join(out_dir, f"round_{r}")
        policy = config.checkpoint if r == 0 else rounds[-1]["aligned"]
        pool = config.contexts_per_round * (1 if r == 0 else config.candidate_pool)
        passes = _passes(train, used, pool)
        used += pool
        steps = {"overwrite": overwrite, "log": log}
        campaigns = [c for k, scenes in enumerate(passes) for c in _generate(config, db, r, k, policy, scenes, folder,
                                                                           steps)]
        if r > 0 and config.candidate_pool > 1 and reward is not None:
            from trafficrlhf_sdk.pipeline.stages import rank_step

            ranked = rank_step(os.path.join(folder, "rank"), db, [c["campaign"] for c in campaigns], reward["folder"],
                               after=[*campaigns, reward], **steps)
            _log_ranking(log, r, ranked)
            campaigns = [*campaigns, ranked]
        labels += _label(config, db, r, campaigns, folder, poll_s, steps)
        reward = _reward_model(config, db, r, labels, folder, steps)
        aligned = _align(config, r, reward, folder, steps)
        rounds.append({"campaigns": [c["campaign"] for c in campaigns if c.name == "generate"],
                       "reward_model": reward["folder"], "probes": reward["probes"],
                       "reward_metrics": reward["metrics"], "aligned": aligned["folder"], "align": aligned.outputs})
    return {"rounds": rounds}


def _passes(train: list[str], start: int, count: int) -> list[list[str]]:
    """The ``count`` scenes after the first ``start`` of ``train``, taken in order and from the start again once
    all are used, cut into passes in which no scene repeats (a scene drawn again gets new candidates)."""
    if not train:
        raise TrafficRLHFError("the train split has no scene left for campaigns; lower `contrast_scenes` or give "
                               "a source with more train scenes.")
    order = [train[(start + i) % len(train)] for i in range(count)]
    first = len(train) - start % len(train)
    cuts = [0, *range(first, count, len(train)), count]
    return [order[a:b] for a, b in zip(cuts, cuts[1:]) if b > a]


def _generate(config: RLHFConfig, db: str, r: int, k: int, policy: str | None, scenes: list[str], folder: str,
              steps: dict[str, Any]) -> list[StepResult]:
    """Campaigns ``round<r>`` (guided) and ``round<r>_unguided`` over ``scenes`` (split by ``unguided_share``);
    pass ``k`` > 0 over scenes drawn again names them ``round<r>_pass<k>`` and ``round<r>_pass<k>_unguided``."""
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig
    from trafficrlhf_sdk.pipeline.stages import generate_step

    split = round(len(scenes) * (1 - config.unguided_share)) if config.guidance else len(scenes)
    made: list[StepResult] = []
    stem = f"round{r}" if k == 0 else f"round{r}_pass{k}"
    for name, part, guidance in ((stem, scenes[:split], config.guidance), (f"{stem}_unguided", scenes[split:], None)):
        if not part:
            continue
        # round 0 samples the base as it is (a head added by `model_options` starts with zero effect); later
        # rounds load the previous round's aligned model, whose config.json carries its options
        options: dict[str, Any] = {"checkpoint": policy} if policy is not None else {}
        campaign = CampaignConfig(name=name, model=config.model, guidance=guidance, model_options=options,
                                  source=config.source, split="train", root=config.root, scene_ids=part,
                                  num_candidates=config.candidates, contexts=config.contexts,
                                  candidate_seconds=config.seconds, seed=config.seed + 1000 * r + 2 * k + len(made))
        done = generate_step(os.path.join(folder, "campaigns", name), db, campaign, execution=config.execution,
                             **steps)
        if not done.cached:
            steps["log"](f"round {r}: {done['contexts']} contexts of {name} ({config.model}, "
                         f"{'guidance ' + guidance if guidance else 'no guidance'}, {policy or 'bundled weights'})")
        made.append(done)
    return made


def _log_ranking(log: Callable[[str], None], r: int, ranked: StepResult) -> None:
    if ranked.cached:
        return
    if ranked["members"] < 2:
        log(f"round {r}: the reward model has one member; items are served in campaign order")
    for name, count in ranked["ranked"].items():
        log(f"round {r}: {name}: disagreement ranked {count} items (max {ranked['max_disagreement'][name]:.3f})")


def _label(config: RLHFConfig, db: str, r: int, campaigns: list[StepResult], folder: str, poll_s: float,
           steps: dict[str, Any]) -> list[StepResult]:
    """``contexts_per_round`` items labelled, shared among the round's campaigns by their sizes."""
    from trafficrlhf_sdk.feedback.synthetic import PROFILES
    from trafficrlhf_sdk.pipeline.stages import label_step

    unknown = [p for p in config.annotators if p not in PROFILES]
    if unknown and not config.people:
        raise TrafficRLHFError(f"annotator profiles {unknown} are unknown; use some of {sorted(PROFILES)}.")
    annotators = {p: PROFILES[p].model_copy(update={"seed": config.seed + r}) for p in config.annotators
                  if p in PROFILES}
    generated = [c for c in campaigns if c.name == "generate"]
    share = config.contexts_per_round / max(sum(c["contexts"] for c in generated), 1)
    done = []
    for campaign in generated:
        name = campaign["campaign"]
        wanted = max(1, round(share * campaign["contexts"]))
        labelled = label_step(os.path.join(folder, "labels", name), db, name, annotators, limit=wanted,
                              people=config.people, poll_s=poll_s, after=campaigns, **steps)
        for profile, counts in labelled.get("counts", {}).items():
            if not labelled.cached:
                steps["log"](f"round {r}: {profile} labelled {counts['labeled']} items of {name} "
                             f"({counts.get('none_realistic', 0)} 'none realistic', {counts.get('ties', 0)} ties)")
        done.append(labelled)
    return done


def _judged_contrast(config: RLHFConfig) -> bool:
    """Whether the stand-ins label the contrast items (otherwise the log wins each pair)."""
    return bool(config.contrast_scenes) and config.contrast_labels == "annotators" and not config.people


def _reward_model(config: RLHFConfig, db: str, r: int, labels: list[StepResult], folder: str,
                  steps: dict[str, Any]) -> StepResult:
    """The round's reward model, trained on every round's labels so far (and any contrast pairs), probed."""
    from trafficrlhf_sdk.pipeline.stages import reward_model_step

    settings = RewardConfig(**{"seed": config.seed + r, "progress": False, **set_fields(config.reward)})
    campaigns = [step["campaign"] for step in labels]
    reward = reward_model_step(
        os.path.join(folder, "reward_model"), settings, db, campaigns, val_fraction=0.15, split_seed=config.seed,
        contrast_scenes=config.contrast_scenes,
        contrast_annotators=config.annotators if _judged_contrast(config) else (),
        probe_scenes=config.probe_scenes, probe_judges=() if config.people else config.annotators, source=config.source,
        root=config.root, candidate_seconds=config.seconds, title=f"Reward model of RLHF round {r} ({config.model})",
        after=labels, **steps)
    if reward.cached:
        return reward
    probes = reward["probes"] or {}
    info = reward["dataset"]
    steps["log"](f"round {r}: reward model on {info['train_pairs']} pairs (+ {info.get('contrast_pairs', 0)} "
                 f"contrast): val accuracy {reward['metrics'].get('val_accuracy', float('nan')):.3f}"
                 + ("; probes " + ", ".join(f"{k} {v['pass_rate']:.2f}" for k, v in probes.items()) if probes else ""))
    for line in _probe_warnings(probes):
        steps["log"](f"round {r}: warning: {line}")
    return reward


def _probe_warnings(probes: dict[str, dict[str, Any]]) -> list[str]:
    """What a round's weak probes (pass rate below :data:`PROBE_PASS`) mean, one line per cause: the reward model
    missing what its stand-in annotators see (``judges`` pass), or the annotators not seeing it themselves."""
    weak = {k: v for k, v in probes.items() if v["pass_rate"] < PROBE_PASS}
    missed = {k: v for k, v in weak.items() if v.get("judges", 1.0) >= PROBE_PASS}
    unseen = {k: v for k, v in weak.items() if k not in missed}
    lines = []
    if missed:
        lines.append(f"the reward model ranks the log below its perturbation in more than {1 - PROBE_PASS:.0%} of "
                     "the probes for " + ", ".join(f"{k} ({v['pass_rate']:.2f})" for k, v in missed.items())
                     + "; PPO is likely to exploit that (more contrast scenes or a higher reward.contrast_weight "
                     "help)")
    if unseen:
        lines.append("the reward model ranks the log below its perturbation in more than "
                     f"{1 - PROBE_PASS:.0%} of the probes for "
                     + ", ".join(f"{k} ({v['pass_rate']:.2f}; the stand-in annotators {v['judges']:.3f})"
                                 for k, v in unseen.items())
                     + ": the annotators themselves do not prefer the log there, so their labels cannot teach it "
                     "(more contrast items will not help)")
    return lines


def _align(config: RLHFConfig, r: int, reward: StepResult, folder: str, steps: dict[str, Any]) -> StepResult:
    """The base model aligned against the round's reward model with the loop's alignment recipe."""
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe
    from trafficrlhf_sdk.pipeline.stages import align_step

    fields = {"guidance": config.guidance, "seed": config.seed + r, **set_fields(config.align)}
    recipe = AlignRecipe(model=config.model, checkpoint=config.checkpoint, model_options=config.model_options,
                         reward_model=reward["folder"], align=fields, reward_aggregation=config.reward_aggregation,
                         reward_pessimism=config.reward_pessimism)
    aligned = align_step(os.path.join(folder, "aligned"), recipe, after=[reward], execution=config.execution,
                         **steps)
    if not aligned.cached:
        summary = aligned.outputs
        steps["log"](f"round {r}: aligned {summary['model']} for {summary['epochs']} epochs in "
                     f"{summary['wall_time_s']:.0f} s; proxy reward {summary['reward_first']:.3f} -> "
                     f"{summary['reward_last']:.3f}, held-out realism {summary['heldout_realism_first']:.3f} -> "
                     f"{summary['heldout_realism_last']:.3f}")
    return aligned
