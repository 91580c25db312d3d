"""``RewardTrainer``: Bradley–Terry training of a reward model from a :class:`PreferenceDataset`.

The loss is ``-log σ(r(S_w) - r(S_l))`` (with TRL's optional margin and reward centring, an inverse temperature
and soft labels for ties; :func:`~trafficrlhf_sdk.reward.losses.bradley_terry_loss`). Each future is featurized
once (:func:`~trafficrlhf_sdk.reward.data.build_pair_data`); an optimiser step takes ``batch_size`` contexts with
all their pairs. Validation is by context. After each epoch the trainer logs loss, accuracy, reward margin and
reward range on the training batches and the validation contexts, stops early when the validation loss stops
improving and restores the best epoch. With ``ensemble_size > 1`` it trains a bootstrap ensemble
(:class:`~trafficrlhf_sdk.reward.model.RewardEnsemble`) whose spread across members is the uncertainty.

With ``checkpoint_dir`` the trainer checkpoints every epoch (weights, moving average, best epoch so far,
optimizer, early-stopping counter, the shuffling generator and torch's RNG) through the same machinery as
``align`` (:mod:`trafficrlhf_sdk.alignment.checkpointing`); ``train(resume=True)`` continues from the newest one,
and the final weights equal those of an uninterrupted run bit for bit.

Example:
    >>> trainer = RewardTrainer(RewardConfig(), train_dataset=PreferenceDataset.load("prefs"))
    >>> result = trainer.train()
    >>> trainer.model.save_pretrained("my_reward_model")
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Any

import torch

from trafficrlhf_sdk.errors import DataFormatError, DeviceUnavailableError, TrafficRLHFError
from trafficrlhf_sdk.feedback.preference import PreferenceDataset
from trafficrlhf_sdk.reward.config import RewardConfig
from trafficrlhf_sdk.reward.data import PairData, build_pair_data, split_by_context
from trafficrlhf_sdk.reward.losses import bradley_terry_loss, preference_metrics
from trafficrlhf_sdk.reward.model import RewardEnsemble, RewardModel, get_reward_model_architecture

__all__ = ["RESUME_FREE_FIELDS", "RewardTrainer", "TrainingResult", "evaluate_pairs", "training_device"]

TENSORS_FILE = "trainer_tensors.safetensors"
# RewardConfig fields a resumed run may differ in: how it is shown and run, and how far (the pipeline's step
# digests leave the same ones out); the weights are bit-identical to an uninterrupted run's on the same threads
RESUME_FREE_FIELDS = frozenset({"progress", "max_epochs", "num_threads"})


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
        checkpoint_dir: a folder for a checkpoint after every epoch (``checkpoint-N``, N the epochs done over
            all members; the newest two are kept); :meth:`train` with ``resume=True`` continues from it.
    """

    def __init__(self, config: RewardConfig | None = None, train_dataset: PreferenceDataset | PairData | None = None,
                 eval_dataset: PreferenceDataset | PairData | None = None, model: RewardModel | None = None,
                 labels: torch.Tensor | None = None, log: Callable[[dict[str, float]], None] | None = None,
                 contrast_dataset: PreferenceDataset | None = None, checkpoint_dir: str | None = None) -> None:
        self.config = config or RewardConfig()
        self.checkpoint_dir = checkpoint_dir
        self._finished: list[tuple[RewardModel, int, list[dict[str, float]]]] = []
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
    def train(self, resume: bool = False) -> TrainingResult:
        """Train (every ensemble member), restore the best epochs, set ``self.model`` and return the result.

        ``resume`` continues from the newest intact checkpoint in ``checkpoint_dir`` (an error when there is
        none, or when the settings or the data differ from the checkpoint's). Without it, a ``checkpoint_dir``
        that already holds checkpoints is refused rather than overwritten."""
        cfg = self.config
        device = training_device(cfg.device)
        saved = self._resume_state() if resume else None
        if saved is None and self.checkpoint_dir is not None:
            from trafficrlhf_sdk.alignment.checkpointing import list_checkpoints

            found = list_checkpoints(self.checkpoint_dir)
            if found:
                raise TrafficRLHFError(
                    f"{self.checkpoint_dir!r} holds checkpoints of an unfinished run (newest: "
                    f"{os.path.basename(found[-1])}); continue it with --resume (resume=True), or delete that folder "
                    "to start over.")
        threads = torch.get_num_threads()
        if cfg.num_threads:
            torch.set_num_threads(cfg.num_threads)
        began = time.perf_counter()
        self._finished = []
        try:
            members, history, best_epochs = [], [], []
            start = 0 if saved is None else int(saved["state"]["member"])
            for m in range(cfg.ensemble_size):
                torch.manual_seed(cfg.seed + 1000 * m)
                if self.model is not None and cfg.ensemble_size == 1:
                    member = self.model
                else:
                    member = self.architecture(self.config.architecture_config)
                member.to(device)
                if m < start:  # finished before the interruption: its final weights are in the checkpoint
                    assert saved is not None
                    done = saved["state"]["finished"][m]
                    member.load_state_dict(_prefixed(saved["tensors"], f"done{m}."))
                    best_epoch, member_history = int(done["best_epoch"]), list(done["history"])
                else:
                    best_epoch, member_history = self._train_member(member, m, saved if m == start else None)
                members.append(member)
                history += member_history
                best_epochs.append(best_epoch)
                self._finished.append((member, best_epoch, member_history))
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

    def _train_member(self, model: RewardModel, member: int,
                      saved: dict[str, Any] | None = None) -> tuple[int, list[dict[str, float]]]:
        cfg = self.config
        generator = torch.Generator().manual_seed(cfg.seed + 7919 * member)
        contexts = self.train_data.contexts_with_pairs()
        if cfg.bootstrap and cfg.ensemble_size > 1:
            contexts = contexts[torch.randint(len(contexts), (len(contexts),), generator=generator)]
        optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
        steps_per_epoch = math.ceil(len(contexts) / cfg.batch_size)
        best = (math.inf, -1, copy.deepcopy(model.state_dict()))
        history: list[dict[str, float]] = []
        stale = 0
        # exponential moving average of the weights (Polyak averaging): labels are noisy, so the raw weights
        # jitter from step to step; the average is what is evaluated, kept and saved
        ema = {k: v.detach().clone() for k, v in model.state_dict().items()} if cfg.ema_decay else None
        contrast = self.contrast_data
        contrast_contexts = None if contrast is None else contrast.contexts_with_pairs()
        contrast_at = 0
        first_epoch, stopped = 1, False
        if saved is not None:  # continue exactly where the checkpoint left this member
            state, tensors = saved["state"], saved["tensors"]
            model.load_state_dict(_prefixed(tensors, "model."))
            if ema is not None:
                ema = {k: v.to(ema[k].device) for k, v in _prefixed(tensors, "ema.").items()}
            if state["best_epoch"] > 0:
                best = (float(state["best_value"]), int(state["best_epoch"]), _prefixed(tensors, "best."))
            from trafficrlhf_sdk.alignment.checkpointing import load_optimizer_state

            load_optimizer_state(optimizer, _prefixed(tensors, "optimizer."), state["optimizer"])
            generator.set_state(tensors["generator_state"])
            torch.set_rng_state(tensors["torch_rng_state"])
            history, stale, contrast_at = list(state["history"]), int(state["stale"]), int(state["contrast_at"])
            first_epoch, stopped = int(state["epoch"]) + 1, bool(state["stopped"])
        bar = None
        if cfg.progress:
            from trafficrlhf_sdk.console import progress

            label = f"reward model {member + 1}/{cfg.ensemble_size}" if cfg.ensemble_size > 1 else "reward model"
            bar = progress(total=cfg.max_epochs * steps_per_epoch, initial=(first_epoch - 1) * steps_per_epoch,
                           desc=label, unit="step", leave=False)
        for epoch in range(first_epoch, 1 if stopped else cfg.max_epochs + 1):
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
            if "val_loss" in row:
                value = row["val_loss"] if cfg.metric_mode == "loss" else -row["val_accuracy"]
                if value < best[0] - cfg.early_stopping_min_delta:
                    best, stale = (value, epoch, copy.deepcopy(model.state_dict())), 0
                else:
                    stale += 1
            if raw is not None:
                model.load_state_dict(raw)
            stop = ("val_loss" in row and cfg.early_stopping_patience is not None
                    and stale >= cfg.early_stopping_patience)
            if self.checkpoint_dir is not None:  # before anything that may be interrupted: this epoch is kept
                self._save_checkpoint(member, epoch, stop, model, ema, best, optimizer, generator, history, stale,
                                      contrast_at)
            if self.log is not None:
                self.log(dict(row))
            if bar is not None:
                bar.set_postfix(**{k: f"{v:.3f}" for k, v in row.items() if k in ("train_loss", "val_loss",
                                                                                 "val_accuracy")})
            if stop:
                break
        if bar is not None:
            bar.close()
        if best[1] > 0:
            model.load_state_dict(best[2])
            return best[1], history
        if ema is not None:
            model.load_state_dict(ema)
        return len(history), history

    # ---------------------------------------------------------------- checkpoints
    def _fingerprint(self) -> str:
        """SHA-256 of the pairs trained and validated on (a resumed run must see the same data)."""
        digest = hashlib.sha256()
        for data in (self.train_data, self.eval_data, self.contrast_data):
            if data is None:
                digest.update(b"-")
                continue
            for tensor in (data.winner, data.loser, data.labels, data.pair_context):
                digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
            digest.update(json.dumps(data.context_keys, sort_keys=True, default=str).encode())
        return digest.hexdigest()

    def _save_checkpoint(self, member: int, epoch: int, stopped: bool, model: RewardModel,
                         ema: dict[str, torch.Tensor] | None, best: tuple[float, int, dict[str, torch.Tensor]],
                         optimizer: torch.optim.Optimizer, generator: torch.Generator,
                         history: list[dict[str, float]], stale: int, contrast_at: int) -> str:
        from safetensors.torch import save_file

        from trafficrlhf_sdk.alignment.checkpointing import STATE_FILE, optimizer_state_files, write_checkpoint

        assert self.checkpoint_dir is not None
        optimizer_tensors, optimizer_meta = optimizer_state_files(optimizer)
        tensors = {**{f"model.{k}": v for k, v in model.state_dict().items()},
                   **{f"optimizer.{k}": v for k, v in optimizer_tensors.items()},
                   "generator_state": generator.get_state(), "torch_rng_state": torch.get_rng_state()}
        if ema is not None:
            tensors.update({f"ema.{k}": v for k, v in ema.items()})
        if best[1] > 0:
            tensors.update({f"best.{k}": v for k, v in best[2].items()})
        for m, (done, _, _) in enumerate(self._finished):
            tensors.update({f"done{m}.{k}": v for k, v in done.state_dict().items()})
        state = {"member": member, "epoch": epoch, "stopped": stopped, "stale": stale, "contrast_at": contrast_at,
                 "best_value": best[0], "best_epoch": best[1], "history": history,
                 "finished": [{"best_epoch": b, "history": h} for _, b, h in self._finished],
                 "optimizer": optimizer_meta, "config": self.config.model_dump(mode="json"),
                 "data_sha256": self._fingerprint()}

        def write(folder: str) -> None:
            save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()},
                      os.path.join(folder, TENSORS_FILE), metadata={"format": "pt"})
            with open(os.path.join(folder, STATE_FILE), "w", encoding="utf-8") as handle:
                json.dump(state, handle)

        epochs_done = sum(len(h) for _, _, h in self._finished) + epoch
        return write_checkpoint(self.checkpoint_dir, epochs_done, write)

    def _resume_state(self) -> dict[str, Any]:
        """The newest intact checkpoint of ``checkpoint_dir`` as ``{"state": ..., "tensors": ...}``, after checking
        that it belongs to this run (settings and data)."""
        from trafficrlhf_sdk.alignment.checkpointing import STATE_FILE, resume_newest
        from trafficrlhf_sdk.scenario.io import safe_load_file

        if self.checkpoint_dir is None:
            raise TrafficRLHFError("resume needs `checkpoint_dir` (the --out of the interrupted run).")
        loaded: dict[str, Any] = {}

        def load(folder: str) -> None:
            with open(os.path.join(folder, STATE_FILE), encoding="utf-8") as handle:
                state = json.load(handle)
            now = self.config.model_dump(mode="json")
            changed = {k: (state["config"].get(k), v) for k, v in now.items()
                       if k not in RESUME_FREE_FIELDS and state["config"].get(k) != v}
            if changed:
                shown = "; ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in sorted(changed.items())[:5])
                raise _ResumeMismatch(f"resume: the settings differ from checkpoint {folder!r} ({shown}); resume "
                                      "with the options of the interrupted run (only --epochs may change).")
            if state["data_sha256"] != self._fingerprint():
                raise _ResumeMismatch(f"resume: checkpoint {folder!r} trained on other preference pairs than this "
                                      "run's (campaigns, annotators, --val-fraction or --split-seed differ); resume "
                                      "with the data options of the interrupted run.")
            tensors, _ = safe_load_file(os.path.join(folder, TENSORS_FILE))
            loaded.update(state=state, tensors=tensors)

        resume_newest(self.checkpoint_dir, load, lambda exc: isinstance(exc, _ResumeMismatch))
        return loaded

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


class _ResumeMismatch(TrafficRLHFError):
    """A checkpoint is intact but belongs to another run (settings or data); resuming must stop, not fall back."""


def _prefixed(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The entries of ``tensors`` whose key starts with ``prefix``, the prefix removed."""
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
