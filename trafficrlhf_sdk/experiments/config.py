"""``PaperConfig``: everything ``trafficrlhf experiment paper`` runs, every nested section typed.

The alignment recipes are the shipped TOML recipes (``docs/recipes/*.toml``, read when the configuration is
loaded, so a misspelled key in one fails then, naming the field and the key: ``align_bits``,
``align.learnig_rate``); the overrides are :class:`~trafficrlhf_sdk.alignment.AlignConfig` fields and the
reward-model settings :class:`~trafficrlhf_sdk.reward.RewardConfig` fields, so a misspelled key in an experiment
file fails when it is loaded, naming its path (``align_overrides.learnig_rate``).
"""

from __future__ import annotations

import os
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from trafficrlhf_sdk.alignment.config import AlignConfig
from trafficrlhf_sdk.config_files import ONLY_SET_FIELDS
from trafficrlhf_sdk.errors import DataNotFoundError, TrafficRLHFError
from trafficrlhf_sdk.parallel import ExecutionConfig
from trafficrlhf_sdk.reward.config import RewardConfig

__all__ = ["GUIDANCES", "TABLES", "PaperConfig", "resolve_path"]

TABLES = ("table1", "table2", "table3", "table4", "figure3")
GUIDANCES = ("speed_limit", "target_speed", "no_collision", "no_offroad", "goal_waypoint")


def resolve_path(path: str) -> str:
    """``path`` as given when it exists, else relative to the folder above the installed SDK (the repository
    root of a source checkout, where the bundled reward models and the recipes live); an error naming both
    otherwise."""
    if os.path.exists(path):
        return os.path.abspath(path)
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # trafficrlhf_sdk/
    beside = os.path.join(os.path.dirname(package), path)
    if os.path.exists(beside):
        return beside
    raise DataNotFoundError(f"{path!r} does not exist here nor at {beside!r}; give the file's or folder's path.")


def _readable_recipe(path: str) -> str:
    """``path`` when it is a valid alignment recipe; a ValueError naming the file and the problem otherwise."""
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe

    try:
        AlignRecipe.load(resolve_path(path))
    except TrafficRLHFError as exc:
        raise ValueError(str(exc)) from None
    return path


AlignSection = Annotated[AlignConfig, ONLY_SET_FIELDS]
RewardSection = Annotated[RewardConfig, ONLY_SET_FIELDS]
RecipeFile = Annotated[str, AfterValidator(_readable_recipe)]

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
    execution: ExecutionConfig = Field(default_factory=ExecutionConfig, description="Where the evaluations' "
                                       "rollouts, the campaigns' candidates and the alignments run: in-process, "
                                       "or on Ray workers (a table's alignments side by side, one per worker on "
                                       "its threads; the numbers of an in-process run with those threads).")
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
    # > alignment recipes (TOML files of `trafficrlhf align --config`; their [align] tables are used, with this
    #   experiment's reward model, aggregation, guidance and seed in place of the recipe's)
    align_bits: RecipeFile = Field("docs/recipes/bits-rm.toml", description="BITS + RM recipe file (relative to "
                                   "the working directory or the repository).")
    align_trafficgen: RecipeFile = Field("docs/recipes/trafficgen-rm.toml", description="TrafficGen + RM recipe "
                                         "file.")
    align_ctg: RecipeFile = Field("docs/recipes/ctg-rm.toml", description="Table 3's recipe file (CTG's own "
                                  "networks; each variant sets the groups it trains).")
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
