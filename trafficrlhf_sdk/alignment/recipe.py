"""``AlignRecipe``: everything one alignment run needs, as one TOML file (``trafficrlhf align --config FILE``).

A recipe names the traffic model and its starting weights, the reward, the adapter options and the
:class:`~trafficrlhf_sdk.alignment.AlignConfig` fields (table ``[align]``); command-line options override it::

    model = "ctg"
    checkpoint = "ctg-4s"                  # a folder or a bundled checkpoint's name
    reward_model = "out/rm"                # a reward-model folder, or builtin:NAME (a hand-written baseline)
    model_options = { steer_road = true }

    [align]
    guidance = "no_collision"
    epochs = 70
    credit = "agent"
"""

from __future__ import annotations

import json
import os
import time
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from trafficrlhf_sdk.alignment.config import AlignConfig, paper_alpha
from trafficrlhf_sdk.config_files import ONLY_SET_FIELDS, read_toml, set_fields, validation_message
from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, TrafficRLHFError

__all__ = ["AlignRecipe", "run_recipe"]


class AlignRecipe(BaseModel):
    """One alignment run: model, starting weights, reward and :class:`AlignConfig` fields."""

    model_config = ConfigDict(extra="forbid")

    model: str | None = Field(None, description="Registered traffic model; None: the one `checkpoint` was saved by.")
    checkpoint: str | None = Field(None, description="Starting weights: a folder or a bundled checkpoint's name "
                                                     "(None: the model's bundled default).")
    reward_model: str = Field(description="A reward-model folder (`trafficrlhf rm train`), or builtin:NAME for a "
                                          "hand-written baseline reward.")
    reward_options: dict[str, Any] = Field(default_factory=dict, description="Keyword arguments of a built-in "
                                                                              "reward.")
    reward_aggregation: Literal["mean", "worst", "lcb"] = Field("mean", description="How an ensemble reward "
                                                                "model's members are combined for the fine-tuner: "
                                                                "their mean, the worst member, or mean - "
                                                                "reward_pessimism x std.")
    reward_pessimism: float = Field(1.0, ge=0, description="k of the 'lcb' aggregation.")
    monitor_reward_model: str | None = Field(None, description="A second reward-model folder the policy never "
                                             "trains on (e.g. trained on other annotators), recorded per epoch as "
                                             "`heldout_reward`.")
    model_options: dict[str, Any] = Field(default_factory=dict, description="Adapter options while training.")
    threads: int | None = Field(None, ge=1, description="torch threads (None: torch's default).")
    align: Annotated[AlignConfig, ONLY_SET_FIELDS] = Field(
        default_factory=AlignConfig, description="AlignConfig fields (table [align]); `alpha` defaults to the "
                                                 "paper's value for the model.")

    @classmethod
    def load(cls, path: str, **fields: Any) -> AlignRecipe:
        """Read and validate a TOML recipe, ``fields`` (those not None, e.g. the command line's) over the file's;
        errors name the file."""
        if not os.path.isfile(path):
            raise DataNotFoundError(f"--config {path!r}: no such file; give a TOML recipe (see "
                                    "reference_models/*/*/recipe.toml or loop.toml).")
        data = {**read_toml(path), **{k: v for k, v in fields.items() if v is not None}}
        try:
            return cls(**data)
        except ValidationError as exc:
            raise DataFormatError(f"--config {path!r}: {validation_message(exc)}") from None

    def config(self, model_name: str, **overrides: Any) -> AlignConfig:
        """The run's :class:`AlignConfig`: the recipe's fields, then ``overrides`` (None values ignored)."""
        fields = {**set_fields(self.align), **{k: v for k, v in overrides.items() if v is not None}}
        fields.setdefault("alpha", paper_alpha(model_name))
        return AlignConfig(**fields)


def run_recipe(recipe: AlignRecipe, output_dir: str, execution: Any = None, **overrides: Any) -> dict[str, Any]:
    """Build the model and reward of ``recipe``, align, save the model and its history in ``output_dir`` and
    return a summary (also written as ``align_summary.json``). ``execution``: a
    :class:`~trafficrlhf_sdk.parallel.ExecutionConfig` whose Ray workers draw each epoch's sample chunks (None:
    this process; the same numbers either way). ``overrides``: AlignConfig fields."""
    import torch

    from trafficrlhf_sdk.alignment.trainer import AlignTrainer
    from trafficrlhf_sdk.plugins import build_policy
    from trafficrlhf_sdk.reward.loading import load_reward

    if recipe.threads is not None:
        torch.set_num_threads(recipe.threads)
    reward = load_reward(recipe.reward_model, recipe.reward_options)
    if recipe.reward_aggregation != "mean":
        if not callable(getattr(reward, "conservative", None)):
            raise TrafficRLHFError(f"reward_aggregation {recipe.reward_aggregation!r} needs an ensemble reward model "
                                   f"(`rm train --ensemble N`); {recipe.reward_model!r} has one member.")
        reward.conservative(recipe.reward_aggregation, recipe.reward_pessimism)
    seed = overrides.get("seed", recipe.align.seed)
    adapter = build_policy(recipe.model, {**recipe.model_options, "checkpoint": recipe.checkpoint, "seed": seed})
    if not hasattr(adapter, "parameter_groups"):
        raise TrafficRLHFError(f"{recipe.model!r} is not a trainable traffic model (no parameter groups).")
    name = str(getattr(adapter, "name", None) or recipe.model or "")
    config = recipe.config(name, output_dir=output_dir, **overrides)
    torch.manual_seed(config.seed)
    start = time.perf_counter()
    monitor = load_reward(recipe.monitor_reward_model) if recipe.monitor_reward_model else None
    trainer = AlignTrainer(adapter, reward, config, monitor_reward=monitor)
    if execution is not None:
        from trafficrlhf_sdk.alignment.distributed import distribute_rollouts

        distribute_rollouts(trainer, execution)
    history = trainer.train()
    wall = time.perf_counter() - start
    summary = {"model": name, "checkpoint": recipe.checkpoint, "reward_model": recipe.reward_model,
               "reward_options": recipe.reward_options, "model_options": recipe.model_options,
               "alpha": config.alpha, "epochs": len(history), "groups": list(trainer.group_names),
               "wall_time_s": wall, "threads": torch.get_num_threads(),
               "reward_first": history[0]["reward_mean"] if history else None,
               "reward_last": history[-1]["reward_mean"] if history else None,
               "heldout_realism_first": history[0].get("heldout_realism") if history else None,
               "heldout_realism_last": history[-1].get("heldout_realism") if history else None}
    os.makedirs(output_dir, exist_ok=True)
    with open(os.path.join(output_dir, "align_summary.json"), "w", encoding="utf-8") as handle:
        json.dump(summary, handle, indent=2)
    return summary
