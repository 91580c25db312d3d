"""Weight averaging (a "model soup", Wortsman et al. 2022) and extrapolation (ExPO) of aligned checkpoints.

Runs fine-tuned from the same starting weights with different seeds often end close together in weight space,
and then their elementwise mean scores at least as well as the average run and varies less; not always (a
multi-modal decoder trained winner-takes-all may average badly), so evaluate an average on held-out scenes
before using it.

:func:`extrapolate_checkpoint` moves further along the direction alignment took: base + factor x (aligned - base),
optionally plus weighted changes of later fine-tuning stages (``directions``). Factors in [0, 1) interpolate back
towards the base (WiSE-FT); factors above 1 extrapolate past the aligned weights (ExPO, Zheng et al. 2024,
"Weak-to-Strong Extrapolation Expedites Alignment"): PPO with a KL term and an imitation loss stops short of where
the reward points. Choose the factor on held-out scenes: too far and the model leaves the region where its
imitation loss holds.

Works on any adapter checkpoint written by ``save_pretrained`` (``config.json`` + ``model.safetensors``); the
SDK never looks inside the tensors beyond their names, shapes and dtypes.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from typing import Any

import torch
from safetensors.torch import save_file

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, TrafficRLHFError
from trafficrlhf_sdk.models.checkpoint import read_checkpoint_config, sha256_file
from trafficrlhf_sdk.models.checkpoint import weights_path as checkpoint_weights_path
from trafficrlhf_sdk.scenario.io import safe_load_file

__all__ = ["AVERAGE_FILE", "EXTRAPOLATE_FILE", "average_checkpoints", "extrapolate_checkpoint"]

AVERAGE_FILE = "averaged_from.json"  # provenance: the source folders and their weights
EXTRAPOLATE_FILE = "extrapolated_from.json"  # provenance: base, aligned and the factor


def _read(directory: str) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    config_path = os.path.join(directory, "config.json")
    weights_path = os.path.join(directory, "model.safetensors")
    for path in (config_path, weights_path):
        if not os.path.isfile(path):
            raise DataNotFoundError(f"{path!r} does not exist: each checkpoint folder must hold config.json and "
                                    "model.safetensors (written by `trafficrlhf align --out` or save_pretrained).")
    with open(config_path, encoding="utf-8") as handle:
        try:
            config = json.load(handle)
        except json.JSONDecodeError as exc:
            raise DataFormatError(f"{config_path}: invalid JSON ({exc}).") from exc
    adapter = config.get("adapter") if isinstance(config, dict) else None
    info = read_checkpoint_config(directory, str(adapter)).weights  # the SHA-256 is required and checked
    path = checkpoint_weights_path(directory, info)
    if sha256_file(path) != info.sha256:
        raise DataFormatError(f"{path!r} does not match the SHA-256 recorded in {config_path}: the weights were "
                              "modified or truncated after saving; restore them before combining.")
    return config, safe_load_file(path)[0]


def average_checkpoints(directories: Sequence[str], output_dir: str,
                        weights: Sequence[float] | None = None) -> str:
    """Write the (weighted) mean of the checkpoints in ``directories`` to ``output_dir``; returns ``output_dir``.

    Args:
        directories: two or more adapter checkpoints of the same adapter and architecture (equal
            ``config.json``, the same tensor names, shapes and dtypes).
        output_dir: where ``config.json``, ``model.safetensors`` and ``averaged_from.json`` are written (it must
            not be one of ``directories``).
        weights: one non-negative weight per checkpoint (normalized to sum 1); None: uniform.

    Floating-point tensors are averaged in float64 and stored in their own dtype; integer tensors (counters,
    buffers) must be equal in every checkpoint and are copied.
    """
    dirs = [str(d) for d in directories]
    if len(dirs) < 2:
        raise TrafficRLHFError(f"`directories` has {len(dirs)} folder(s); average at least two checkpoints.")
    if os.path.abspath(output_dir) in {os.path.abspath(d) for d in dirs}:
        raise TrafficRLHFError(f"`output_dir` {output_dir!r} is one of the inputs; write the average elsewhere.")
    if weights is None:
        weights = [1.0] * len(dirs)
    weights = [float(w) for w in weights]
    if len(weights) != len(dirs) or any(not math.isfinite(w) or w < 0 for w in weights) or sum(weights) <= 0:
        raise TrafficRLHFError(f"`weights` is {weights}; give {len(dirs)} non-negative numbers, not all zero.")
    total = sum(weights)
    weights = [w / total for w in weights]

    first_config, first = _read(dirs[0])
    configs = [first_config]
    summed = {k: v.double() * weights[0] if v.is_floating_point() else v for k, v in first.items()}
    for directory, weight in zip(dirs[1:], weights[1:]):
        config, state = _read(directory)
        _check_compatible(directory, config, state, dirs[0], first_config, first)
        configs.append(config)
        for name, tensor in state.items():
            if tensor.is_floating_point():
                summed[name] = summed[name] + tensor.double() * weight
    _write(output_dir, _merged(configs), first, summed, "average", AVERAGE_FILE, {"sources": dirs, "weights": weights})
    return output_dir


def extrapolate_checkpoint(base_dir: str, aligned_dir: str, output_dir: str, factor: float,
                           directions: Sequence[tuple[str, str, float]] = ()) -> str:
    """Write ``base + factor * (aligned - base)`` (plus any further ``directions``) to ``output_dir``; returns it.

    Args:
        base_dir: the checkpoint alignment started from (e.g. the model's bundled checkpoint).
        aligned_dir: an aligned checkpoint of the same adapter and architecture (one run or a seed average).
        output_dir: where ``config.json``, ``model.safetensors`` and ``extrapolated_from.json`` are written (not
            one of the inputs).
        factor: 0 gives the base, 1 the aligned weights, between them an interpolation, above 1 an
            extrapolation along the alignment direction (non-negative, finite).
        directions: further ``(from_dir, to_dir, weight)`` terms, each adding ``weight * (to - from)``: the
            change a second fine-tuning stage made (task arithmetic, Ilharco et al. 2023), e.g. a realism
            stage run from the aligned checkpoint, added to an extrapolated failure direction. Weights are
            finite and may be negative (to subtract a direction).

    Computed per tensor in float64 and stored in the input dtype, so tensors alignment left unchanged (frozen
    parameter groups) stay bitwise equal to the base's. Integer tensors must be equal in all and are copied.
    """
    if not isinstance(factor, (int, float)) or not math.isfinite(factor) or factor < 0:
        raise TrafficRLHFError(f"`factor` is {factor!r}; give a finite number >= 0 (1 reproduces the aligned "
                               "weights, 2 goes as far again past them).")
    terms = [(str(a), str(b), w) for a, b, w in directions]
    for source, target, weight in terms:
        if not isinstance(weight, (int, float)) or not math.isfinite(weight):
            raise TrafficRLHFError(f"the weight of direction {source!r} -> {target!r} is {weight!r}; give a "
                                   "finite number (1 adds the whole change, -1 removes it).")
    inputs = {os.path.abspath(d) for d in (base_dir, aligned_dir, *(x for t in terms for x in t[:2]))}
    if os.path.abspath(output_dir) in inputs:
        raise TrafficRLHFError(f"`output_dir` {output_dir!r} is one of the inputs; write the result elsewhere.")
    base_config, base = _read(base_dir)
    loaded = {os.path.abspath(base_dir): (base_config, base)}  # a folder named twice (e.g. FROM = aligned) is read once

    def checked(directory: str) -> dict[str, torch.Tensor]:
        key = os.path.abspath(directory)
        if key not in loaded:
            loaded[key] = _read(directory)
            _check_compatible(directory, *loaded[key], base_dir, base_config, base)
        return loaded[key][1]

    aligned = checked(aligned_dir)
    moved = {name: base[name].double() + float(factor) * (tensor.double() - base[name].double())
             if tensor.is_floating_point() else tensor for name, tensor in aligned.items()}
    for source, target, weight in terms:
        start, end = checked(source), checked(target)
        for name, tensor in end.items():
            if tensor.is_floating_point():
                moved[name] = moved[name] + float(weight) * (tensor.double() - start[name].double())
    configs = [config for config, _ in loaded.values()]
    record: dict[str, Any] = {"base": str(base_dir), "aligned": str(aligned_dir), "factor": float(factor)}
    if terms:
        record["directions"] = [{"from": a, "to": b, "weight": float(w)} for a, b, w in terms]
    _write(output_dir, _merged(configs), base, moved, "extrapolation", EXTRAPOLATE_FILE, record)
    return output_dir


def _merged(configs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The first config with the fields that only later ones record added (see :func:`_check_compatible`)."""
    fields: dict[str, Any] = {}
    for config in reversed(configs):
        fields.update(config.get("config") or {})
    return {**configs[0], "config": fields}


def _check_compatible(directory: str, config: dict[str, Any], state: dict[str, torch.Tensor], ref_dir: str,
                      ref_config: dict[str, Any], ref: dict[str, torch.Tensor]) -> None:
    """Raise DataFormatError unless two checkpoints share adapter, architecture, tensor names/shapes/dtypes and
    integer tensors."""
    if config.get("adapter") != ref_config.get("adapter"):
        raise DataFormatError(f"{directory!r} holds adapter {config.get('adapter')!r} weights but {ref_dir!r} "
                              f"{ref_config.get('adapter')!r}; only checkpoints of one adapter can be combined.")
    # A field only one config records is one added to the adapter's config after the other checkpoint was
    # saved (it loads with the default); the tensor names and shapes below still have to match exactly.
    fields, ref_fields = config.get("config") or {}, ref_config.get("config") or {}
    differing = {k: (fields[k], ref_fields[k]) for k in fields.keys() & ref_fields.keys() if fields[k] != ref_fields[k]}
    if differing:
        shown = "; ".join(f"{k}: {a!r} vs {b!r}" for k, (a, b) in sorted(differing.items())[:5])
        raise DataFormatError(f"{directory!r} and {ref_dir!r} have different architecture configs ({shown}); "
                              "only checkpoints of one architecture can be combined.")
    if state.keys() != ref.keys():
        extra = sorted(state.keys() ^ ref.keys())[:5]
        raise DataFormatError(f"{directory!r} and {ref_dir!r} hold different tensors (e.g. {extra}).")
    for name, tensor in state.items():
        other = ref[name]
        if tensor.shape != other.shape or tensor.dtype != other.dtype:
            raise DataFormatError(f"tensor {name!r} is {tuple(tensor.shape)} {tensor.dtype} in {directory!r} "
                                  f"but {tuple(other.shape)} {other.dtype} in {ref_dir!r}.")
        if not tensor.is_floating_point() and not torch.equal(tensor, other):
            raise DataFormatError(f"integer tensor {name!r} differs between {directory!r} and {ref_dir!r}; "
                                  "it cannot be combined.")


def _write(output_dir: str, config: dict[str, Any], ref: dict[str, torch.Tensor], combined: dict[str, torch.Tensor],
           what: str, record_name: str, record: dict[str, Any]) -> None:
    """Cast ``combined`` (float64) back to the dtypes of ``ref`` and save it with its provenance record."""
    bad = [name for name, v in combined.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise DataFormatError(f"the {what} has non-finite values in {bad[:5]}: an input checkpoint holds NaN or "
                              "inf; leave it out.")
    tensors = {k: (v.to(ref[k].dtype) if ref[k].is_floating_point() else v).contiguous() for k, v in combined.items()}
    os.makedirs(output_dir, exist_ok=True)
    weights = os.path.join(output_dir, "model.safetensors")
    save_file(tensors, weights, metadata={"format": "pt", "adapter": str(config.get("adapter"))})
    config = {**config, "weights": {"file": "model.safetensors", "sha256": sha256_file(weights),
                                    "bytes": os.path.getsize(weights)}}
    with open(os.path.join(output_dir, "config.json"), "w", encoding="utf-8") as handle:
        json.dump(config, handle, indent=2)
    with open(os.path.join(output_dir, record_name), "w", encoding="utf-8") as handle:
        json.dump(record, handle, indent=2)
