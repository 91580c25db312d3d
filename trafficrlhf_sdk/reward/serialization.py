"""Reward-model folders: ``config.json`` + ``model.safetensors`` + a ``README.md`` model card, never pickle.

``config.json`` holds the format version, the registered ``architecture`` name, its constructor ``config``,
the SHA-256 of the weights file, the parameter count and the provenance (data, training, metrics).
``model.safetensors`` holds the ``state_dict`` (``{"format": "pt"}`` and the architecture in its header).
Loading resolves the class from the architecture registry, rebuilds it from ``config`` and checks every tensor
name and shape before copying the values, so an unknown architecture, an edited, truncated or mis-shaped file
fails with one clear error instead of a half-loaded model.
"""

from __future__ import annotations

import json
import os
from typing import Any

import torch
from safetensors.torch import save_file
from torch import nn

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError
from trafficrlhf_sdk.safetensors_files import check_safetensors_file
from trafficrlhf_sdk.scenario.io import safe_load_file, sha256_file
from trafficrlhf_sdk.version import __version__

__all__ = ["CARD_FILE", "CONFIG_FILE", "WEIGHTS_FILE", "load_weights", "read_config", "read_weights",
           "render_model_card", "save_reward_model"]

FORMAT_VERSION = "1"
CARD_KEYS = ("title", "summary", "notes", "commands", "intended_use", "license", "license_text")
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
CARD_FILE = "README.md"


def save_reward_model(model: Any, directory: str | os.PathLike[str], info: dict[str, Any],
                      dtype: torch.dtype | None = None) -> str:
    """Write the three files of ``model`` (a :class:`~trafficrlhf_sdk.reward.RewardModel`) into ``directory``
    (created); returns the directory.

    ``dtype`` (e.g. ``torch.float16``) stores floating-point weights in that type (half the bytes); loading casts
    them back to the model's dtype.
    """
    if not model.architecture:
        raise ValueError(f"{type(model).__name__} has no `architecture` name; set the class attribute and "
                         "register it with `register_reward_model_architectures`.")
    directory = os.fspath(directory)
    os.makedirs(directory, exist_ok=True)
    weights = os.path.join(directory, WEIGHTS_FILE)
    tensors = {name: t.detach().cpu().to(dtype if dtype is not None and t.is_floating_point() else t.dtype)
               .contiguous() for name, t in model.state_dict().items()}
    save_file(tensors, weights, metadata={"format": "pt", "trafficrlhf_reward_model": FORMAT_VERSION,
                                          "architecture": model.architecture})
    config = {
        "trafficrlhf_reward_model": FORMAT_VERSION,
        "architecture": model.architecture,
        "config": model.config_dict(),
        "weights": {"file": WEIGHTS_FILE, "sha256": sha256_file(weights), "bytes": os.path.getsize(weights),
                    "dtype": str(dtype or next(iter(tensors.values())).dtype).replace("torch.", "")},
        "num_parameters": model.num_parameters,
        "sdk_version": __version__,
        **{k: info[k] for k in ("data", "training", "metrics") if k in info},
    }
    card = {k: info[k] for k in CARD_KEYS if k in info}
    if card:
        config["card"] = card
    with open(os.path.join(directory, CONFIG_FILE), "w", encoding="utf-8") as handle:
        json.dump(config, handle, indent=2)
    with open(os.path.join(directory, CARD_FILE), "w", encoding="utf-8") as handle:
        handle.write(render_model_card(config, info))
    return directory


def read_config(directory: str | os.PathLike[str]) -> dict[str, Any]:
    """The parsed ``config.json`` of a reward-model folder, checked for the keys loading needs."""
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        raise DataNotFoundError(f"reward-model folder not found: {directory!r}; pass the folder that "
                                f"`save_pretrained` wrote (it holds {CONFIG_FILE} and {WEIGHTS_FILE}).")
    path = os.path.join(directory, CONFIG_FILE)
    if not os.path.isfile(path):
        raise DataNotFoundError(f"{directory!r} has no {CONFIG_FILE}; it is not a saved reward model.")
    try:
        with open(path, encoding="utf-8") as handle:
            config = json.load(handle)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"{path!r} is not valid JSON ({exc}); restore the file that save_pretrained wrote.") \
            from exc
    if not isinstance(config, dict) or config.get("trafficrlhf_reward_model") != FORMAT_VERSION:
        got = config.get("trafficrlhf_reward_model") if isinstance(config, dict) else type(config).__name__
        raise DataFormatError(f"{path!r} is not a TrafficRLHF reward-model config (`trafficrlhf_reward_model` is "
                              f"{got!r}, expected {FORMAT_VERSION!r}).")
    for key in ("architecture", "config"):
        if key not in config:
            raise DataFormatError(f"{path!r} lacks the key {key!r}; restore the file that save_pretrained wrote.")
    return config


def read_weights(directory: str | os.PathLike[str], config: dict[str, Any], verify: bool = True,
                 expected_bytes: int | None = None) -> tuple[dict[str, torch.Tensor], str]:
    """The tensors of the weights file that ``config`` (the folder's ``config.json``) names, and its path.

    The file must lie inside ``directory``, pass :func:`~trafficrlhf_sdk.safetensors_files.check_safetensors_file`
    (its header and size, against ``expected_bytes`` of float32 weights when given, and against the memory left),
    match the SHA-256 recorded in ``config`` (with ``verify``) and hold weights of the architecture ``config``
    names.
    """
    directory = os.fspath(directory)
    name = config["architecture"]
    weights_info = config.get("weights", {})
    if not isinstance(weights_info, dict):
        raise DataFormatError(f"{directory!r}: config.json's `weights` must be an object, got {weights_info!r:.60}.")
    weights_name = weights_info.get("file", WEIGHTS_FILE)
    weights = os.path.join(directory, str(weights_name))
    inside = os.path.realpath(directory)
    if os.path.isabs(str(weights_name)) or os.path.commonpath([inside, os.path.realpath(weights)]) != inside:
        raise DataFormatError(f"{directory!r}: config.json's `weights.file` is {weights_name!r}, which lies outside "
                              "the "
                              "model folder; name a file inside it (model.safetensors).")
    if not os.path.isfile(weights):
        raise DataNotFoundError(f"{directory!r} has no {os.path.basename(weights)}; the weights are missing.")
    # from the header and the file size, before the file is hashed or read
    check_safetensors_file(weights, f"reward model {directory!r}: weights file", expected_bytes,
                           exact_size=not verify)  # with verify, the SHA-256 below names a truncated file
    expected = config.get("weights", {}).get("sha256")
    if verify and not expected:
        raise DataFormatError(f"{os.path.join(directory, CONFIG_FILE)!r} records no SHA-256 of the weights "
                              "(`weights.sha256`), so they cannot be verified; re-save the model, or pass "
                              "verify=False only for a file you trust.")
    if verify and expected:
        actual = sha256_file(weights)
        if actual != expected:
            raise DataFormatError(
                f"{weights!r} does not match the SHA-256 recorded in config.json (expected {expected[:16]}..., got "
                f"{actual[:16]}...): the weights were modified or truncated after saving. Re-download or re-save "
                "the model; pass verify=False only for a file you trust."
            )
    tensors, header = safe_load_file(weights)
    if header.get("architecture") not in (None, name):
        raise DataFormatError(f"{weights!r} holds weights of architecture {header.get('architecture')!r} but "
                              f"config.json says {name!r}; the two files do not belong together.")
    return tensors, weights


def load_weights(model: nn.Module, tensors: dict[str, torch.Tensor], weights: str, config: dict[str, Any],
                 directory: str | os.PathLike[str]) -> None:
    """Copy ``tensors`` (read from the file ``weights`` by :func:`read_weights`) into ``model``, built from
    ``config``, after checking every tensor name, shape, dtype and value."""
    name = config["architecture"]
    state = model.state_dict()
    missing = sorted(set(state) - set(tensors))
    unexpected = sorted(set(tensors) - set(state))
    if missing or unexpected:
        raise DataFormatError(f"{weights!r} does not fit architecture {name!r} with its config: missing tensors "
                              f"{missing[:5]}, unexpected tensors {unexpected[:5]}.")
    wrong = [(k, tuple(tensors[k].shape), tuple(v.shape)) for k, v in state.items() if tensors[k].shape != v.shape]
    if wrong:
        k, got, want = wrong[0]
        raise DataFormatError(f"{weights!r}: tensor {k!r} has shape {got} but the config of {name!r} needs {want} "
                              f"({len(wrong)} tensors differ); config.json and the weights do not belong together.")
    not_float = [k for k, t in tensors.items() if state[k].is_floating_point() and not t.is_floating_point()]
    if not_float:
        raise DataFormatError(f"{weights!r}: tensor {not_float[0]!r} is not floating point.")
    for key, tensor in tensors.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise DataFormatError(f"reward model {os.fspath(directory)!r}: tensor {key!r} holds "
                                  f"{int((~torch.isfinite(tensor)).sum())} NaN or infinite value(s); the weights are "
                                  "unusable: restore them or re-train.")
    model.load_state_dict({k: t.to(state[k].dtype) for k, t in tensors.items()})


def _table(rows: dict[str, Any]) -> str:
    lines = ["| key | value |", "|---|---|"]
    for key, value in rows.items():
        if isinstance(value, float):
            value = f"{value:.4f}"
        elif isinstance(value, (dict, list)):
            value = "`" + json.dumps(value) + "`"
        lines.append(f"| {key} | {value} |")
    return "\n".join(lines)


def render_model_card(config: dict[str, Any], info: dict[str, Any]) -> str:
    """The ``README.md`` of a saved reward model.

    ``info`` keys used: ``title``, ``summary``, ``data`` (dict), ``training`` (dict), ``metrics`` (dict),
    ``commands`` (list of shell lines), ``notes`` (markdown), ``intended_use`` (markdown), ``license``.
    """
    data, training, metrics = info.get("data", {}), dict(info.get("training", {})), info.get("metrics", {})
    training.pop("history", None)
    training_config = training.pop("config", {})
    license_id = info.get("license", "cc-by-nc-sa-4.0")
    parts = [
        "---",
        "library_name: trafficrlhf-sdk",
        f"license: {license_id}",
        "tags: [trafficrlhf, reward-model, rlhf, traffic-simulation]",
        "datasets: [nuscenes]",
        "---",
        "",
        f"# {info.get('title', 'TrafficRLHF reward model')}",
        "",
        info.get("summary", "A reward model r_HF that scores how realistic a traffic scenario is, trained from "
                            "best-of-N preferences with a Bradley–Terry loss."),
        "",
        "## Model",
        "",
        _table({"architecture": f"`{config['architecture']}`", "parameters": f"{config['num_parameters']:,}",
                "weights": f"`{config['weights']['file']}` ({config['weights']['bytes']:,} bytes, SHA-256 "
                           f"`{config['weights']['sha256'][:16]}...`)", "sdk_version": config.get("sdk_version")}),
        "",
        "Options (`config` in `config.json`): `" + json.dumps(config["config"]) + "`",
        "",
        "## Data",
        "",
        _table({k: v for k, v in data.items() if k != "metadata"}) if data else "Not recorded.",
    ]
    if data.get("metadata"):
        parts += ["", "Campaign provenance: `" + json.dumps(data["metadata"]) + "`"]
    parts += ["", "## Training", "", _table(training) if training else "Not recorded."]
    if training_config:
        parts += ["", "`RewardConfig`: `" + json.dumps(training_config) + "`"]
    parts += ["", "## Metrics", ""]
    if metrics:
        parts += ["Accuracy is the share of preference pairs with r(S_w) > r(S_l). `val_*`: the held-out contexts of "
                  "the training campaign with the training labels (a noisy annotator's pick among equally good "
                  "candidates is a coin flip, so these stay far below 1). `test_*`: a held-out campaign; "
                  "`test_strict_*` counts only the pairs whose winner is strictly more realistic under the synthetic "
                  "annotator's hidden judgment, `test_accuracy_gap_above_G` those with a realism gap above G.", "",
                  _table(metrics)]
    else:
        parts.append("Not recorded.")
    if info.get("notes"):
        parts += ["", info["notes"].strip()]
    parts += [
        "", "## Intended use", "",
        info.get("intended_use", "Research on aligning traffic-simulation models with human preferences: the "
                                 "reward-cost metric (`trafficrlhf evaluate --reward-model DIR`) and PPO fine-tuning "
                                 "(r + alpha * r_HF). Not for safety-critical decisions or for judging real drivers."),
        "", "## How to load", "", "```python", "from trafficrlhf_sdk.reward import RewardModel", "",
        "model = RewardModel.from_pretrained(\"PATH/TO/THIS/FOLDER\")  # class from the registry, never pickle",
        "step_rewards = model.step_rewards(scenario)  # (B, T) in [-1, 1]",
        "scores = model(scenario)                    # (B,) mean per-step reward", "```",
    ]
    if info.get("commands"):
        parts += ["", "## Reproduce", "", "```console", *info["commands"], "```"]
    parts += ["", "## Licence", "",
              info.get("license_text", "Trained on nuScenes data (Motional): the weights and this card are shared "
                                       "under the nuScenes terms, CC BY-NC-SA 4.0 (non-commercial, attribution, "
                                       "share-alike)."), ""]
    return "\n".join(parts)
