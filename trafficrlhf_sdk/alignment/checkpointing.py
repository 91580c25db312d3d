"""Epoch checkpoints of a training run (``<folder>/checkpoint-N``), enough for a resumed run to match an
uninterrupted one bit for bit.

The module-level functions are the machinery every trainer shares: a checkpoint folder is written whole under
a temporary name and renamed into place (an interrupt never leaves a half-written ``checkpoint-N``), only the
newest :data:`SAVE_TOTAL_LIMIT` are kept, an optimizer's state goes to safetensors plus JSON (never pickle), and
resuming loads the newest intact checkpoint, falling back to an older one when the newest is damaged.

:class:`TrainerCheckpoints` applies them to an :class:`~trafficrlhf_sdk.alignment.AlignTrainer`
(``output_dir/checkpoints``): the adapter's weights (``save_pretrained``), the optimizer state and
``trainer_state.json`` (epochs done, history, optimizer hyper-parameters, RNG state). The reward-model trainer
uses the same functions (:mod:`trafficrlhf_sdk.reward.trainer`).
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from collections.abc import Callable
from typing import Any

import torch
from safetensors.torch import save_file

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario.io import safe_load_file

__all__ = ["RESUME_FREE_FIELDS", "SAVE_TOTAL_LIMIT", "STATE_FILE", "TrainerCheckpoints", "list_checkpoints",
           "load_optimizer_state", "optimizer_state_files", "resume_newest", "write_checkpoint"]

STATE_FILE = "trainer_state.json"
OPTIMIZER_FILE = "optimizer.safetensors"
SAVE_TOTAL_LIMIT = 2  # checkpoints kept; older ones are deleted
# AlignConfig fields a resumed run may change without `resume_allow_changes`: bookkeeping, not training
RESUME_FREE_FIELDS = frozenset({"resume", "resume_allow_changes", "progress_bar", "output_dir", "epochs",
                                "save_every"})


def write_checkpoint(root: str, number: int, write: Callable[[str], None], keep: int = SAVE_TOTAL_LIMIT) -> str:
    """Write ``root/checkpoint-<number>`` atomically: ``write(folder)`` fills a temporary folder, which is then
    renamed into place; checkpoints beyond the newest ``keep`` are deleted. Returns the folder. ``write`` must
    create :data:`STATE_FILE`, which marks a checkpoint complete."""
    final = os.path.join(root, f"checkpoint-{number}")
    tmp = final + ".tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    os.makedirs(tmp)
    write(tmp)
    if not os.path.isfile(os.path.join(tmp, STATE_FILE)):
        raise TrafficRLHFError(f"checkpoint {final!r}: the writer made no {STATE_FILE}; it would never be resumed.")
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    for old in list_checkpoints(root)[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def list_checkpoints(root: str | None) -> list[str]:
    """Complete checkpoint folders (``checkpoint-N`` holding :data:`STATE_FILE`) in ``root``, oldest first."""
    if root is None or not os.path.isdir(root):
        return []
    found = []
    for name in os.listdir(root):
        path = os.path.join(root, name)
        complete = os.path.isfile(os.path.join(path, STATE_FILE))
        if name.startswith("checkpoint-") and name[11:].isdigit() and complete:
            found.append((int(name[11:]), path))
    return [p for _, p in sorted(found)]


def resume_newest(root: str | None, load: Callable[[str], None], fatal: Callable[[Exception], bool],
                  out_option: str = "--out") -> str:
    """``load`` the newest intact checkpoint of ``root`` (a broken one is skipped with a warning, unless
    ``fatal(error)`` says the error must stop the run, e.g. changed settings); returns its folder. Raises
    TrafficRLHFError when there is none, rather than silently starting over."""
    found = list_checkpoints(root)
    if not found:
        raise TrafficRLHFError(f"resume: no checkpoint in {root!r} (no checkpoint-N folder with {STATE_FILE}); "
                               f"drop --resume to start a new run, or pass the {out_option} of the run to continue.")
    problems = []
    for directory in reversed(found):
        try:
            load(directory)
            return directory
        except (TrafficRLHFError, OSError, ValueError, KeyError, TypeError) as exc:
            if fatal(exc):
                raise
            problems.append(f"{os.path.basename(directory)}: {' '.join(str(exc).split())[:200]}")
            warnings.warn(f"resume: checkpoint {directory!r} is broken ({problems[-1]}); trying an older one.",
                          stacklevel=3)
    raise TrafficRLHFError(f"resume: no intact checkpoint in {root!r} ({'; '.join(problems)}); drop --resume "
                           "to start a new run.")


def optimizer_state_files(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """An optimizer's state as safetensors tensors (``"<param index>.<key>"``) and a JSON-ready dict
    (``param_groups`` and the non-tensor ``scalars``); :func:`load_optimizer_state` reverses it."""
    state = optimizer.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, Any] = {}
    for index, entry in state["state"].items():
        for key, value in entry.items():
            if isinstance(value, torch.Tensor):
                tensors[f"{index}.{key}"] = value.detach().cpu().contiguous()
            else:
                scalars[f"{index}.{key}"] = value
    return tensors, {"param_groups": state["param_groups"], "scalars": scalars}


def load_optimizer_state(optimizer: torch.optim.Optimizer, tensors: dict[str, torch.Tensor],
                         meta: dict[str, Any]) -> None:
    """Restore what :func:`optimizer_state_files` wrote into ``optimizer``."""
    per_param: dict[int, dict[str, Any]] = {}
    for key, value in tensors.items():
        index, name = key.split(".", 1)
        per_param.setdefault(int(index), {})[name] = value
    for key, value in meta.get("scalars", {}).items():
        index, name = key.split(".", 1)
        per_param.setdefault(int(index), {})[name] = value
    optimizer.load_state_dict({"state": per_param, "param_groups": meta["param_groups"]})


class TrainerCheckpoints:
    """Saving and restoring a trainer's state; mixed into :class:`~trafficrlhf_sdk.alignment.AlignTrainer`, whose
    ``model``, ``optimizer``, ``config``, ``group_names``, ``history`` and ``start_epoch`` it reads and writes."""

    model: Any
    optimizer: torch.optim.Optimizer
    config: Any
    group_names: list[str]
    history: list[dict[str, float]]
    start_epoch: int
    config_changes: list[dict[str, Any]]

    def _checkpoint_root(self) -> str | None:
        return None if self.config.output_dir is None else os.path.join(self.config.output_dir, "checkpoints")

    def save_checkpoint(self, epochs_done: int) -> str:
        """Write ``checkpoints/checkpoint-N``: the adapter (``save_pretrained``), the optimizer state as
        safetensors and ``trainer_state.json`` (epochs done, history, optimizer hyper-parameters, RNG state)."""
        root = self._checkpoint_root()
        if root is None:
            raise TrafficRLHFError("set `output_dir` to save checkpoints.")

        def write(folder: str) -> None:
            self.model.save_pretrained(folder)
            tensors, optimizer_meta = optimizer_state_files(self.optimizer)
            save_file(tensors, os.path.join(folder, OPTIMIZER_FILE), metadata={"format": "pt"})
            payload = {
                "epochs_done": epochs_done,
                "groups": list(self.group_names),
                "config": self.config.model_dump(mode="json"),
                "history": self.history,
                "optimizer_param_groups": optimizer_meta["param_groups"],
                "optimizer_scalars": optimizer_meta["scalars"],
                "torch_rng_state": torch.get_rng_state().tolist(),
                "config_changes": list(getattr(self, "config_changes", [])),
            }
            with open(os.path.join(folder, STATE_FILE), "w", encoding="utf-8") as handle:
                json.dump(payload, handle, indent=1)

        return write_checkpoint(root, epochs_done, write)

    def list_checkpoints(self) -> list[str]:
        """Complete checkpoint folders in ``output_dir``, oldest first."""
        return list_checkpoints(self._checkpoint_root())

    def resume_newest(self) -> str:
        """Load the newest intact checkpoint of ``output_dir`` (a broken one is skipped with a warning); returns its
        folder. Raises TrafficRLHFError when there is none, rather than silently starting over."""
        return resume_newest(self._checkpoint_root(), self.load_checkpoint,
                             lambda exc: isinstance(exc, TrafficRLHFError) and "changed hyper-parameter" in str(exc))

    def _config_changes(self, directory: str, saved: dict[str, Any]) -> dict[str, list[Any]]:
        """Fields of the running config that differ from the checkpoint's, bookkeeping fields left out."""
        now = self.config.model_dump(mode="json")
        return {key: [saved.get(key), value] for key, value in now.items()
                if key not in RESUME_FREE_FIELDS and key in saved and saved[key] != value}

    def load_checkpoint(self, directory: str) -> None:
        """Restore weights, optimizer state, history and the epoch counter from a checkpoint folder.

        Refuses changed hyper-parameters unless ``config.resume_allow_changes``; accepted changes are recorded
        in ``config_changes`` with the epoch they apply from."""
        with open(os.path.join(directory, STATE_FILE), encoding="utf-8") as handle:
            payload = json.load(handle)
        if list(payload["groups"]) != list(self.group_names):
            raise TrafficRLHFError(f"checkpoint {directory!r} trained groups {payload['groups']}, this run trains "
                                   f"{list(self.group_names)}; resume with the same `groups`.")
        changes = self._config_changes(directory, payload.get("config") or {})
        if changes and not getattr(self.config, "resume_allow_changes", False):
            shown = "; ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in sorted(changes.items())[:5])
            raise TrafficRLHFError(f"resume: changed hyper-parameter(s) against checkpoint {directory!r} ({shown}); "
                                   "resume with the same settings, or allow it with --allow-changes "
                                   "(resume_allow_changes=true), which records the change.")
        self.config_changes = list(payload.get("config_changes", []))
        if changes:
            self.config_changes.append({"from_epoch": int(payload["epochs_done"]) + 1, "changes": changes})
        self.model.load_weights(directory)
        tensors, _ = safe_load_file(os.path.join(directory, OPTIMIZER_FILE))
        load_optimizer_state(self.optimizer, tensors, {"param_groups": payload["optimizer_param_groups"],
                                                       "scalars": payload.get("optimizer_scalars", {})})
        torch.set_rng_state(torch.tensor(payload["torch_rng_state"], dtype=torch.uint8))
        self.history = list(payload["history"])
        self.start_epoch = int(payload["epochs_done"])
