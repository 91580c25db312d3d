"""Checked loading of traffic-model checkpoints (``config.json`` + ``model.safetensors``), shared by every adapter.

A checkpoint gets the checks a reward model gets (:mod:`trafficrlhf_sdk.reward.serialization`), in this order, so
that nothing is built or read before what it depends on has been checked:

1. ``config.json`` is a JSON object with the keys ``adapter``, ``config`` and ``weights`` (and optionally
   ``options``: the adapter options its card was measured with); ``weights``
   names the weights file (inside the folder: no ``..``, no absolute path, no link out of it) and its SHA-256,
   which is required.
2. ``config`` fits the architecture's config dataclass: no unknown key, every value of the field's type, finite
   numbers, whole numbers that default to a positive value at least 1, none above :data:`MAX_CONFIG_INT`.
3. The module is built on the ``meta`` device (no memory): its parameter count must stay under
   :data:`MAX_PARAMETERS`, and every tensor name, shape and kind (floating point or not) must match the weights
   file's header. A config that would allocate gigabytes fails here, naming the field.
4. The weights file's SHA-256 must match ``config.json``; then its tensors are read and must be finite.
5. Only then is the real module built and the weights copied into it.

Every failure is one :class:`~trafficrlhf_sdk.errors.DataFormatError` or
:class:`~trafficrlhf_sdk.errors.DataNotFoundError` naming the folder (and the tensor or field) and saying how to
fix it. ``trafficrlhf checkpoint-digest DIR`` records the SHA-256 of a folder saved without one.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import typing
from typing import Any

import torch
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError
from trafficrlhf_sdk.safetensors_files import check_safetensors_file
from trafficrlhf_sdk.scenario.io import safe_load_file, sha256_file

__all__ = [
    "CONFIG_FILE",
    "MAX_CONFIG_INT",
    "MAX_PARAMETERS",
    "WEIGHTS_FILE",
    "CheckpointConfig",
    "WeightsInfo",
    "build_checked",
    "check_state",
    "load_checked_weights",
    "parse_architecture_config",
    "read_checkpoint_config",
    "record_weights_digest",
    "sha256_file",
    "weights_path",
]

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
MAX_PARAMETERS = 200_000_000  # 800 MB of float32: far above every bundled model (under 2 M parameters)
MAX_CONFIG_INT = 100_000  # no architecture size, step count or horizon of these models comes near it


class WeightsInfo(BaseModel):
    """``weights`` in a checkpoint's ``config.json``."""

    model_config = ConfigDict(extra="forbid")

    file: str = Field(WEIGHTS_FILE, description="Weights file name, inside the checkpoint folder.")
    sha256: str = Field(..., pattern=r"^[0-9a-f]{64}$", description="Hex SHA-256 of the weights file (required).")
    bytes: int | None = Field(None, ge=0, description="Size of the weights file.")


class CheckpointConfig(BaseModel):
    """A traffic-model checkpoint's ``config.json``."""

    model_config = ConfigDict(extra="forbid")

    adapter: str = Field(..., description="Registered name of the adapter that saved it.")
    config: dict[str, Any] = Field(..., description="The architecture config (the adapter's get_config()).")
    weights: WeightsInfo = Field(..., description="The weights file and its SHA-256.")
    options: dict[str, Any] = Field(default_factory=dict, description="Adapter options the model card's figures "
                                    "were measured with, e.g. {'guidance': 'no_collision'}; loading by name or "
                                    "folder applies those the caller does not give, and says so.")


def _record_hint(directory: str) -> str:
    return (f"re-save it with save_pretrained, or, for a folder you trust, record the digest with "
            f"`trafficrlhf checkpoint-digest {directory}`")


def read_checkpoint_config(directory: str, adapter_name: str, train_hint: str = "") -> CheckpointConfig:
    """The validated ``config.json`` of the checkpoint folder ``directory`` saved by adapter ``adapter_name``.

    Raises ``DataNotFoundError`` (with ``train_hint``, e.g. the training command) when there is none and
    ``DataFormatError`` for invalid JSON, unknown or missing keys, a missing SHA-256 or another adapter's weights.
    """
    directory = os.fspath(directory)
    path = os.path.join(directory, CONFIG_FILE)
    if not os.path.isfile(path):
        hint = f" Train one with `{train_hint}` or" if train_hint else ""
        raise DataNotFoundError(
            f"no {adapter_name} checkpoint at {directory!r} (missing {CONFIG_FILE}).{hint} pass checkpoint=DIR with "
            "a directory written by save_pretrained."
        )
    try:
        with open(path, encoding="utf-8") as handle:
            saved = json.load(handle)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"{path}: invalid JSON ({exc}); restore the file that save_pretrained wrote.") from exc
    if not isinstance(saved, dict):
        raise DataFormatError(f"{path}: expected a JSON object with keys adapter, config and weights, got a "
                              f"{type(saved).__name__}; restore the file that save_pretrained wrote.")
    if saved.get("adapter") != adapter_name:
        raise DataFormatError(
            f"{directory!r} holds weights for adapter {saved.get('adapter')!r}, not {adapter_name!r}; load it with "
            "that adapter."
        )
    if not isinstance(saved.get("weights"), dict) or "sha256" not in saved["weights"]:
        raise DataFormatError(f"{path} records no SHA-256 of the weights (`weights.sha256`), so they cannot be "
                              f"verified; {_record_hint(directory)}.")
    try:
        return CheckpointConfig.model_validate(saved)
    except ValidationError as exc:
        error = exc.errors()[0]
        where = ".".join(str(part) for part in error["loc"])
        raise DataFormatError(f"{path}: `{where}` {error['msg'].lower()} (value {error.get('input')!r}); restore "
                              "the file that save_pretrained wrote.") from None


def weights_path(directory: str, weights: WeightsInfo) -> str:
    """The weights file of ``directory``, refused unless it lies inside the folder (no ``..``, absolute path or
    link leading out of it)."""
    name = weights.file
    inside = os.path.realpath(directory)
    path = os.path.realpath(os.path.join(directory, name))
    if os.path.isabs(name) or os.path.commonpath([inside, path]) != inside or path == inside:
        raise DataFormatError(f"{os.path.join(directory, CONFIG_FILE)}: `weights.file` is {name!r}, which lies "
                              "outside the checkpoint folder; name a file inside it (model.safetensors).")
    if not os.path.isfile(path):
        raise DataNotFoundError(f"{directory!r} has no weights file {name!r}; the weights are missing.")
    return path


def _field_types(config_type: type) -> dict[str, Any]:
    hints = typing.get_type_hints(config_type)
    return {f.name: hints[f.name] for f in dataclasses.fields(config_type)}


def _ints(value: Any) -> list[int]:
    if isinstance(value, bool):
        return []
    if isinstance(value, int):
        return [value]
    if isinstance(value, (list, tuple)):
        return [v for item in value for v in _ints(item)]
    return []


def _floats(value: Any) -> list[float]:
    if isinstance(value, float):
        return [value]
    if isinstance(value, (list, tuple)):
        return [v for item in value for v in _floats(item)]
    return []


def parse_architecture_config(config_type: Any, raw: Any, label: str) -> Any:
    """``config_type.from_dict(raw)`` after checking ``raw`` against the dataclass's fields (see the module
    docstring); ``label`` names the folder or argument in errors. Non-dataclass types are built as they are."""
    if not isinstance(raw, dict):
        raise DataFormatError(f"{label}: the architecture config must be a JSON object, got "
                              f"{type(raw).__name__} {raw!r:.80}; restore the file that save_pretrained wrote.")
    if not dataclasses.is_dataclass(config_type):
        return config_type.from_dict(raw) if hasattr(config_type, "from_dict") else config_type(**raw)
    types = _field_types(config_type)
    unknown = sorted(set(raw) - set(types))
    if unknown:
        raise DataFormatError(f"{label}: unknown architecture config key(s) {unknown} for {config_type.__name__}; "
                              f"known keys: {sorted(types)}. Remove them or use a newer adapter.")
    defaults = {f.name: f.default for f in dataclasses.fields(config_type)}
    checked: dict[str, Any] = {}
    for name, value in raw.items():
        try:
            checked[name] = TypeAdapter(types[name]).validate_python(value, strict=False)
        except ValidationError as exc:
            raise DataFormatError(f"{label}: architecture config `{name}` = {value!r:.80} is not a valid "
                                  f"{getattr(types[name], '__name__', types[name])} "
                                  f"({exc.errors()[0]['msg'].lower()}); restore the value save_pretrained wrote.") \
                from None
        if isinstance(value, str) and types[name] is not str:
            raise DataFormatError(f"{label}: architecture config `{name}` = {value!r:.80} is a string; write it as "
                                  "a JSON number or list.")
        if any(not math.isfinite(v) for v in _floats(checked[name])):
            raise DataFormatError(f"{label}: architecture config `{name}` = {value!r:.80} is not finite.")
        ints = _ints(checked[name])
        if any(abs(v) > MAX_CONFIG_INT for v in ints):
            raise DataFormatError(f"{label}: architecture config `{name}` = {value!r:.80} exceeds "
                                  f"{MAX_CONFIG_INT:,}; no model of this size can be built here.")
        default = defaults.get(name)
        positive = (isinstance(default, (int, float)) and not isinstance(default, bool) and default > 0) \
            or isinstance(default, tuple)
        if positive and any(v < 1 for v in ints):
            raise DataFormatError(f"{label}: architecture config `{name}` = {value!r:.80} must be at least 1.")
        if positive and any(v <= 0 for v in _floats(checked[name])) and name in ("dt",):
            raise DataFormatError(f"{label}: architecture config `{name}` = {value!r:.80} must be positive.")
    try:
        return config_type.from_dict(checked) if hasattr(config_type, "from_dict") else config_type(**checked)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{label}: the architecture config does not fit {config_type.__name__} "
                              f"({' '.join(str(exc).split())}).") from None


def _header(path: str) -> dict[str, tuple[tuple[int, ...], str]]:
    """Name → (shape, dtype) of every tensor in a safetensors file, without reading the data."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(path, framework="pt") as handle:
            return {k: (tuple(handle.get_slice(k).get_shape()), str(handle.get_slice(k).get_dtype()))
                    for k in handle.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise DataFormatError(f"{path!r} is not a readable safetensors file ({exc}); it may be truncated or "
                              "corrupt: re-save it.") from exc


_FLOAT_DTYPES = {"F16", "BF16", "F32", "F64", "F8_E4M3", "F8_E5M2"}


def check_state(expected: dict[str, torch.Tensor], found: dict[str, tuple[tuple[int, ...], str]],
                where: str, what: str) -> None:
    """Every tensor of ``expected`` (a state dict, possibly on ``meta``) is in ``found`` (name → (shape, dtype
    name as safetensors writes it)) with its shape and kind (floating point or not), and nothing else is.

    ``where`` names the file in errors, ``what`` the architecture."""
    missing = sorted(set(expected) - set(found))
    unexpected = sorted(set(found) - set(expected))
    if missing or unexpected:
        raise DataFormatError(f"{where} does not fit {what}: missing tensors {missing[:5]}"
                              f"{' ...' if len(missing) > 5 else ''}, unexpected tensors {unexpected[:5]}"
                              f"{' ...' if len(unexpected) > 5 else ''}; config.json and the weights do not belong "
                              "together.")
    for name, tensor in expected.items():
        shape, dtype = found[name]
        if shape != tuple(tensor.shape):
            raise DataFormatError(f"{where}: tensor {name!r} has shape {shape} but {what} needs "
                                  f"{tuple(tensor.shape)}; config.json and the weights do not belong together.")
        if tensor.is_floating_point() != (dtype.upper() in _FLOAT_DTYPES):
            kind = "floating point" if tensor.is_floating_point() else str(tensor.dtype).replace("torch.", "")
            raise DataFormatError(f"{where}: tensor {name!r} is stored as {dtype} but {what} needs {kind}; the file "
                                  "was edited or written by another program: restore the saved weights.")


def _check_finite(tensors: dict[str, torch.Tensor], directory: str) -> None:
    for name, tensor in tensors.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            bad = int((~torch.isfinite(tensor)).sum())
            raise DataFormatError(f"checkpoint {directory!r}: tensor {name!r} holds {bad} NaN or infinite value(s); "
                                  "the weights are unusable: restore them or re-train.")


def _verified_tensors(directory: str, info: WeightsInfo, expected: dict[str, torch.Tensor], what: str,
                      device: str | torch.device) -> dict[str, torch.Tensor]:
    path = weights_path(directory, info)
    size = sum(t.numel() * t.element_size() for t in expected.values())
    # before hashing or reading; a truncated file is named by the SHA-256 check below
    check_safetensors_file(path, f"checkpoint {directory!r}: weights file", size, exact_size=False)
    check_state(expected, _header(path), repr(path), what)
    actual = sha256_file(path)
    if actual != info.sha256:
        raise DataFormatError(
            f"{path!r} does not match the SHA-256 recorded in config.json (expected {info.sha256[:16]}..., got "
            f"{actual[:16]}...): the weights were modified or truncated after saving. Restore the saved file, or "
            f"{_record_hint(directory)}."
        )
    tensors, _ = safe_load_file(path, device=device)
    _check_finite(tensors, directory)
    return {k: t.to(expected[k].dtype) for k, t in tensors.items()}


def load_checked_weights(module: torch.nn.Module, directory: str, adapter_name: str,
                         device: str | torch.device = "cpu") -> None:
    """Load the weights of checkpoint ``directory`` into the built ``module`` after every check above."""
    info = read_checkpoint_config(directory, adapter_name).weights
    expected = module.state_dict()
    tensors = _verified_tensors(directory, info, expected, f"the {adapter_name!r} model as built", device)
    module.load_state_dict(tensors, strict=True)


def build_checked(module_type: Any, cfg: Any, directory: str | None, adapter_name: str, label: str,
                  device: str | torch.device = "cpu") -> torch.nn.Module:
    """``module_type(cfg)`` built only after a ``meta``-device build shows its size and, with a checkpoint
    ``directory``, that the weights file fits it (then the weights are loaded, checked, into it)."""
    try:
        with torch.device("meta"):
            shadow = module_type(cfg)
    except (TypeError, ValueError, RuntimeError, IndexError) as exc:
        raise DataFormatError(f"{label}: the architecture config does not build a {module_type.__name__} "
                              f"({' '.join(str(exc).split())[:200]}); restore the config save_pretrained wrote.") \
            from None
    count = sum(t.numel() for t in shadow.state_dict().values())
    if count > MAX_PARAMETERS:
        raise DataFormatError(f"{label}: the architecture config asks for {count:,} parameters (over "
                              f"{MAX_PARAMETERS:,}, {4 * count / 2**30:.0f} GiB of float32); a layer size in it is "
                              "wrong: restore the config save_pretrained wrote.")
    tensors = None
    if directory is not None:
        info = read_checkpoint_config(directory, adapter_name).weights
        tensors = _verified_tensors(directory, info, shadow.state_dict(), f"the {adapter_name!r} config in "
                                    f"{os.path.join(directory, CONFIG_FILE)}", device)
    module = module_type(cfg)
    if tensors is not None:
        module.load_state_dict(tensors, strict=True)
    return module


def record_weights_digest(directory: str) -> str:
    """Write the SHA-256 (and size) of ``directory``'s weights file into its ``config.json``; returns the digest.

    For checkpoints saved before the digest was recorded; the weights are not changed."""
    path = os.path.join(directory, CONFIG_FILE)
    with open(path, encoding="utf-8") as handle:
        saved = json.load(handle)
    if not isinstance(saved, dict):
        raise DataFormatError(f"{path}: expected a JSON object.")
    weights = saved.get("weights") if isinstance(saved.get("weights"), dict) else {}
    name = weights.get("file", WEIGHTS_FILE)
    file = weights_path(directory, WeightsInfo(file=name, sha256="0" * 64))
    digest = sha256_file(file)
    saved["weights"] = {"file": name, "sha256": digest, "bytes": os.path.getsize(file)}
    with open(path, "w", encoding="utf-8") as handle:
        json.dump(saved, handle, indent=2)
        handle.write("\n")
    return digest
