"""``PaperConfig``: everything ``trafficrlhf experiment paper`` runs, every nested section typed.

The alignment recipes are :class:`~trafficrlhf_sdk.alignment.AlignConfig` fields and the reward-model settings
:class:`~trafficrlhf_sdk.reward.RewardConfig` fields, so a misspelled key in an experiment file fails when it is
loaded, naming its path (``align_bits.learnig_rate``).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from trafficrlhf_sdk.alignment.config import AlignConfig
from trafficrlhf_sdk.config_files import ONLY_SET_FIELDS
from trafficrlhf_sdk.reward.config import RewardConfig

__all__ = ["GUIDANCES", "TABLES", "PaperConfig"]

TABLES = ("table1", "table2", "table3", "table4", "figure3")
GUIDANCES = ("speed_limit", "target_speed", "no_collision", "no_offroad", "goal_waypoint")

AlignSection = Annotated[AlignConfig, ONLY_SET_FIELDS]
RewardSection = Annotated[RewardConfig, ONLY_SET_FIELDS]

# the [align] sections of the loop recipes (BITS, TrafficGen) and of docs/recipes/ctg-rlhf.toml without the
# steering head (CTG); see PaperConfig.align_ctg for the one setting that differs
ALIGN_BITS = {"alpha": 3.0, "kl_coef": 0.05, "learning_rate": 2e-4, "ppo_epochs": 4, "minibatch_contexts": 4,
              "epochs": 20, "contexts_per_epoch": 16, "samples_per_context": 8, "failure_fraction": 0.75,
              "failure_scenes": 24, "credit": "agent", "holdout_every": 10, "early_stopping_patience": 6}
ALIGN_TRAFFICGEN = {"alpha": 6.0, "kl_coef": 0.05, "epochs": 20, "contexts_per_epoch": 16, "samples_per_context": 8,
                    "failure_fraction": 0.75, "failure_scenes": 24, "credit": "agent", "holdout_every": 10,
                    "early_stopping_patience": 6}
ALIGN_CTG = {"alpha": 3.0, "imitation_coef": 0.0, "passing_anchor_coef": 1.0, "denoising_steps": 4,
             "learning_rate": 1e-4, "epochs": 20, "contexts_per_epoch": 16, "samples_per_context": 8,
             "failure_fraction": 0.75, "failure_scenes": 24, "credit": "agent", "holdout_every": 10,
             "early_stopping_patience": 6}
QUICK_ALIGN = {"epochs": 1, "contexts_per_epoch": 2, "samples_per_context": 2, "ppo_epochs": 1,
               "minibatch_contexts": 2, "failure_fraction": 0.5, "failure_scenes": 4, "num_scenes": 4,
               "holdout_every": None, "early_stopping_patience": None}



class PaperConfig(BaseModel):
    """Everything ``trafficrlhf experiment paper`` runs; :meth:`quick` is the small form CI runs."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # > what and where
    label: str = Field("full", description="Name of this configuration, recorded with every result ('full', "
                                           "'quick').")
    only: tuple[Literal["table1", "table2", "table3", "table4", "figure3"], ...] = Field(
        TABLES, min_length=1, description="Tables and figures to produce, in this order.")
    source: str = Field("nuscenes_pred", description="Registered scenario source (val: evaluation, train: feedback "
                                                     "and alignment).")
    root: str | None = Field(None, description="Data directory of the source; None: its default.")
    # > evaluation protocol
    scenes: int = Field(100, ge=1, description="First N long-enough val scenes, sorted by name.")
    rollouts: int = Field(3, ge=1, description="Closed-loop rollouts per scene (metrics pooled over them); K >= 2 "
                                              "adds the realism meta-metric at that K.")
    seed: int = Field(0, description="Seed of evaluation, campaigns, annotators, reward models and alignment.")
    batch_size: int = Field(50, ge=1, description="Scenes simulated per policy batch.")
    threads: int | None = Field(None, ge=1, description="torch threads (None: torch's default).")
    progress: bool = Field(True, description="Progress bars for simulation and alignment.")
    guidance: str | None = Field("no_collision", description="Guidance of Tables 2-4 (sampling, alignment, "
                                                             "evaluation).")
    guidances: tuple[str, ...] = Field(GUIDANCES, min_length=1, description="Guidances of Table 1.")
    # > models
    ctg_base: str = Field("ctg-4s", description="CTG's weights (a bundled checkpoint's name or a folder).")
    ctg_aligned: str = Field("ctg-aligned", description="CTG + RM: the checkpoint aligned by the RLHF loop.")
    bits: str = Field("bits", description="BITS's weights.")
    trafficgen: str = Field("trafficgen-4s", description="TrafficGen's weights.")
    reward_model: str = Field("reference_models/reward/ctg_loop", description="The reward model of Tables 1-3 "
                              "(trained on CTG candidates); a folder, relative to the working directory or to the "
                              "repository.")
    reward_aggregation: Literal["mean", "worst", "lcb"] = Field("lcb", description="How the fine-tuner reads an "
                                                                "ensemble reward model (one member: 'mean').")
    # > alignment recipes (AlignConfig fields)
    align_bits: AlignSection = Field(default_factory=lambda: AlignConfig(**ALIGN_BITS), description="BITS + RM "
                                     "recipe (the loop recipe's [align]).")
    align_trafficgen: AlignSection = Field(default_factory=lambda: AlignConfig(**ALIGN_TRAFFICGEN),
                                           description="TrafficGen + RM recipe (the loop recipe's [align]).")
    align_ctg: AlignSection = Field(default_factory=lambda: AlignConfig(**ALIGN_CTG), description="Table 3's recipe: "
                                      "docs/recipes/ctg-rlhf.toml's [align] without the steering head, at the "
                                      "AlignConfig default learning rate 1e-4 (the recipe's 1e-3 is for a fresh "
                                      "zero-effect head, too large a step for pretrained networks).")
    table3_groups: dict[str, list[str] | None] = Field(
        default_factory=lambda: {"encoder": ["encoder"], "decoder": ["decoder"], "full": None},
        description="Table 3's variants: name -> CTG parameter groups trained (None: all).")
    align_overrides: AlignSection = Field(default_factory=AlignConfig, description="AlignConfig fields applied to "
                                          "every alignment over its recipe (the quick form's small sizes).")
    # > Table 4: feedback over three models and two reward-model backbones
    feedback_contexts: int = Field(48, ge=1, description="Labelled train contexts of Table 4's feedback set.")
    feedback_models: list[str] = Field(default_factory=lambda: ["ctg", "ctg", "bits", "bits", "trafficgen",
                                                                "trafficgen"],
                                       description="The traffic model of each candidate slot (bundled weights).")
    feedback_seconds: float = Field(4.0, gt=0, le=30, description="Length of each candidate (s).")
    annotators: list[str] = Field(default_factory=lambda: ["attentive", "safety", "flow"],
                                  description="Stand-in annotator profiles labelling every context.")
    contrast_scenes: int = Field(120, ge=0, description="Recorded train scenes (from the split's end) giving "
                                                        "automatic contrast pairs to both reward models; 0: none.")
    reward: RewardSection = Field(default_factory=lambda: RewardConfig(ensemble_size=3, max_epochs=12,
                                                                       contrast_weight=2.0),
                                  description="RewardConfig fields of Table 4's reward models.")
    backbones: dict[str, RewardSection] = Field(
        default_factory=lambda: {"CTG encoder": RewardConfig(architecture="ctg_mlp"),
                                 "TrafficGen encoder": RewardConfig(architecture="trafficgen_mcg")},
        description="Table 4's reward models: name -> architecture and architecture_config.")
    # > Figure 3
    figure3_contexts: int = Field(10_000, ge=2, description="Labelled CTG train contexts (first N long-enough; "
                                                            "more than there are: all).")
    figure3_dev_fraction: float = Field(0.1472, gt=0, lt=1, description="Share of them held out for early "
                                                                          "stopping (400 of the 469 train scenes).")
    figure3_sizes: tuple[int, ...] = Field((25, 50, 100, 200, 400), min_length=1,
                                           description="Numbers of training contexts on the x axis.")
    figure3_seeds: tuple[int, ...] = Field((0, 1, 2), min_length=1, description="Training seeds per size.")
    figure3_steps: int = Field(300, ge=1, description="Optimizer steps a small training set gets at least "
                                                      "(more epochs, up to 40).")
    figure3_reward: RewardSection = Field(default_factory=RewardConfig, description="RewardConfig fields of "
                                          "Figure 3's reward models over the defaults.")

    @classmethod
    def quick(cls, **fields: Any) -> PaperConfig:
        """The small form (CI): 4 scenes, 2 rollouts, one-epoch alignments, tiny feedback and reward models; every
        table's code path runs, in about 5 minutes on 2 cores."""
        small = {"label": "quick", "scenes": 4, "rollouts": 2, "progress": False, "align_overrides": QUICK_ALIGN,
                 "feedback_contexts": 2, "contrast_scenes": 2,
                 "reward": {"ensemble_size": 1, "max_epochs": 2, "batch_size": 2, "contrast_weight": 2.0},
                 "figure3_contexts": 12, "figure3_sizes": (4, 8), "figure3_seeds": (0,), "figure3_steps": 4,
                 "figure3_reward": {"max_epochs": 2}}
        return cls(**{**small, **fields})
