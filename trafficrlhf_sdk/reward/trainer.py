"""``RewardTrainer``: Bradley–Terry training of a reward model from a :class:`PreferenceDataset`.

The loss is ``-log σ(r(S_w) - r(S_l))`` (with TRL's optional margin and reward centring, an inverse temperature
and soft labels for ties; :func:`~trafficrlhf_sdk.reward.losses.bradley_terry_loss`). Each future is featurized
once (:func:`~trafficrlhf_sdk.reward.data.build_pair_data`); an optimiser step takes ``batch_size`` contexts with
all their pairs. Validation is by context. After each epoch the trainer logs loss, accuracy, reward margin and
reward range on the training batches and the validation contexts, stops early when the validation loss stops
improving and restores the best epoch. With ``ensemble_size > 1`` it trains a bootstrap ensemble
(:class:`~trafficrlhf_sdk.reward.model.RewardEnsemble`) whose spread across members is the uncertainty.

Example:
    >>> trainer = RewardTrainer(RewardConfig(), train_dataset=PreferenceDataset.load("prefs"))
    >>> result = trainer.train()
    >>> trainer.model.save_pretrained("my_reward_model")
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Any

import torch

from trafficrlhf_sdk.errors import DataFormatError, DeviceUnavailableError
from trafficrlhf_sdk.feedback.preference import PreferenceDataset
from trafficrlhf_sdk.reward.config import RewardConfig
from trafficrlhf_sdk.reward.data import PairData, build_pair_data, split_by_context
from trafficrlhf_sdk.reward.losses import bradley_terry_loss, preference_metrics
from trafficrlhf_sdk.reward.model import RewardEnsemble, RewardModel, get_reward_model_architecture

__all__ = ["RewardTrainer", "TrainingResult", "evaluate_pairs", "training_device"]


@dataclass
class TrainingResult:
    """What :meth:`RewardTrainer.train` returns.

    Fields:
        model: the trained model (a :class:`RewardEnsemble` for several members).
        history: one dict per member and epoch (member, epoch, train_* and val_* metrics, seconds).
        metrics: final metrics: ``val_*`` of the returned model and, for an ensemble, the members' mean and
            standard deviation of each (``val_accuracy_member_mean`` / ``_member_std``) and ``val_uncertainty``
            (mean over validation futures of the members' reward std).
        best_epochs: the restored epoch of each member; train_seconds: wall time of the whole call;
            featurize_seconds: the part spent featurizing.
    """

    model: RewardModel
    history: list[dict[str, float]]
    metrics: dict[str, float]
    best_epochs: list[int]
    train_seconds: float
    featurize_seconds: float
    info: dict[str, Any] = field(default_factory=dict)


def evaluate_pairs(model: RewardModel, data: PairData, config: RewardConfig | None = None,
                   batch_contexts: int = 64) -> dict[str, float]:
    """Loss, accuracy, margin and reward range of ``model`` on all pairs of ``data`` (no gradient)."""
    config = config or RewardConfig()
    was_training = model.training
    model.eval()
    chosen, rejected, labels = [], [], []
    contexts = data.contexts_with_pairs()
    with torch.no_grad():
        for lo in range(0, len(contexts), batch_contexts):
            inputs, w, lo_, lab = data.batch(contexts[lo:lo + batch_contexts])
            scores = model.score_prepared(inputs).cpu()
            chosen.append(scores[w])
            rejected.append(scores[lo_])
            labels.append(lab)
    model.train(was_training)
    c, r, lab = torch.cat(chosen), torch.cat(rejected), torch.cat(labels)
    metrics = preference_metrics(c, r, lab)
    metrics["loss"] = float(bradley_terry_loss(c, r, lab, config.margin, config.center_rewards_coefficient,
                                               config.logit_scale))
    return metrics


def training_device(name: str) -> torch.device:
    """``torch.device(name)``, after checking that such a device is there (CUDA devices by index)."""
    device = torch.device(name)
    if device.type == "cuda" and (not torch.cuda.is_available()
                                  or (device.index or 0) >= torch.cuda.device_count()):
        found = torch.cuda.device_count() if torch.cuda.is_available() else 0
        raise DeviceUnavailableError(
            f"`device` is {name!r} but this machine has {found} CUDA device(s) visible to torch {torch.__version__}; "
            "use device='cpu' (`--device cpu`) or a CUDA build of torch.")
    return device


class RewardTrainer:
    """Trains a reward model on preference pairs.

    Args:
        config: :class:`RewardConfig`.
        train_dataset: a :class:`PreferenceDataset` (or prepared :class:`PairData`). Its contexts marked "val"
            validate unless ``eval_dataset`` is given; without either, ``config.val_fraction`` of the contexts
            are held out by a seeded hash.
        eval_dataset: validation pairs (other contexts), optional.
        model: a model to fine-tune; default a fresh ``config.architecture`` (one per ensemble member).
        labels: soft labels ``(P,)`` of ``train_dataset``'s pairs (probability the winner is preferred).
        log: called with each epoch's metrics dict (e.g. ``print`` or a logger's ``record``).
        contrast_dataset: automatic contrast pairs (:func:`~trafficrlhf_sdk.reward.contrast.contrast_dataset`):
            every optimiser step adds ``config.contrast_weight`` times their Bradley–Terry loss on a batch of
            them; they never enter the validation figures.
    """

    def __init__(self, config: RewardConfig | None = None, train_dataset: PreferenceDataset | PairData | None = None,
                 eval_dataset: PreferenceDataset | PairData | None = None, model: RewardModel | None = None,
                 labels: torch.Tensor | None = None, log: Callable[[dict[str, float]], None] | None = None,
                 contrast_dataset: PreferenceDataset | None = None) -> None:
        self.config = config or RewardConfig()
        training_device(self.config.device)  # before featurizing, which can take a while
        self.architecture = get_reward_model_architecture(self.config.architecture)
        if train_dataset is None:
            raise ValueError("`train_dataset` is required: a PreferenceDataset (`trafficrlhf feedback export`) or "
                             "PairData.")
        self.model = model
        self._template = model or self.architecture(self.config.architecture_config)
        self.log = log
        self.featurize_seconds = 0.0
        tic = time.perf_counter()
        train = self._prepare(train_dataset, labels)
        if eval_dataset is not None:
            self.train_data, self.eval_data = train, self._prepare(eval_dataset, None)
        elif "val" in train.split:
            self.train_data, self.eval_data = train.split_subset("train"), train.split_subset("val")
        else:
            self.train_data, self.eval_data = train, None
        self.contrast_data = None
        if contrast_dataset is not None:
            contrast_split = tuple("train" for _ in range(contrast_dataset.num_contexts))
            self.contrast_data = build_pair_data(self._template.prepare, contrast_dataset, None, contrast_split,
                                                 progress=self.config.progress)
        self.featurize_seconds = time.perf_counter() - tic
        if len(self.train_data) == 0:
            raise DataFormatError("no training pairs left after the train/val split; lower `val_fraction`.")
        self.dataset_info = {"train_contexts": len(self.train_data.contexts_with_pairs()),
                             "train_pairs": len(self.train_data),
                             "val_contexts": 0 if self.eval_data is None else len(self.eval_data.contexts_with_pairs()),
                             "val_pairs": 0 if self.eval_data is None else len(self.eval_data),
                             "contrast_pairs": 0 if self.contrast_data is None else len(self.contrast_data)}
        if isinstance(train_dataset, PreferenceDataset):
            self.dataset_info["metadata"] = dict(train_dataset.metadata)
            self.dataset_info["annotators"] = sorted({train_dataset.annotators[int(i)]
                                                      for i in train_dataset.pair_annotator.unique()})

    def _prepare(self, data: PreferenceDataset | PairData, labels: torch.Tensor | None) -> PairData:
        if isinstance(data, PairData):
            return data if labels is None else data.with_labels(labels)
        split = split_by_context(data, self.config.val_fraction, self.config.seed)
        return build_pair_data(self._template.prepare, data, labels, split, progress=self.config.progress)

    # -------------------------------------------------------------------- train
    def train(self) -> TrainingResult:
        """Train (every ensemble member), restore the best epochs, set ``self.model`` and return the result."""
        cfg = self.config
        device = training_device(cfg.device)
        threads = torch.get_num_threads()
        if cfg.num_threads:
            torch.set_num_threads(cfg.num_threads)
        began = time.perf_counter()
        try:
            members, history, best_epochs = [], [], []
            for m in range(cfg.ensemble_size):
                torch.manual_seed(cfg.seed + 1000 * m)
                if self.model is not None and cfg.ensemble_size == 1:
                    member = self.model
                else:
                    member = self.architecture(self.config.architecture_config)
                member.to(device)
                best_epoch, member_history = self._train_member(member, m)
                members.append(member)
                history += member_history
                best_epochs.append(best_epoch)
        finally:
            torch.set_num_threads(threads)
        model = members[0] if len(members) == 1 else RewardEnsemble(members=members)
        model.eval()
        metrics = self._final_metrics(model, members)
        seconds = time.perf_counter() - began + self.featurize_seconds
        model.card_info = {"training": {"config": cfg.model_dump(mode="json"), "best_epochs": best_epochs,
                                        "train_seconds": round(seconds, 1), "torch_threads": cfg.num_threads or threads,
                                        "device": str(device),
                                        "history": history},
                           "data": self.dataset_info, "metrics": metrics}
        self.model = model
        return TrainingResult(model, history, metrics, best_epochs, seconds, self.featurize_seconds,
                              dict(self.dataset_info))

    def _train_member(self, model: RewardModel, member: int) -> tuple[int, list[dict[str, float]]]:
        cfg = self.config
        generator = torch.Generator().manual_seed(cfg.seed + 7919 * member)
        contexts = self.train_data.contexts_with_pairs()
        if cfg.bootstrap and cfg.ensemble_size > 1:
            contexts = contexts[torch.randint(len(contexts), (len(contexts),), generator=generator)]
        optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
        steps_per_epoch = math.ceil(len(contexts) / cfg.batch_size)
        bar = None
        if cfg.progress:
            from trafficrlhf_sdk.console import progress

            label = f"reward model {member + 1}/{cfg.ensemble_size}" if cfg.ensemble_size > 1 else "reward model"
            bar = progress(total=cfg.max_epochs * steps_per_epoch, desc=label, unit="step", leave=False)
        best = (math.inf, -1, copy.deepcopy(model.state_dict()))
        history: list[dict[str, float]] = []
        stale = 0
        # exponential moving average of the weights (Polyak averaging): labels are noisy, so the raw weights
        # jitter from step to step; the average is what is evaluated, kept and saved
        ema = {k: v.detach().clone() for k, v in model.state_dict().items()} if cfg.ema_decay else None
        contrast = self.contrast_data
        contrast_contexts = None if contrast is None else contrast.contexts_with_pairs()
        contrast_at = 0
        for epoch in range(1, cfg.max_epochs + 1):
            tic = time.perf_counter()
            model.train()
            order = contexts[torch.randperm(len(contexts), generator=generator)]
            chosen, rejected, labels, losses = [], [], [], []
            for lo in range(0, len(order), cfg.batch_size):
                inputs, w, l_, lab = self.train_data.batch(order[lo:lo + cfg.batch_size])
                scores = model.score_prepared(inputs)
                w, l_, lab = w.to(scores.device), l_.to(scores.device), lab.to(scores.device)
                loss = bradley_terry_loss(scores[w], scores[l_], lab, cfg.margin, cfg.center_rewards_coefficient,
                                          cfg.logit_scale)
                if contrast is not None and contrast_contexts is not None and cfg.contrast_weight > 0:
                    take = contrast_contexts[(torch.arange(cfg.batch_size) + contrast_at) % len(contrast_contexts)]
                    contrast_at += cfg.batch_size
                    c_inputs, cw, cl, c_lab = contrast.batch(take)
                    c_scores = model.score_prepared(c_inputs)
                    cw, cl = cw.to(c_scores.device), cl.to(c_scores.device)
                    loss = loss + cfg.contrast_weight * bradley_terry_loss(
                        c_scores[cw], c_scores[cl], c_lab.to(c_scores.device), cfg.margin,
                        cfg.center_rewards_coefficient, cfg.logit_scale)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                if cfg.max_grad_norm:
                    torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
                optimizer.step()
                if ema is not None:
                    with torch.no_grad():
                        for k, v in model.state_dict().items():
                            if v.is_floating_point():
                                ema[k].mul_(cfg.ema_decay).add_(v, alpha=1 - cfg.ema_decay)
                chosen.append(scores[w].detach())
                rejected.append(scores[l_].detach())
                labels.append(lab)
                losses.append(float(loss.detach()) * len(w))
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(epoch=epoch, loss=f"{float(loss.detach()):.3f}")
            train = preference_metrics(torch.cat(chosen).cpu(), torch.cat(rejected).cpu(), torch.cat(labels).cpu())
            row = {"member": member, "epoch": epoch, "train_loss": sum(losses) / max(len(torch.cat(labels)), 1),
                   **{f"train_{k}": v for k, v in train.items() if k != "num_pairs"}}
            raw = None
            if ema is not None:
                raw = copy.deepcopy(model.state_dict())
                model.load_state_dict(ema)
            if self.eval_data is not None and cfg.eval_every_epoch:
                row.update({f"val_{k}": v for k, v in evaluate_pairs(model, self.eval_data, cfg).items()
                            if k != "num_pairs"})
            row["seconds"] = time.perf_counter() - tic
            history.append(row)
            if self.log is not None:
                self.log(dict(row))
            if bar is not None:
                bar.set_postfix({k: f"{v:.3f}" for k, v in row.items() if k in ("train_loss", "val_loss",
                                                                                 "val_accuracy")})
            if "val_loss" in row:
                value = row["val_loss"] if cfg.metric_mode == "loss" else -row["val_accuracy"]
                if value < best[0] - cfg.early_stopping_min_delta:
                    best, stale = (value, epoch, copy.deepcopy(model.state_dict())), 0
                else:
                    stale += 1
            if raw is not None:
                model.load_state_dict(raw)
            if "val_loss" in row and cfg.early_stopping_patience is not None and stale >= cfg.early_stopping_patience:
                break
        if bar is not None:
            bar.close()
        if best[1] > 0:
            model.load_state_dict(best[2])
            return best[1], history
        if ema is not None:
            model.load_state_dict(ema)
        return len(history), history

    def _final_metrics(self, model: RewardModel, members: list[RewardModel]) -> dict[str, float]:
        metrics: dict[str, float] = {}
        if self.eval_data is None:
            return metrics
        metrics.update({f"val_{k}": v for k, v in evaluate_pairs(model, self.eval_data, self.config).items()})
        if len(members) > 1:
            accs = torch.tensor([evaluate_pairs(m, self.eval_data, self.config)["accuracy"] for m in members])
            metrics["val_accuracy_member_mean"] = float(accs.mean())
            metrics["val_accuracy_member_std"] = float(accs.std())
            with torch.no_grad():
                inputs = self.eval_data.inputs
                scores = torch.stack([m.score_prepared(inputs).cpu() for m in members])
            metrics["val_uncertainty"] = float(scores.std(0).mean())
        return metrics

    # ------------------------------------------------------------------ helpers
    def evaluate(self, dataset: PreferenceDataset | PairData) -> dict[str, float]:
        """Loss, accuracy, margin and reward range of the trained model on ``dataset``'s pairs."""
        if self.model is None:
            raise ValueError("call `train()` first (or pass `model=`).")
        data = dataset if isinstance(dataset, PairData) else build_pair_data(
            self.model.prepare, dataset, split=tuple("val" for _ in range(dataset.num_contexts)))
        return evaluate_pairs(self.model, data, self.config)
