"""``AlignConfig``: every knob of the PPO fine-tuner (stage III), with the paper's defaults."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["PAPER_ALPHA", "AlignConfig", "paper_alpha"]

PAPER_ALPHA: dict[str, float] = {"ctg": 0.1, "bits": 0.5, "trafficgen": 0.3}
"""Weight of the PPO surrogate (the paper's alpha in r + alpha * r_HF) per traffic model."""


def paper_alpha(model_name: str, default: float = 0.3) -> float:
    """The paper's alpha for ``model_name`` (``default`` for models the paper does not cover)."""
    return PAPER_ALPHA.get(model_name, default)


class AlignConfig(BaseModel):
    """How :class:`~trafficrlhf_sdk.alignment.AlignTrainer` fine-tunes a traffic model against a reward model.

    One *epoch* = a rollout phase (``contexts_per_epoch`` logged contexts, ``samples_per_context`` futures each,
    scored by the reward model) followed by ``ppo_epochs`` passes of minibatch updates over those samples.
    The loss of a minibatch is ``imitation_coef * imitation_loss - alpha * surrogate + kl_coef * KL``
    (``+ winner_coef * imitation_loss(best samples)`` when ``winner_coef > 0``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    # ---------------------------------------------------------------- objective
    alpha: float = Field(0.3, ge=0, description="Weight of the PPO surrogate (paper: CTG 0.1, BITS 0.5, "
                                                "TrafficGen 0.3).")
    imitation_coef: float = Field(1.0, ge=0, description="Weight of the model's own imitation loss (0 disables it).")
    winner_coef: float = Field(0.0, ge=0, description="Weight of the model's own imitation loss with each "
                               "context's best sample as the target (per agent with credit='agent'; the "
                               "highest-reward sample of the context with credit='scene'), for agents whose "
                               "samples' rewards spread by more than `winner_min_gap`: reward-ranked fine-tuning "
                               "(RAFT, expert iteration) beside the PPO surrogate, a low-variance pull towards "
                               "the futures the reward prefers. 0 disables it.")
    winner_min_gap: float = Field(0.0, ge=0, description="A context's (agent's) best sample is imitated only when "
                                  "its reward exceeds the worst sample's by more than this (ties teach nothing).")
    imitation_contexts: Literal["rollout", "log"] = Field("rollout", description="Windows the imitation loss "
                                                          "learns from: 'rollout', the epoch's contexts (failure-"
                                                          "focused ones included); 'log', as many fresh windows "
                                                          "drawn uniformly from the training log (InstructGPT's "
                                                          "PPO-ptx mix).")
    kl_coef: float = Field(0.0, ge=0, description="Weight of the k3 KL estimate to the frozen starting model "
                                                  "(0: no reference model is kept).")
    anchor_coef: float = Field(0.0, ge=0, description="Weight of a KL anchor to the frozen starting model on "
                               "contexts drawn uniformly from the training log each epoch (as many as "
                               "contexts_per_epoch, `anchor_samples` futures each): the k3 estimate of KL(current || "
                               "start) on the current model's samples there. The PPO contexts are mostly failure-"
                               "focused; the anchor holds the driving on ordinary roads, where nothing needs to "
                               "change. 0 disables it.")
    anchor_samples: int = Field(2, ge=1, description="Futures drawn per anchor context (anchor_coef > 0).")
    passing_anchor_coef: float = Field(0.0, ge=0, description="Weight of a KL anchor to the frozen starting model "
                                       "on the PPO samples of *passing* agents: sampled agents none of whose "
                                       "samples in a context collides or leaves the road over the scored steps. "
                                       "Their advantages are set to 0, so the surrogate moves only agents with a "
                                       "failing sample while the anchor holds the others where they were: a "
                                       "contrast inside each scene between agents that need a change and agents "
                                       "that do not. Needs credit='agent'. 0 disables it.")
    passing_margins: bool = Field(False, description="With passing_anchor_coef: an agent passes only if none of "
                                  "its samples comes near a failure either (a box corner off the drivable area, "
                                  "or a box grown by FailureReward's near-miss buffer overlapping another agent), "
                                  "so agents that graze an edge keep their push.")
    target_kl: float | None = Field(None, gt=0, description="Stop an epoch's PPO passes once the approximate KL "
                                                            "to the sampling policy exceeds 1.5 x this (SB3 rule).")
    clip_range: float = Field(0.2, gt=0, description="PPO ratio clip: ratios outside 1 +- clip_range get no "
                                                     "gradient when that would help.")
    denoising_steps: int | None = Field(None, ge=1, description="For adapters with per-step log-probabilities "
                                        "(B, S, A, K), use only the first N of the K steps in the surrogate and "
                                        "the KL terms (the noisiest ones, where a sample's outcome is decided; the "
                                        "last DDIM steps have a tiny sigma, so their ratios swing wildly). DDPO's "
                                        "timestep_fraction. None: all steps.")
    advantage_clip: float = Field(5.0, gt=0, description="Normalized advantages are clipped to +- this (DDPO).")
    advantage_eps: float = Field(1e-6, gt=0, description="Added to the reward std before dividing.")
    advantage_scale: Literal["group", "batch"] = Field(
        "group", description="What the centred rewards are divided by: 'group', each advantage group's own std "
        "(DDPO, GRPO), so a group whose samples differ by a hair gets advantages as large as one where a sample "
        "fails; 'batch', one std over the whole rollout's centred rewards (Dr. GRPO, Liu et al. 2025), so each "
        "group pushes in proportion to how much its samples' rewards differ.")

    # ---------------------------------------------------------------- schedule
    epochs: int = Field(70, ge=1, description="Rollout + optimization rounds (paper: 70).")
    contexts_per_epoch: int = Field(16, ge=1, description="Logged contexts sampled per epoch.")
    samples_per_context: int = Field(4, ge=2, description="Futures drawn per context (S); advantages are "
                                                          "normalized among them.")
    ppo_epochs: int = Field(2, ge=1, description="Passes over an epoch's samples.")
    minibatch_contexts: int = Field(8, ge=1, description="Contexts per optimizer step (with all their samples).")
    learning_rate: float = Field(1e-4, ge=0, description="AdamW learning rate (of the first epoch).")
    lr_schedule: Literal["constant", "linear"] = Field("constant", description="'linear': epoch e (from 0) "
                                                       "trains at learning_rate x (1 - e / epochs), down towards "
                                                       "0 as stable-baselines3's linear schedules do; damps the "
                                                       "epoch-to-epoch drift of the last epochs.")
    weight_decay: float = Field(0.0, ge=0, description="AdamW weight decay (trained parameters only).")
    max_grad_norm: float | None = Field(1.0, gt=0, description="Gradient-norm clip; None disables it.")
    groups: tuple[str, ...] | None = Field(None, description="Parameter groups to train, from the adapter's "
                                                             "parameter_groups() (e.g. ('decoder',)); None: all "
                                                             "groups it offers.")

    # ---------------------------------------------------------------- rollouts
    guidance: str | None = Field(None, description="Guidance spec used while sampling, e.g. 'no_collision'.")
    history_steps: int = Field(30, ge=1, description="Logged steps kept before each context's start step (3 s).")
    horizon: int | None = Field(None, ge=1, description="Future steps scored per sample; None: the model's "
                                                        "horizon.")
    closed_loop_fraction: float = Field(0.0, ge=0, le=1, description="Share of each epoch's contexts whose history "
                                        "comes from a closed-loop rollout of the current model (its own plan, "
                                        "with `guidance`) instead of the log: trains on the states the model "
                                        "reaches itself. Their imitation loss still uses the logged scene.")
    closed_loop_max_s: float = Field(6.0, gt=0, description="Longest closed-loop lead-in (s); each epoch draws a "
                                                            "multiple of 0.5 s up to this.")
    failure_fraction: float = Field(0.0, ge=0, le=1, description="Share of each epoch's contexts cut shortly "
                                    "before a failure (collision or off-road) of the current model in a "
                                    "closed-loop run on `failure_scenes` training scenes; the log fills in when "
                                    "the run has fewer failures.")
    perturb_fraction: float = Field(0.0, ge=0, le=1, description="Share of each epoch's contexts drawn from the "
                                    "log with every controlled agent's history moved rigidly off its logged "
                                    "path (`perturb_lateral_m`, `perturb_yaw_rad`): recovery states on every "
                                    "training road, not only on the roads of the failure drive (DART-style "
                                    "noise injection). Their imitation loss still uses the unperturbed log.")
    perturb_lateral_m: float = Field(1.0, ge=0, description="Largest sideways shift (m, across the agent's "
                                     "current heading) of a perturbed context; drawn uniformly in +- this.")
    perturb_yaw_rad: float = Field(0.15, ge=0, description="Largest heading change (rad) of a perturbed context, "
                                   "a rotation of the history about the agent's current position; uniform in "
                                   "+- this.")
    failure_scenes: int = Field(16, ge=1, description="Training scenes driven in closed loop per epoch to find "
                                                      "failures (`failure_fraction` > 0).")
    failure_drive_s: float = Field(10.0, gt=0, description="Length (s) of the closed-loop runs that find failures "
                                                           "(the evaluation protocol's 10 s).")
    failure_refresh_every: int = Field(1, ge=1, description="Drive the failure scenes in epochs 0, k, 2k, ... "
                                       "only and cut the epochs in between from the same run (other events, "
                                       "other leads): the drive is most of an epoch's rollout time, so k = 2 "
                                       "saves a good part of each second epoch, at the price of contexts up to "
                                       "k - 1 epochs stale. 1: a fresh drive every epoch.")
    failure_lead_steps: tuple[int, int] = Field((5, 15), description="A failure-focused context starts d steps "
                                                "before the agent's first failure, d uniform in this range.")
    failure_kinds: tuple[Literal["collision", "offroad"], ...] = Field(
        ("collision", "offroad"), description="Which closed-loop failures failure-focused contexts "
        "are cut before: ('collision',) aims the contexts at agents that collide (with simulated or replayed "
        "agents), ('offroad',) at agents that leave the road. The reward still scores both.")
    credit: Literal["scene", "agent"] = Field("scene", description="'scene': one reward per sample, shared by "
                                              "its agents (the paper's scenario reward). 'agent': each sampled "
                                              "agent gets its own reward and advantage (needs a reward model "
                                              "with `agent_scores`); sharper credit for models that sample "
                                              "agents independently given the context, such as CTG.")
    counterfactual_credit: bool = Field(False, description="With credit='agent': score sample k of an agent in "
                                        "a scenario where only that agent takes sample k and every other sampled "
                                        "agent keeps sample 0 (COMA-style counterfactual), instead of all agents "
                                        "taking sample k together. An agent's samples then differ in its own "
                                        "future only, so a collision between two simulated agents is charged to "
                                        "the one whose sample caused it. Costs one scenario per sampled agent "
                                        "and sample.")
    selection_credit: bool = Field(False, description="For models whose planner executes the best of K samples "
                                   "by its own score (BITS; CTG with a guidance): replace each sample's reward by "
                                   "its best-of-K return (`trafficrlhf_sdk.alignment.selection`) before the "
                                   "advantages, so PPO improves "
                                   "what the planner executes rather than single samples. Needs an adapter whose "
                                   "`selection_scores` ranks its samples; per agent with credit='agent' (exact "
                                   "for per-agent selection, an approximation under scene-level guidance), on "
                                   "the scene reward with credit='scene'.")
    speed_neutral_advantages: bool = Field(False, description="Regress, within each advantage group (context, "
                                           "or context and agent), the samples' rewards on their mean speed over "
                                           "the scored window and use the residuals, divided by the group's "
                                           "reward std: a sample no longer gains from being slower or faster "
                                           "than its siblings in a straight line. Removes a failure reward's lean "
                                           "to slower samples; with a stall term (realism-*) the lean is to faster "
                                           "ones, and removing it made the 4 s CTG stop (alignment results, "
                                           "session 15).")
    reward_horizon: int | None = Field(None, ge=1, description="Future steps each sample is scored over; a "
                                       "longer value than the model's horizon extends the sample at constant "
                                       "speed and heading (denser failure signal), a shorter one scores only "
                                       "the first steps of each sample (the imitation loss still sees the whole "
                                       "horizon); None: the horizon.")
    continuation_steps: int = Field(0, ge=0, description="> 0: score each sample by its closed-loop "
                                    "consequences. Its first `continuation_executed_steps` steps are executed, "
                                    "then the current model drives on for this many steps (replanning every 5 "
                                    "steps, `guidance`), and the reward scores that trajectory: the credit the "
                                    "evaluation protocol gives a plan, of which only 0.5 s is driven before the "
                                    "next replan. The continuations of a context's samples share their random "
                                    "numbers, so they differ by the executed steps alone. Costs one closed-loop "
                                    "run of that length per sample. 0: score the open-loop sample.")
    continuation_executed_steps: int = Field(5, ge=1, description="Steps of each sample executed before the "
                                             "continuation takes over (5 = one replan at 2 Hz).")
    continuation_weight: float = Field(1.0, ge=0, le=1, description="With `continuation_steps` > 0: the reward is "
                                       "this share of the continuation's score plus the rest of the open-loop "
                                       "sample's score.")
    reward_history_steps: int = Field(10, ge=0, description="History steps handed to the reward model in front "
                                                            "of the sampled future (it sees step_dt back).")
    log_reference: Literal["log", "context"] = Field("log", description="What a reward with `uses_log` "
                                                     "compares the samples with: 'log', the logged window; "
                                                     "'context', each context's own continuation (the model's "
                                                     "own driving in closed-loop and failure-focused "
                                                     "contexts): how every run before session 11 was trained, "
                                                     "kept to reproduce them.")

    # ---------------------------------------------------------------- data
    source: str = Field("nuscenes_pred", description="Registered scenario source of the training contexts.")
    split: str = Field("train", description="Split the contexts come from (never the evaluation split).")
    root: str | None = Field(None, description="Data directory of the source (None: the source's default).")
    num_scenes: int | None = Field(None, ge=1, description="First N long-enough scenes of the split; None: all.")
    holdout_every: int | None = Field(None, ge=2, description="Hold out every k-th long-enough scene of the split "
                                      "(positions k-1, 2k-1, ...; before `num_scenes` is applied): never trained "
                                      "on, spread over the whole split, for choosing settings "
                                      "(`scripts/align_dev_eval.py --holdout-every k`). None: none held out.")
    mirror_scenes: bool = Field(False, description="Also train on every training scene mirrored across its x axis "
                                "(`trafficrlhf_sdk.scenario.mirror_scenario`: turns change sign, right-hand "
                                "traffic becomes left-hand): twice the roads, and roads the base model never "
                                "imitated, for contexts and failure-focused drives alike. Held-out scenes stay "
                                "as recorded.")

    # ---------------------------------------------------------------- held-out evaluation
    eval_every: int | None = Field(None, ge=1, description="Every N epochs (and after the last), drive the "
                                   "held-out scenes in closed loop (10 s, `guidance`) and record eval_failure_rate "
                                   "and realism in the history (stable-baselines3's EvalCallback). Needs "
                                   "`holdout_every` or held-out scenes passed to the trainer. None: never.")
    eval_seeds: int = Field(2, ge=1, description="Sampling seeds per held-out evaluation (their mean is "
                                                 "recorded; one seed moves the failure rate by up to 0.04).")
    keep_best: bool = Field(False, description="End with the evaluated weights of the lowest held-out failure "
                            "rate instead of the last epoch's (needs `eval_every`).")

    # ---------------------------------------------------------------- bookkeeping
    seed: int = Field(0, description="Seed of every generator (contexts, sampling, minibatch order, imitation "
                                     "noise); each epoch's randomness is a function of (seed, epoch).")
    output_dir: str | None = Field(None, description="Folder for logs and checkpoints; None: nothing is written.")
    save_every: int = Field(10, ge=1, description="Write a checkpoint every N epochs (and after the last).")
    save_total_limit: int | None = Field(2, ge=1, description="Keep only the newest N checkpoints; None keeps all.")
    resume: bool = Field(False, description="Continue from the newest checkpoint in output_dir if there is one.")
    log_formats: tuple[Literal["stdout", "csv", "tensorboard", "json", "log"], ...] = Field(
        ("stdout", "csv", "tensorboard"),
        description="stable-baselines3 logger outputs (tensorboard is skipped if it is not installed)."
    )
    progress_bar: bool = Field(True, description="Show a tqdm progress bar over epochs.")

    @model_validator(mode="after")
    def _check(self) -> AlignConfig:
        if self.split in ("val", "test"):
            raise ValueError(f"`split` is {self.split!r}: alignment must not train on an evaluation split; use "
                             "'train'.")
        if self.resume and self.output_dir is None:
            raise ValueError("`resume=True` needs `output_dir` (the folder holding the checkpoints).")
        lo, hi = self.failure_lead_steps
        if not 1 <= lo <= hi:
            raise ValueError(f"`failure_lead_steps` is {self.failure_lead_steps}; give (low, high) with "
                             "1 <= low <= high, e.g. (5, 15).")
        shares = self.failure_fraction + self.closed_loop_fraction + self.perturb_fraction
        if shares > 1 + 1e-9:
            raise ValueError(f"`failure_fraction` ({self.failure_fraction}) + `closed_loop_fraction` "
                             f"({self.closed_loop_fraction}) + `perturb_fraction` ({self.perturb_fraction}) "
                             "exceed 1; lower one of them.")
        if self.keep_best and self.eval_every is None:
            raise ValueError("`keep_best=True` needs `eval_every` (how often the held-out scenes are driven), "
                             "e.g. eval_every=10.")
        if self.counterfactual_credit and self.credit != "agent":
            raise ValueError("`counterfactual_credit=True` needs `credit='agent'` (it changes how each agent's "
                             "samples are scored).")
        if self.passing_anchor_coef > 0 and self.credit != "agent":
            raise ValueError(f"`passing_anchor_coef` is {self.passing_anchor_coef} but `credit` is 'scene': a "
                             "passing agent is told apart from a failing one only with credit='agent'.")
        if self.passing_margins and self.passing_anchor_coef == 0:
            raise ValueError("`passing_margins=True` changes which agents the passing anchor holds, but "
                             "`passing_anchor_coef` is 0; set it (e.g. 1.0) or drop passing_margins.")
        if self.continuation_steps and self.continuation_executed_steps > (self.horizon or 10**9):
            raise ValueError(f"`continuation_executed_steps` ({self.continuation_executed_steps}) exceeds `horizon` "
                             f"({self.horizon}): a sample cannot execute more steps than it holds; lower it.")
        if self.selection_credit and (self.counterfactual_credit or self.speed_neutral_advantages):
            raise ValueError("`selection_credit=True` cannot be combined with `counterfactual_credit` or "
                             "`speed_neutral_advantages` (each redefines the samples' returns); choose one.")
        if self.continuation_steps and self.counterfactual_credit:
            raise ValueError("`continuation_steps` and `counterfactual_credit=True` cannot be combined (a "
                             "continuation moves every sampled agent); choose one.")
        if not self.failure_kinds:
            raise ValueError("`failure_kinds` is empty: name 'collision', 'offroad' or both.")
        if self.groups is not None and len(self.groups) == 0:
            raise ValueError("`groups` is empty: name at least one parameter group, or pass None for all.")
        return self
