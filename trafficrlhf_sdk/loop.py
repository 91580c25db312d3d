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
4. **reward model**: retrained on every round's labels plus automatic contrast pairs from recorded driving,
   saved with its model card and probe results;
5. **align**: the base model (every round starts from it, which is robust to a reward model's errors) is aligned
   against the new reward model with the alignment recipe.

Every step writes its outputs under ``DIR/round_<r>/`` and records itself in ``DIR/state.json``; a rerun skips
the steps already done, so an interrupted loop resumes where it stopped.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from trafficrlhf_sdk.alignment.config import AlignConfig
from trafficrlhf_sdk.config_files import ONLY_SET_FIELDS, set_fields
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.reward.config import RewardConfig

__all__ = ["RLHFConfig", "rlhf"]

STATE_FILE = "state.json"
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
    contexts_per_round: int = Field(40, ge=2, description="Contexts labelled per round.")
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
    contrast_scenes: int = Field(120, ge=0, description="Recorded train scenes (from the end of the split) whose "
                                 "logs give automatic contrast pairs; 0: none.")
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


def _load_state(out_dir: str) -> dict[str, Any]:
    path = os.path.join(out_dir, STATE_FILE)
    if not os.path.isfile(path):
        return {"done": []}
    with open(path, encoding="utf-8") as handle:
        return json.load(handle)


def _save_state(out_dir: str, state: dict[str, Any]) -> None:
    tmp = os.path.join(out_dir, STATE_FILE + ".tmp")
    with open(tmp, "w", encoding="utf-8") as handle:
        json.dump(state, handle, indent=1)
    os.replace(tmp, os.path.join(out_dir, STATE_FILE))


def rlhf(config: RLHFConfig, out_dir: str, log: Callable[[str], None] = print,
         poll_s: float = 10.0) -> dict[str, Any]:
    """Run (or resume) the loop of ``config`` in ``out_dir``; returns the state (each round's reward model,
    aligned model and figures). See the module docstring."""
    from trafficrlhf_sdk.plugins import get_scenario_source
    from trafficrlhf_sdk.feedback.store import FeedbackStore

    os.makedirs(out_dir, exist_ok=True)
    state = _load_state(out_dir)
    saved = state.get("config")
    if saved is not None and saved != config.model_dump(mode="json"):
        raise TrafficRLHFError(f"{out_dir!r} holds a loop run with another configuration; use a new --out folder "
                               "or the same configuration to resume.")
    state["config"] = config.model_dump(mode="json")
    _save_state(out_dir, state)
    store = FeedbackStore(os.path.join(out_dir, "feedback.sqlite"))
    source = get_scenario_source(config.source, **({"root": config.root} if config.root else {}))
    train = source.scene_ids("train")
    if config.contrast_scenes:
        train = train[: max(0, len(train) - config.contrast_scenes)]  # the contrast logs stay out of campaigns
    used = 0
    for r in range(config.rounds):
        folder = os.path.join(out_dir, f"round_{r}")
        os.makedirs(folder, exist_ok=True)
        policy = config.checkpoint if r == 0 else os.path.join(out_dir, f"round_{r - 1}", "aligned")
        pool = config.contexts_per_round * (1 if r == 0 else config.candidate_pool)
        scenes = train[used: used + pool]
        used += pool
        if len(scenes) < pool:
            raise TrafficRLHFError(f"round {r} needs {pool} new train scenes but only {len(scenes)} are left; lower "
                                   "`contexts_per_round`, `candidate_pool` or `rounds`.")
        campaigns = _generate(config, store, r, policy, scenes, state, out_dir, log)
        if r > 0 and config.candidate_pool > 1:
            _select(config, store, campaigns, os.path.join(out_dir, f"round_{r - 1}", "reward_model"), r, state,
                    out_dir, log)
        _label(config, store, campaigns, r, state, out_dir, log, poll_s)
        every = [c for k in range(r + 1) for c in state.get(f"campaigns_{k}", [])]
        _reward_model(config, out_dir, every, folder, r, state, log)
        _align(config, folder, r, state, out_dir, log)
    store.close()
    return state


def _done(state: dict[str, Any], step: str) -> bool:
    return step in state["done"]


def _mark(state: dict[str, Any], out_dir: str, step: str, **info: Any) -> None:
    state["done"].append(step)
    state.update(info)
    _save_state(out_dir, state)


def _generate(config: RLHFConfig, store: Any, r: int, policy: str | None, scenes: list[str], state: dict[str, Any],
              out_dir: str, log: Callable[[str], None]) -> list[str]:
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig, create_campaign

    step = f"round_{r}/generate"
    names = [f"round{r}", f"round{r}_unguided"]
    if _done(state, step):
        return state[f"campaigns_{r}"]
    split = round(len(scenes) * (1 - config.unguided_share)) if config.guidance else len(scenes)
    made = []
    for name, part, guidance in ((names[0], scenes[:split], config.guidance), (names[1], scenes[split:], None)):
        if not part:
            continue
        if name in {c.name for c in store.campaigns()}:  # a generation interrupted midway: start it again
            raise TrafficRLHFError(f"campaign {name!r} exists but round {r}'s generation was not finished; delete "
                                   f"{os.path.join(out_dir, 'feedback.sqlite')} or use a new --out folder.")
        # round 0 samples the base as it is (a head added by `model_options` starts with zero effect); later
        # rounds load the previous round's aligned model, whose config.json carries its options
        options: dict[str, Any] = {}
        if policy is not None:
            options["checkpoint"] = policy
        log(f"round {r}: {len(part)} contexts of {name} ({config.model}, "
            f"{'guidance ' + guidance if guidance else 'no guidance'}, {policy or 'bundled weights'})")
        create_campaign(store, CampaignConfig(
            name=name, model=config.model, guidance=guidance, model_options=options, source=config.source,
            split="train", root=config.root, scene_ids=part, num_candidates=config.candidates, contexts=config.contexts,
            candidate_seconds=config.seconds, seed=config.seed + 1000 * r + len(made)))
        made.append(name)
    _mark(state, out_dir, step, **{f"campaigns_{r}": made})
    return made


def _select(config: RLHFConfig, store: Any, campaigns: list[str], reward_dir: str, r: int, state: dict[str, Any],
            out_dir: str, log: Callable[[str], None]) -> None:
    from trafficrlhf_sdk.feedback.selection import rank_by_disagreement
    from trafficrlhf_sdk.reward.model import RewardModel

    step = f"round_{r}/select"
    if _done(state, step):
        return
    model = RewardModel.from_pretrained(reward_dir).eval()
    members = list(getattr(model, "members", [])) or [model]
    if len(members) < 2:
        log(f"round {r}: the reward model has one member; items are served in campaign order")
    else:
        for name in campaigns:
            scores = rank_by_disagreement(store, name, [m.score for m in members])
            log(f"round {r}: {name}: disagreement ranked {len(scores)} items (max {max(scores.values()):.3f})")
    _mark(state, out_dir, step)


def _label(config: RLHFConfig, store: Any, campaigns: list[str], r: int, state: dict[str, Any], out_dir: str,
           log: Callable[[str], None], poll_s: float) -> None:
    from trafficrlhf_sdk.feedback.synthetic import PROFILES, SyntheticAnnotator

    step = f"round_{r}/label"
    if _done(state, step):
        return
    total = sum(len(store.context_keys(store.campaign(c))) for c in campaigns)
    share = config.contexts_per_round / max(total, 1)
    for name in campaigns:
        campaign = store.campaign(name)
        wanted = max(1, round(share * len(store.context_keys(campaign))))
        if config.people:
            log(f"round {r}: waiting for people to label {wanted} items of {name} (`trafficrlhf feedback serve "
                f"--db {os.path.join(out_dir, 'feedback.sqlite')}`); stop and rerun to resume")
            while len({lab.context_id for lab in store.labels(campaign)}) < wanted:
                time.sleep(poll_s)
            continue
        for profile in config.annotators:
            if profile not in PROFILES:
                raise TrafficRLHFError(f"annotator profile {profile!r} is unknown; use one of {sorted(PROFILES)}.")
            settings = PROFILES[profile].model_copy(update={"seed": config.seed + r})
            counts = SyntheticAnnotator(store, profile, settings).label(campaign, limit=wanted)
            log(f"round {r}: {profile} labelled {counts['labeled']} items of {name} ({counts['none_realistic']} "
                f"'none realistic', {counts['ties']} ties)")
    _mark(state, out_dir, step)


def _reward_model(config: RLHFConfig, out_dir: str, campaigns: list[str], folder: str, r: int,
                  state: dict[str, Any], log: Callable[[str], None]) -> None:
    from trafficrlhf_sdk.reward import RewardTrainer
    from trafficrlhf_sdk.reward.contrast import contrast_dataset, probe_reward_model, recorded_windows
    from trafficrlhf_sdk.reward.evaluation import load_preferences

    step = f"round_{r}/reward_model"
    if _done(state, step):
        return
    dataset, _ = load_preferences(os.path.join(out_dir, "feedback.sqlite"), campaigns, val_fraction=0.15,
                                  seed=config.seed)
    contrast = None
    if config.contrast_scenes:
        contrast = contrast_dataset(recorded_windows(config.source, "train", config.contrast_scenes, config.root,
                                                     from_end=True, future_steps=round(config.seconds * 10)))
    settings = RewardConfig(**{"seed": config.seed + r, "progress": False, **set_fields(config.reward)})
    trainer = RewardTrainer(settings, train_dataset=dataset, contrast_dataset=contrast)
    result = trainer.train()
    card: dict[str, Any] = {"metrics": dict(result.metrics),
                            "title": f"Reward model of RLHF round {r} ({config.model})",
                            "data": {**result.model.card_info.get("data", {}), "campaigns": campaigns,
                                     "annotators": config.annotators if not config.people else "people",
                                     "contrast_pairs": trainer.dataset_info.get("contrast_pairs", 0)}}
    probes = None
    if config.probe_scenes:
        probes = probe_reward_model(result.model.eval(), recorded_windows(config.source, "val",
                                                                          config.probe_scenes, config.root))
        card["metrics"].update({f"probe_{kind}": entry["pass_rate"] for kind, entry in probes.items()})
    path = os.path.join(folder, "reward_model")
    result.model.save_pretrained(path, card)
    log(f"round {r}: reward model on {trainer.dataset_info['train_pairs']} pairs (+ "
        f"{trainer.dataset_info.get('contrast_pairs', 0)} contrast): val accuracy "
        f"{result.metrics.get('val_accuracy', float('nan')):.3f}"
        + ("; probes " + ", ".join(f"{k} {v['pass_rate']:.2f}" for k, v in probes.items()) if probes else ""))
    weak = {k: v["pass_rate"] for k, v in (probes or {}).items() if v["pass_rate"] < PROBE_PASS}
    if weak:
        log(f"round {r}: warning: the reward model ranks the log below its perturbation in more than "
            f"{1 - PROBE_PASS:.0%} of the probes for " + ", ".join(f"{k} ({v:.2f})" for k, v in weak.items())
            + "; PPO is likely to exploit that (more contrast scenes or a higher reward.contrast_weight help)")
    _mark(state, out_dir, step, **{f"reward_model_{r}": path, f"probes_{r}": probes,
                                   f"reward_metrics_{r}": result.metrics})


def _align(config: RLHFConfig, folder: str, r: int, state: dict[str, Any], out_dir: str,
           log: Callable[[str], None]) -> None:
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe, run_recipe

    step = f"round_{r}/align"
    if _done(state, step):
        return
    fields = {"guidance": config.guidance, "seed": config.seed + r, **set_fields(config.align)}
    recipe = AlignRecipe(model=config.model, checkpoint=config.checkpoint, model_options=config.model_options,
                         reward_model=os.path.join(folder, "reward_model"), align=fields,
                         reward_aggregation=config.reward_aggregation, reward_pessimism=config.reward_pessimism)
    summary = run_recipe(recipe, os.path.join(folder, "aligned"))
    log(f"round {r}: aligned {summary['model']} for {summary['epochs']} epochs in {summary['wall_time_s']:.0f} s; "
        f"proxy reward {summary['reward_first']:.3f} -> {summary['reward_last']:.3f}, held-out realism "
        f"{summary['heldout_realism_first']:.3f} -> {summary['heldout_realism_last']:.3f}")
    _mark(state, out_dir, step, **{f"aligned_{r}": os.path.join(folder, "aligned"), f"align_{r}": summary})
