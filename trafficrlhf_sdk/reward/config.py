"""``RewardConfig``: everything :class:`~trafficrlhf_sdk.reward.trainer.RewardTrainer` needs, in one frozen model.

Fields are grouped as in TRL's ``RewardConfig``: the model, the loss, optimisation, early stopping, the
ensemble and logging. Defaults train the paper's architecture on a feedback campaign of a few hundred
contexts (``benchmarks/bench_reward_training.py`` times them).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

# torch's device types a reward model can train on (checked without importing torch, so a config loads fast)
DEVICE_TYPES = ("cpu", "cuda", "mps", "xpu", "hpu", "mtia", "meta")

__all__ = ["RewardConfig"]


class RewardConfig(BaseModel):
    """Training options of a reward model (stored with it in ``config.json``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # > the model
    architecture: str = Field("ctg_mlp", description="Registered reward-model architecture (`trafficrlhf rm info`).")
    architecture_config: dict[str, Any] = Field(
        default_factory=dict, description="Options of the architecture (e.g. {'hidden_sizes': [256, 32]}).")

    # > the loss: -[p log σ(d) + (1-p) log σ(-d)], d = logit_scale (r_w - r_l) - margin
    margin: float = Field(0.0, ge=0, description="Margin the preferred scenario should win by (TRL's `margin`).")
    center_rewards_coefficient: float | None = Field(
        None, ge=0, description="Weight of mean((r_w + r_l)^2), keeping rewards centred (TRL; 0.01 recommended).")
    logit_scale: float = Field(10.0, gt=0, description="Bradley–Terry inverse temperature on reward differences; "
                                                      "rewards are means in [-1, 1], so differences are small.")

    # > automatic contrast from recorded driving (trafficrlhf_sdk.reward.contrast)
    contrast_weight: float = Field(0.5, ge=0, description="Weight of the contrast pairs' loss (log preferred to "
                                   "the same log made faster, slower, jerky, off its lane or tailgating) next to "
                                   "the labelled pairs' loss; used only when a contrast dataset is given.")

    # > optimisation
    learning_rate: float = Field(3e-4, gt=0, description="Adam learning rate.")
    weight_decay: float = Field(0.05, ge=0, description="AdamW weight decay.")
    batch_size: int = Field(16, ge=1, description="Contexts per optimiser step (all their pairs together).")
    max_epochs: int = Field(8, ge=1, description="Passes over the training contexts at most.")
    max_grad_norm: float | None = Field(1.0, gt=0, description="Gradient-norm clip; None turns it off.")
    ema_decay: float | None = Field(
        0.99, ge=0, lt=1, description="Per-step decay of the moving average of the weights that is evaluated and "
                                      "saved (Polyak averaging against label noise); None uses the raw weights.")
    seed: int = Field(0, description="Seed of initialisation, shuffling and bootstrap draws.")
    num_threads: int | None = Field(None, ge=1, description="torch threads while training; None keeps torch's.")
    device: str = Field(
        "cpu", description="Where the optimiser steps run: 'cpu', 'cuda', 'cuda:1', ... Featurization stays on the "
                           "CPU; each batch is moved to the device. The trained model is left on this device.")

    # > early stopping on the validation contexts (by context, never by pair)
    early_stopping_patience: int | None = Field(
        3, ge=1, description="Stop after this many epochs without a better validation loss; None trains all "
                             "epochs. The best epoch's weights are restored either way when validation exists.")
    early_stopping_min_delta: float = Field(1e-4, ge=0, description="Smallest loss decrease that counts as better.")
    val_fraction: float = Field(
        0.15, ge=0, lt=1, description="Share of contexts held out when the dataset has no 'val' contexts and no "
                                      "eval dataset is given (seeded hash of the context, as the export does).")

    # > ensemble
    ensemble_size: int = Field(1, ge=1, description="Members of a bootstrap ensemble (1: a single model).")
    bootstrap: bool = Field(True, description="Each member trains on contexts drawn with replacement (bagging).")

    # > logging
    progress: bool = Field(True, description="Show a tqdm progress bar per member.")
    eval_every_epoch: bool = Field(True, description="Evaluate on the validation contexts after every epoch.")
    metric_mode: Literal["loss", "accuracy"] = Field(
        "loss", description="Validation metric for early stopping and the best epoch.")

    @field_validator("device")
    @classmethod
    def _known_device(cls, value: str) -> str:
        kind, _, index = value.partition(":")
        if kind not in DEVICE_TYPES or (index and not index.isdigit()):
            raise ValueError(f"`device` must be a torch device such as 'cpu' or 'cuda:0'; got {value!r} (types: "
                             f"{', '.join(DEVICE_TYPES)}, optionally ':N').")
        return value
