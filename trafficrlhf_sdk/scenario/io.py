"""Reading safetensors files (scenarios, checkpoints, reward models) with one clear error, and the SHA-256 their
``config.json`` records."""

from __future__ import annotations

import hashlib
import os

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError

__all__ = ["safe_load_file", "sha256_file"]


def sha256_file(path: str) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def safe_load_file(path: str | os.PathLike[str],
                   device: str | torch.device = "cpu") -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Read tensors and header metadata from a safetensors file, turning every failure into one clear error."""
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
