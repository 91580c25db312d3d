"""``AlignConfig``: the settings of the PPO fine-tuner (stage III), with the paper's defaults."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["PAPER_ALPHA", "AlignConfig", "paper_alpha"]

PAPER_ALPHA: dict[str, float] = {"ctg": 0.1, "bits": 0.5, "trafficgen": 0.3}
"""Weight of the PPO surrogate (the paper's alpha in r + alpha * r_HF) per traffic model."""

HISTORY_STEPS = 30
"""Logged steps kept before each context's start step (3 s at 0.1 s)."""
REWARD_HISTORY_STEPS = 10
"""History steps handed to the reward model in front of each sampled future."""
FAILURE_DRIVE_S = 10.0
"""Length of the closed-loop runs that find the current model's failures (the evaluation protocol's 10 s)."""
FAILURE_LEAD_STEPS = (5, 15)
"""A failure-focused context starts d steps before the agent's first failure, d uniform in this range."""
ADVANTAGE_CLIP = 5.0
"""Normalized advantages are clipped to +- this (as DDPO does)."""
MAX_GRAD_NORM = 1.0
"""Gradients are clipped to this norm before each optimizer step."""


def paper_alpha(model_name: str, default: float = 0.3) -> float:
    """The paper's alpha for ``model_name`` (``default`` for models the paper does not cover)."""
    return PAPER_ALPHA.get(model_name, default)


class AlignConfig(BaseModel):
    """How :class:`~trafficrlhf_sdk.alignment.AlignTrainer` fine-tunes a traffic model against a reward model.

    One *epoch* = a rollout phase (``contexts_per_epoch`` contexts, ``samples_per_context`` futures each, scored
    by the reward model) followed by ``ppo_epochs`` passes of minibatch updates over those samples. The loss of a
    minibatch is ``imitation_coef * imitation_loss - alpha * surrogate + kl_coef * KL`` (+ the passing anchor,
    ``- alpha * choice_coef * sum_c pi_c A_c``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    # ---------------------------------------------------------------- objective
    alpha: float = Field(0.3, ge=0, description="Weight of the PPO surrogate (paper: CTG 0.1, BITS 0.5, "
                                                "TrafficGen 0.3).")
    imitation_coef: float = Field(1.0, ge=0, description="Weight of the model's own imitation loss, the paper's r "
                                  "(0 disables it).")
    kl_coef: float = Field(0.0, ge=0, description="Weight of the k3 KL estimate to the frozen starting model "
                                                  "(0: no reference model is kept).")
    passing_anchor_coef: float = Field(0.0, ge=0, description="With credit='agent': agents none of whose samples "
                                       "in a context collides or leaves the road get advantage 0 and this weight "
                                       "times the KL to the starting model on their samples, so the surrogate "
                                       "moves only agents with a failing sample. 0 disables it.")
    choice_coef: float = Field(0.0, ge=0, description="With credit='agent', for adapters that offer "
                               "choice_futures (a mixture's modes): every agent's C discrete choices are scored by "
                               "the reward model at each context, and alpha times this weight times the exact "
                               "expected advantage over the choices, sum_c pi_c A_c, is added to the objective "
                               "(the reward's advantages normalized over the choices, without the pace term, which "
                               "would rank every agent's choices by speed; 0 for passing agents under "
                               "passing_anchor_coef). 0 disables it.")
    pace_tolerance: float | None = Field(None, gt=0, lt=1, description="Constrain the pace (PPO-Lagrangian, "
                                         "trafficrlhf_sdk.alignment.pace): keep the closed-loop speed / logged "
                                         "speed on fixed held-out scenes within this fraction of the starting "
                                         "model's; each sample's speed enters the advantage with a multiplier "
                                         "that grows while the pace is outside the band. None: no constraint.")
    pace_multiplier_lr: float = Field(5.0, gt=0, description="Step of the pace multipliers per unit of relative "
                                      "pace outside the band, per epoch (with pace_tolerance).")
    pace_multiplier_kp: float = Field(0.0, ge=0, description="Proportional gain of the pace multipliers (a PI "
                                      "Lagrangian): each epoch uses its accumulated multiplier plus this times the "
                                      "pace's current distance outside the band (negative inside it), at least 0. "
                                      "It damps the swings of a model whose pace answers the multiplier within a "
                                      "few epochs. 0: the plain Lagrangian.")
    pace_by_turning: bool = Field(False, description="With pace_tolerance and credit='agent': hold two bands, the "
                                  "pooled pace of the agents whose logged heading turns by more than 0.6 rad over "
                                  "the drive and that of the others, each with its own multipliers (a training "
                                  "sample's agent takes the turning band's when its logged window turns that "
                                  "much), so that slower turns cannot be paid for with faster straights.")
    target_kl: float | None = Field(None, gt=0, description="Stop an epoch's PPO passes once the approximate KL "
                                                            "to the sampling policy exceeds 1.5 x this.")
    clip_range: float = Field(0.2, gt=0, description="PPO ratio clip: ratios outside 1 +- clip_range get no "
                                                     "gradient when that would help.")
    denoising_steps: int | None = Field(None, ge=1, description="For adapters with per-step log-probabilities "
                                        "(B, S, A, K), use only the first N of the K steps in the surrogate and "
                                        "the KL terms (DDPO's timestep fraction). None: all steps.")
    credit: Literal["scene", "agent"] = Field("scene", description="'scene': one reward per sample, shared by "
                                              "its agents (the paper's scenario reward). 'agent': each sampled "
                                              "agent gets its own reward and advantage (needs a reward with "
                                              "`agent_scores`).")

    # ---------------------------------------------------------------- schedule
    epochs: int = Field(70, ge=1, description="Rollout + optimization rounds (paper: 70).")
    contexts_per_epoch: int = Field(16, ge=1, description="Contexts sampled per epoch.")
    samples_per_context: int = Field(4, ge=2, description="Futures drawn per context (S); advantages are "
                                                          "normalized among them.")
    ppo_epochs: int = Field(2, ge=1, description="Passes over an epoch's samples.")
    minibatch_contexts: int = Field(8, ge=1, description="Contexts per optimizer step (with all their samples).")
    learning_rate: float = Field(1e-4, ge=0, description="AdamW learning rate.")
    groups: tuple[str, ...] | None = Field(None, description="Parameter groups to train, from the adapter's "
                                                             "parameter_groups() (e.g. ('decoder',)); None: all "
                                                             "groups it offers.")

    # ---------------------------------------------------------------- rollouts
    guidance: str | None = Field(None, description="Guidance used while sampling, e.g. 'no_collision'.")
    failure_fraction: float = Field(0.0, ge=0, le=1, description="Share of each epoch's contexts cut shortly "
                                    "before a failure (collision or off-road) of the current model in a 10 s "
                                    "closed-loop run on `failure_scenes` training scenes; logged windows fill in "
                                    "when the run has fewer failures.")
    failure_scenes: int = Field(16, ge=1, description="Training scenes driven in closed loop per epoch to find "
                                                      "failures (`failure_fraction` > 0).")

    # ---------------------------------------------------------------- data
    source: str = Field("nuscenes_pred", description="Registered scenario source of the training contexts (its "
                                                     "'train' split; alignment never reads an evaluation split).")
    root: str | None = Field(None, description="Data directory of the source (None: the source's default).")
    num_scenes: int | None = Field(None, ge=1, description="First N long-enough training scenes; None: all.")
    holdout_every: int | None = Field(None, ge=2, description="Never train on every k-th long-enough training "
                                      "scene (a held-out set spread over the split, for choosing settings without "
                                      "the evaluation split). None: none held out.")
    mirror_scenes: bool = Field(False, description="Also train on every training scene mirrored across its x axis "
                                "(turns change sign): twice the roads.")

    # ---------------------------------------------------------------- bookkeeping
    seed: int = Field(0, description="Seed of every generator; each epoch's randomness is a function of "
                                     "(seed, epoch), so a resumed run matches an uninterrupted one.")
    output_dir: str | None = Field(None, description="Folder for logs and checkpoints; None: nothing is written.")
    save_every: int = Field(10, ge=1, description="Write a checkpoint every N epochs (and after the last).")
    early_stopping_patience: int | None = Field(None, ge=1, description="Stop once the held-out realism of the "
                                                "policy's own samples (stand-in annotators' judgment, smoothed, on "
                                                "fixed logged and failure-focused contexts of held-out scenes) has "
                                                "not improved for this many epochs, and keep the best weights "
                                                "(possibly the starting ones). None: train every epoch, keep the "
                                                "last.")
    resume: bool = Field(False, description="Continue from the newest intact checkpoint in output_dir (an error "
                         "when there is none).")
    resume_allow_changes: bool = Field(False, description="With `resume`, accept hyper-parameters that differ from "
                                       "the checkpoint's (recorded as `config_changes` with the epoch they apply "
                                       "from); by default a resume with changed settings is refused.")
    progress_bar: bool = Field(True, description="Show a progress bar over epochs and per-epoch statistics.")

    @model_validator(mode="after")
    def _check(self) -> AlignConfig:
        if self.resume and self.output_dir is None:
            raise ValueError("`resume=True` needs `output_dir` (the folder holding the checkpoints).")
        if self.pace_by_turning and (self.pace_tolerance is None or self.credit != "agent"):
            raise ValueError(f"`pace_by_turning` is set but `pace_tolerance` is {self.pace_tolerance} and `credit` "
                             f"is {self.credit!r}: it needs both a pace_tolerance and credit='agent'.")
        if self.passing_anchor_coef > 0 and self.credit != "agent":
            raise ValueError(f"`passing_anchor_coef` is {self.passing_anchor_coef} but `credit` is 'scene': a "
                             "passing agent is told apart from a failing one only with credit='agent'.")
        if self.choice_coef > 0 and self.credit != "agent":
            raise ValueError(f"`choice_coef` is {self.choice_coef} but `credit` is 'scene': each agent's choices "
                             "are scored apart only with credit='agent'.")
        if self.groups is not None and len(self.groups) == 0:
            raise ValueError("`groups` is empty: name at least one parameter group, or pass None for all.")
        return self
