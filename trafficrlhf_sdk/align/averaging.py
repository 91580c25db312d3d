"""Weight averaging of aligned checkpoints (a "model soup", Wortsman et al. 2022).

Runs fine-tuned from the same starting weights with different seeds often end close together in weight space,
and then their elementwise mean scores at least as well as the average run and varies less: on nuScenes val,
CTG seeds at 0.1292 / 0.1425 / 0.1273 averaged to 0.1190. Not always: for TrafficGen, whose six modes are trained
winner-takes-all, one average of two seeds (0.2035) was worse than either seed (0.1795 / 0.1793), so evaluate
an average on held-out scenes before using it (docs/explanation/alignment-results.md).

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
from trafficrlhf_sdk.scenario.io import safe_load_file

__all__ = ["AVERAGE_FILE", "average_checkpoints"]

AVERAGE_FILE = "averaged_from.json"  # provenance: the source folders and their weights


def _read(directory: str) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    config_path = os.path.join(directory, "config.json")
    weights_path = os.path.join(directory, "model.safetensors")
    for path in (config_path, weights_path):
        if not os.path.isfile(path):
            raise DataNotFoundError(f"{path!r} does not exist: each folder to average must hold config.json and "
                                    "model.safetensors (written by `trafficrlhf align --out` or save_pretrained).")
    with open(config_path, encoding="utf-8") as handle:
        try:
            config = json.load(handle)
        except json.JSONDecodeError as exc:
            raise DataFormatError(f"{config_path}: invalid JSON ({exc}).") from exc
    return config, safe_load_file(weights_path)[0]


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
    summed = {k: v.double() * weights[0] if v.is_floating_point() else v for k, v in first.items()}
    for directory, weight in zip(dirs[1:], weights[1:]):
        config, state = _read(directory)
        if config != first_config:
            raise DataFormatError(f"{directory!r} has another config.json than {dirs[0]!r} (adapter "
                                  f"{config.get('adapter')!r} vs {first_config.get('adapter')!r}); only "
                                  "checkpoints of one adapter and architecture can be averaged.")
        if state.keys() != first.keys():
            extra = sorted(state.keys() ^ first.keys())[:5]
            raise DataFormatError(f"{directory!r} and {dirs[0]!r} hold different tensors (e.g. {extra}).")
        for name, tensor in state.items():
            ref = first[name]
            if tensor.shape != ref.shape or tensor.dtype != ref.dtype:
                raise DataFormatError(f"tensor {name!r} is {tuple(tensor.shape)} {tensor.dtype} in {directory!r} "
                                      f"but {tuple(ref.shape)} {ref.dtype} in {dirs[0]!r}.")
            if tensor.is_floating_point():
                summed[name] = summed[name] + tensor.double() * weight
            elif not torch.equal(tensor, ref):
                raise DataFormatError(f"integer tensor {name!r} differs between {directory!r} and {dirs[0]!r}; "
                                      "it cannot be averaged.")
    bad = [name for name, v in summed.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise DataFormatError(f"the average has non-finite values in {bad[:5]}: an input checkpoint holds NaN or "
                              "inf; leave it out.")
    averaged = {k: (v.to(first[k].dtype) if first[k].is_floating_point() else v).contiguous()
                for k, v in summed.items()}
    os.makedirs(output_dir, exist_ok=True)
    with open(os.path.join(output_dir, "config.json"), "w", encoding="utf-8") as handle:
        json.dump(first_config, handle, indent=2)
    save_file(averaged, os.path.join(output_dir, "model.safetensors"),
              metadata={"format": "pt", "adapter": str(first_config.get("adapter"))})
    with open(os.path.join(output_dir, AVERAGE_FILE), "w", encoding="utf-8") as handle:
        json.dump({"sources": dirs, "weights": weights}, handle, indent=2)
    return output_dir
