"""Save and load :class:`ScenarioTensor` as safetensors; metadata travels as JSON strings in the header."""

from __future__ import annotations

import json
import os
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load, load_file, save, save_file

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, ScenarioValidationError
from trafficrlhf_sdk.scenario.map import MapRaster
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = [
    "load_scenario",
    "safe_load_file",
    "save_scenario",
    "scenario_from_bytes",
    "scenario_from_tensors",
    "scenario_tensors",
    "scenario_to_bytes",
]

FORMAT_VERSION = "1"
_TENSOR_FIELDS = ("states", "valid", "extent", "agent_type", "controlled", "origin")
_MAP_FIELDS = ("raster", "world_to_pixel", "polylines", "polyline_valid", "polyline_type")


def save_scenario(scenario: ScenarioTensor, path: str | os.PathLike[str]) -> None:
    """Write ``scenario`` to ``path`` (a ``.safetensors`` file)."""
    tensors, metadata = scenario_tensors(scenario)
    save_file(tensors, os.fspath(path), metadata=metadata)


def scenario_to_bytes(scenario: ScenarioTensor) -> bytes:
    """``scenario`` as the bytes of a safetensors file (what :func:`save_scenario` writes), e.g. for a database."""
    tensors, metadata = scenario_tensors(scenario)
    return save(tensors, metadata=metadata)


def scenario_from_bytes(data: bytes, name: str = "<bytes>") -> ScenarioTensor:
    """Read bytes written by :func:`scenario_to_bytes`; ``name`` labels the blob in error messages."""
    try:
        tensors = load(bytes(data))
        header_len = int.from_bytes(bytes(data[:8]), "little")
        metadata = dict(json.loads(bytes(data[8 : 8 + header_len])).get("__metadata__") or {})
    except (SafetensorError, ValueError, RuntimeError, TypeError) as exc:
        raise DataFormatError(f"{name} is not a readable safetensors blob ({exc}); it may be truncated.") from exc
    return scenario_from_tensors(tensors, metadata, name)


def scenario_tensors(scenario: ScenarioTensor) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """The tensors (CPU, contiguous) and string metadata that :func:`save_scenario` writes."""
    tensors: dict[str, torch.Tensor] = {}
    for name in _TENSOR_FIELDS:
        value = getattr(scenario, name)
        if value is not None:
            tensors[name] = value.detach().cpu().contiguous()
    if scenario.map is not None:
        dense_map = scenario.map.dense()  # one raster row per scene, as the file format stores it
        for name in _MAP_FIELDS:
            value = getattr(dense_map, name)
            if value is not None:
                tensors[f"map.{name}"] = value.detach().cpu().contiguous()
    metadata = {
        "format": "pt",
        "trafficrlhf_scenario": FORMAT_VERSION,
        "dt": json.dumps(scenario.dt),
        "current_index": json.dumps(scenario.current_index),
        "scene_ids": json.dumps(list(scenario.scene_ids)),
        "agent_ids": json.dumps([list(ids) for ids in scenario.agent_ids]),
        "source": json.dumps(scenario.source),
        "extras": json.dumps(scenario.extras),
        "map_layers": json.dumps(list(scenario.map.layers) if scenario.map is not None else None),
    }
    return tensors, metadata


def safe_load_file(path: str | os.PathLike[str],
                   device: str | torch.device = "cpu") -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Read tensors and header metadata from a safetensors file, turning every failure into one clear error."""
    from safetensors import safe_open

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DataNotFoundError(f"safetensors file not found: {path!r}; check the path.")
    try:
        with safe_open(path, framework="pt") as handle:
            metadata = dict(handle.metadata() or {})
        tensors = load_file(path, device=str(device))
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise DataFormatError(
            f"{path!r} is not a readable safetensors file ({exc}); it may be truncated or corrupt: re-save it."
        ) from exc
    return tensors, metadata


def load_scenario(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> ScenarioTensor:
    """Read a scenario written by :func:`save_scenario`."""
    tensors, meta = safe_load_file(path, device)
    return scenario_from_tensors(tensors, meta, repr(os.fspath(path)))


def scenario_from_tensors(tensors: dict[str, torch.Tensor], meta: dict[str, str], label: str) -> ScenarioTensor:
    """Build the scenario from tensors and header metadata; ``label`` names the file or blob in errors."""
    if meta.get("trafficrlhf_scenario") != FORMAT_VERSION:
        raise DataFormatError(
            f"{label} is a safetensors file but not a TrafficRLHF scenario (header key "
            f"'trafficrlhf_scenario' is {meta.get('trafficrlhf_scenario')!r}, expected {FORMAT_VERSION!r})."
        )
    required = [name for name in _TENSOR_FIELDS if name != "origin"]
    if "map.raster" in tensors:
        required.append("map.world_to_pixel")
    missing = [name for name in required if name not in tensors]
    if missing:
        raise DataFormatError(
            f"{label} is a TrafficRLHF scenario header without the tensors {missing}; the file is "
            "incomplete: re-save it."
        )
    try:
        decoded: dict[str, Any] = {k: json.loads(meta[k]) for k in ("dt", "current_index", "scene_ids",
                                                                     "agent_ids", "source", "extras", "map_layers")}
        scenario_map = None
        if "map.raster" in tensors:
            scenario_map = MapRaster(
                layers=tuple(decoded["map_layers"]),
                **{name: tensors.get(f"map.{name}") for name in _MAP_FIELDS},  # type: ignore[arg-type]
            )
        return ScenarioTensor(
            **{name: tensors.get(name) for name in _TENSOR_FIELDS},  # type: ignore[arg-type]
            dt=float(decoded["dt"]),
            current_index=int(decoded["current_index"]),
            map=scenario_map,
            scene_ids=tuple(decoded["scene_ids"]),
            agent_ids=tuple(tuple(ids) for ids in decoded["agent_ids"]),
            source=decoded["source"],
            extras=decoded["extras"],
        )
    except (KeyError, json.JSONDecodeError, TypeError) as exc:
        raise DataFormatError(f"{label}: scenario metadata is missing or malformed ({exc!r}).") from exc
    except ScenarioValidationError as exc:
        raise DataFormatError(f"{label} holds an invalid scenario: {exc}") from exc
