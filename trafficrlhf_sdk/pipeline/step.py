"""The one cache and resume scheme of the pipeline: a step's folder and its manifest, ``step.json``.

A step is a function of its resolved inputs (a JSON-able dict: the configuration it runs with and the digests of
the steps it reads from) that writes its output folder. :func:`run_step` runs it at most once:

- ``step.json`` present with the same inputs: the recorded outputs are returned, nothing runs;
- no ``step.json`` (never run, or stopped midway): the step runs; what an interrupted run left in the folder is
  the step's own business (alignment and reward-model training continue from their newest epoch checkpoint, a
  campaign gets the contexts it lacks);
- ``step.json`` with other inputs: :class:`StepConfigError`, naming each input that differs, unless
  ``overwrite``: then the folder is emptied and the step runs again.

``step.json`` holds ``step`` (the name), ``digest`` (SHA-256 of the inputs), ``inputs``, ``completed`` (UTC,
ISO 8601), ``seconds`` and ``outputs``. It is written last, atomically, so a folder without it is never taken for
a finished step.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

from trafficrlhf_sdk.errors import DataFormatError, TrafficRLHFError

__all__ = ["MANIFEST", "StepConfigError", "StepResult", "input_differences", "inputs_digest", "read_manifest",
           "run_step"]

MANIFEST = "step.json"
_SHOWN = 60  # characters of a differing value shown in an error


class StepConfigError(TrafficRLHFError):
    """A finished step's folder was asked to hold the same step with other inputs."""


@dataclass(frozen=True)
class StepResult:
    """A finished step: its name, folder, the digest of its inputs and its outputs (``result["key"]`` reads
    ``outputs``). ``cached``: the outputs were read from ``step.json``, nothing ran."""

    name: str
    folder: str
    digest: str
    outputs: dict[str, Any] = field(default_factory=dict)
    cached: bool = False

    def __getitem__(self, key: str) -> Any:
        return self.outputs[key]

    def get(self, key: str, default: Any = None) -> Any:
        """``outputs.get(key, default)``."""
        return self.outputs.get(key, default)


def _plain(value: Any) -> Any:
    """``value`` as JSON reads it back (tuples become lists, keys strings), so stored and new inputs compare."""
    return json.loads(json.dumps(value, sort_keys=True, default=str))


def inputs_digest(inputs: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of ``inputs`` written as canonical JSON (sorted keys)."""
    text = json.dumps(_plain(dict(inputs)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def input_differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    """Every dotted key where ``old`` and ``new`` differ, as ``key: old -> new`` (``<absent>`` for a missing key);
    lists of different length are one difference."""
    if isinstance(old, dict) and isinstance(new, dict):
        lines = []
        for key in sorted(set(old) | set(new), key=str):
            path = f"{prefix}.{key}" if prefix else str(key)
            if key not in old or key not in new:
                lines.append(f"{path}: {_shown(old.get(key, '<absent>'))} -> {_shown(new.get(key, '<absent>'))}")
            else:
                lines += input_differences(old[key], new[key], path)
        return lines
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        return [line for i, (a, b) in enumerate(zip(old, new)) for line in input_differences(a, b, f"{prefix}[{i}]")]
    return [] if old == new else [f"{prefix or '<inputs>'}: {_shown(old)} -> {_shown(new)}"]


def _shown(value: Any) -> str:
    text = value if value == "<absent>" else json.dumps(value, default=str)
    return text if len(text) <= _SHOWN else text[: _SHOWN - 3] + "..."


def read_manifest(folder: str) -> dict[str, Any] | None:
    """The ``step.json`` of ``folder``, or None when the step never finished there."""
    path = os.path.join(folder, MANIFEST)
    if not os.path.isfile(path):
        return None
    try:
        with open(path, encoding="utf-8") as handle:
            manifest = json.load(handle)
    except (OSError, json.JSONDecodeError) as exc:
        raise DataFormatError(f"{path!r} is not a readable step manifest ({exc}); delete it to run the step "
                              "again.") from None
    if not isinstance(manifest, dict) or not {"step", "digest", "inputs", "outputs"} <= set(manifest):
        raise DataFormatError(f"{path!r} is not a step manifest (it needs step, digest, inputs and outputs); "
                              "delete it to run the step again.")
    return manifest


def run_step(name: str, folder: str, inputs: Mapping[str, Any], work: Callable[[], Mapping[str, Any]], *,
             after: Sequence[StepResult] = (), overwrite: bool = False,
             log: Callable[[str], None] | None = None) -> StepResult:
    """Run step ``name`` in ``folder`` once for ``inputs``; see the module docstring.

    Args:
        name: the step's name, recorded in ``step.json`` and shown in messages.
        folder: its output folder (created); ``work`` writes there.
        inputs: everything that decides its outputs, JSON-able (configurations, paths, seeds).
        work: does the step and returns its outputs (JSON-able: paths, counts, metrics).
        after: the steps it reads from; their digests join ``inputs`` (as ``after``), so a step redone upstream
            with other settings makes this one differ too.
        overwrite: a finished step with other inputs is deleted and run again instead of refused.
        log: hears one line when the step is skipped, refused or redone.

    Returns:
        :class:`StepResult` (``cached`` when nothing ran).
    """
    resolved = _plain({**inputs, **({"after": [f"{r.name}:{r.digest}" for r in after]} if after else {})})
    digest = inputs_digest(resolved)
    manifest = read_manifest(folder)
    if manifest is not None and manifest["digest"] == digest:
        if log is not None:
            log(f"{name}: done before ({folder}); skipped")
        return StepResult(name, folder, digest, manifest["outputs"], cached=True)
    if manifest is not None:
        changes = input_differences(manifest["inputs"], resolved)
        if not overwrite:
            raise StepConfigError(
                f"step {name!r} in {folder!r} was finished with other settings: {'; '.join(changes[:8])}"
                f"{'; ...' if len(changes) > 8 else ''}. Use another output folder to keep both, or overwrite it "
                "(`--overwrite`, `overwrite=True`) to run it again with these settings.")
        if log is not None:
            log(f"{name}: finished with other settings ({'; '.join(changes[:3])}); overwriting {folder}")
        shutil.rmtree(folder)
    os.makedirs(folder, exist_ok=True)
    began = time.perf_counter()
    outputs = _plain(dict(work()))
    record = {"step": name, "digest": digest, "inputs": resolved,
              "completed": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "seconds": round(time.perf_counter() - began, 3), "outputs": outputs}
    tmp = os.path.join(folder, MANIFEST + ".tmp")
    with open(tmp, "w", encoding="utf-8") as handle:
        json.dump(record, handle, indent=2, allow_nan=True)
    os.replace(tmp, os.path.join(folder, MANIFEST))
    return StepResult(name, folder, digest, outputs)
