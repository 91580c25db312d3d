"""``ScenarioTensor``: the one data structure every part of the SDK exchanges, and its file format (safetensors,
metadata as JSON strings in the header)."""

from __future__ import annotations

import json
import math
import numbers
import os
from dataclasses import dataclass, field, replace
from collections.abc import Sequence
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_bytes
from safetensors.torch import save as save_bytes
from safetensors.torch import save_file

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.errors import DataFormatError, ScenarioValidationError
from trafficrlhf_sdk.scenario.io import safe_load_file
from trafficrlhf_sdk.scenario.map import MapRaster, check_copies

__all__ = [
    "ScenarioTensor",
    "load_scenario",
    "save_scenario",
    "scenario_from_bytes",
    "scenario_from_tensors",
    "scenario_tensors",
    "scenario_to_bytes",
]

STATE_FIELDS = ("x", "y", "speed", "yaw")


@dataclass(frozen=True)
class ScenarioTensor:
    """A batch of traffic scenes on a common time grid.

    **Shape convention** (stated once, used everywhere): ``(batch B, agents A, time T, ...)``.

    Fields:
        states: float32 ``(B, A, T, 4)``: x, y (m, scene frame), speed (m/s, signed along the heading),
            yaw (rad, wrapped to [-pi, pi)). Entries where ``valid`` is False carry no meaning and are zeroed.
        valid: bool ``(B, A, T)``: whether the agent exists at that step. Padding agents are all False.
        extent: float32 ``(B, A, 2)``: box length and width (m).
        agent_type: int64 ``(B, A)``: :class:`~trafficrlhf_sdk.scenario.agents.AgentType` codes.
        controlled: bool ``(B, A)``: agents a traffic model drives; the others replay the log.
        dt: seconds between consecutive steps (0.1 by default).
        current_index: index along T of the last history step ("now"); the future starts after it.
        map: optional :class:`MapRaster` with one map per scene.
        origin: float64 ``(B, 2)``: world coordinates (m) of each scene frame's origin, so that
            world = scene + origin. A scene frame keeps float32 coordinates small and precise.
        scene_ids: one id per scene; ``agent_ids``: per scene, one id per agent slot ("" for padding).
        source: name of the scenario source that produced the batch.
        extras: free JSON-serializable metadata (per-batch).
    """

    states: torch.Tensor
    valid: torch.Tensor
    extent: torch.Tensor
    agent_type: torch.Tensor
    controlled: torch.Tensor
    dt: float = 0.1
    current_index: int = 0
    map: MapRaster | None = None
    origin: torch.Tensor | None = None
    scene_ids: tuple[str, ...] = ()
    agent_ids: tuple[tuple[str, ...], ...] = ()
    source: str = ""
    extras: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._validate()

    def replace_unchecked(self, **changes: Any) -> ScenarioTensor:
        """Like ``dataclasses.replace`` but skips validation: for hot loops whose inputs are known to be valid."""
        new = object.__new__(ScenarioTensor)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    # ------------------------------------------------------------ validation
    def _validate(self) -> None:
        s = self.states
        if s.dim() != 4 or s.shape[-1] != 4:
            raise ScenarioValidationError(
                f"`states` must have shape (B, A, T, 4) = (x, y, speed, yaw); got {tuple(s.shape)}."
            )
        if s.dtype != torch.float32:
            raise ScenarioValidationError(f"`states` must be float32; got {s.dtype}. Use `states.float()`.")
        b, a, t, _ = s.shape
        expected = {
            "valid": ((b, a, t), torch.bool),
            "extent": ((b, a, 2), torch.float32),
            "agent_type": ((b, a), torch.int64),
            "controlled": ((b, a), torch.bool),
        }
        for name, (shape, dtype) in expected.items():
            value = getattr(self, name)
            if not isinstance(value, torch.Tensor) or tuple(value.shape) != shape or value.dtype != dtype:
                got = (tuple(value.shape), value.dtype) if isinstance(value, torch.Tensor) else type(value).__name__
                raise ScenarioValidationError(
                    f"`{name}` must be a {dtype} tensor of shape {shape} to match `states` {tuple(s.shape)}; got {got}."
                )
        if not (self.dt > 0 and math.isfinite(self.dt)):
            raise ScenarioValidationError(f"`dt` must be a positive number of seconds; got {self.dt!r}.")
        if not 0 <= self.current_index < max(t, 1):
            raise ScenarioValidationError(
                f"`current_index` must index a step of the {t} steps in `states`; got {self.current_index}."
            )
        bad = ~torch.isfinite(s) & self.valid[..., None]
        if bad.any():
            scene, agent, step, component = (int(v) for v in bad.nonzero()[0])
            raise ScenarioValidationError(
                f"`states` holds a non-finite {STATE_FIELDS[component]} where `valid` is True (scene {scene}, agent"
                f" {agent}, step {step}); fix the data or mark that step invalid."
            )
        if not torch.isfinite(self.extent[self.valid.any(-1)]).all():
            raise ScenarioValidationError("`extent` holds NaN or inf for an agent that is valid at some step.")
        if not torch.isfinite(s).all():  # NaN only in invalid slots: zero them so masked sums stay finite
            object.__setattr__(self, "states", torch.where(self.valid[..., None], s, torch.zeros((), dtype=s.dtype)))
        if self.controlled.any() and (self.controlled & ~self.valid.any(-1)).any():
            raise ScenarioValidationError("`controlled` marks an agent that is never valid; unmark padding agents.")
        if self.map is not None and self.map.num_scenes != b:
            raise ScenarioValidationError(f"`map` holds {self.map.num_scenes} scenes but `states` holds {b}.")
        if self.origin is not None and tuple(self.origin.shape) != (b, 2):
            raise ScenarioValidationError(f"`origin` must have shape ({b}, 2); got {tuple(self.origin.shape)}.")
        if self.scene_ids and len(self.scene_ids) != b:
            raise ScenarioValidationError(f"`scene_ids` names {len(self.scene_ids)} scenes but `states` holds {b}.")
        if self.agent_ids and (len(self.agent_ids) != b or any(len(ids) != a for ids in self.agent_ids)):
            raise ScenarioValidationError(f"`agent_ids` must hold {b} tuples of {a} ids (one per agent slot).")

    # ----------------------------------------------------------------- sizes
    @property
    def num_scenes(self) -> int:
        """B."""
        return int(self.states.shape[0])

    @property
    def num_agents(self) -> int:
        """A (agent slots, padding included)."""
        return int(self.states.shape[1])

    @property
    def num_steps(self) -> int:
        """T."""
        return int(self.states.shape[2])

    @property
    def device(self) -> torch.device:
        """Device of the tensors."""
        return self.states.device

    @property
    def xy(self) -> torch.Tensor:
        """Positions ``(B, A, T, 2)`` (m)."""
        return self.states[..., :2]

    @property
    def speed(self) -> torch.Tensor:
        """Speeds ``(B, A, T)`` (m/s)."""
        return self.states[..., 2]

    @property
    def yaw(self) -> torch.Tensor:
        """Headings ``(B, A, T)`` (rad)."""
        return self.states[..., 3]

    # ----------------------------------------------------------------- views
    def time_slice(self, start: int, stop: int | None = None) -> ScenarioTensor:
        """Steps ``start:stop`` as a new scenario; ``current_index`` is shifted and clamped into the window."""
        stop = self.num_steps if stop is None else stop
        if not 0 <= start < stop <= self.num_steps:
            raise ScenarioValidationError(f"time window {start}:{stop} is outside 0:{self.num_steps}.")
        return self.replace_unchecked(  # a window of a valid scenario is valid
            states=self.states[:, :, start:stop],
            valid=self.valid[:, :, start:stop],
            current_index=min(max(self.current_index - start, 0), stop - start - 1),
        )

    @property
    def history(self) -> ScenarioTensor:
        """Steps ``0 .. current_index`` (inclusive)."""
        return self.time_slice(0, self.current_index + 1)

    @property
    def future(self) -> ScenarioTensor:
        """Steps after ``current_index``; its ``current_index`` is 0 (the first future step)."""
        if self.current_index + 1 >= self.num_steps:
            raise ScenarioValidationError("this scenario has no future steps after `current_index`.")
        return self.time_slice(self.current_index + 1)

    def with_future(self, future_states: torch.Tensor, future_valid: torch.Tensor | None = None) -> ScenarioTensor:
        """Replace everything after ``current_index`` with ``future_states (B, A, H, 4)``.

        ``future_valid (B, A, H)`` defaults to "valid wherever the agent is valid now". Returns a scenario of
        ``current_index + 1 + H`` steps.
        """
        b, a = self.num_scenes, self.num_agents
        if future_states.dim() != 4 or tuple(future_states.shape[:2]) != (b, a) or future_states.shape[-1] != 4:
            raise ScenarioValidationError(
                f"`future_states` must have shape ({b}, {a}, H, 4); got {tuple(future_states.shape)}."
            )
        h = future_states.shape[2]
        if future_valid is None:
            future_valid = self.valid[:, :, self.current_index, None].expand(b, a, h)
        hist = self.history
        return replace(
            self,
            states=torch.cat([hist.states, future_states.to(self.states.dtype)], 2),
            valid=torch.cat([hist.valid, future_valid.bool()], 2),
        )

    def actions(self) -> torch.Tensor:
        """Inverse unicycle dynamics: ``(B, A, T-1, 2)`` acceleration (m/s^2) and yaw rate (rad/s).

        Action ``t`` takes step ``t`` to step ``t+1`` exactly (before bounds) for speed and yaw. Entries whose
        two endpoints are not both valid are 0; see :attr:`action_valid`.
        """
        s = self.states
        acc = (s[:, :, 1:, 2] - s[:, :, :-1, 2]) / self.dt
        yaw_rate = wrap_angle(s[:, :, 1:, 3] - s[:, :, :-1, 3]) / self.dt
        return torch.stack([acc, yaw_rate], -1) * self.action_valid[..., None]

    @property
    def action_valid(self) -> torch.Tensor:
        """bool ``(B, A, T-1)``: both endpoints of the action are valid."""
        return self.valid[:, :, 1:] & self.valid[:, :, :-1]

    # ------------------------------------------------------------ batch ops
    def to(self, device: torch.device | str) -> ScenarioTensor:
        """The same scenario on ``device`` (``origin`` stays float64)."""
        return self.replace_unchecked(
            states=self.states.to(device),
            valid=self.valid.to(device),
            extent=self.extent.to(device),
            agent_type=self.agent_type.to(device),
            controlled=self.controlled.to(device),
            map=None if self.map is None else self.map.to(device),
            origin=None if self.origin is None else self.origin.to(device),
        )

    def __getitem__(self, index: int | slice | torch.Tensor | Sequence[int]) -> ScenarioTensor:
        """Select scenes along B; an int keeps the batch axis (B = 1)."""
        if isinstance(index, torch.Tensor) and index.dim() == 0 and index.dtype != torch.bool:
            index = int(index)  # a 0-d integer tensor selects one scene like an int
        elif isinstance(index, numbers.Integral) and not isinstance(index, int):
            index = int(index)  # numpy integers
        if isinstance(index, int):
            if not -self.num_scenes <= index < self.num_scenes:
                raise IndexError(f"scene index {index} out of range for {self.num_scenes} scenes")
            index = slice(index % self.num_scenes, index % self.num_scenes + 1)
        if not isinstance(index, (slice, torch.Tensor)):
            index = torch.as_tensor(list(index))
            if index.dtype != torch.bool:  # a list of bools is a mask, not the indices 0 and 1
                index = index.long()
        positions = list(range(self.num_scenes))[index] if isinstance(index, slice) else index.tolist()
        if isinstance(index, torch.Tensor) and index.dtype == torch.bool:
            positions = index.nonzero().flatten().tolist()
        # scenes of a valid batch form a valid batch; a window cut by `time_slice` (which may leave a controlled
        # agent without a valid step) stays as unchecked as it was
        return self.replace_unchecked(
            states=self.states[index],
            valid=self.valid[index],
            extent=self.extent[index],
            agent_type=self.agent_type[index],
            controlled=self.controlled[index],
            map=None if self.map is None else self.map.index(index),
            origin=None if self.origin is None else self.origin[index],
            scene_ids=tuple(self.scene_ids[i] for i in positions) if self.scene_ids else (),
            agent_ids=tuple(self.agent_ids[i] for i in positions) if self.agent_ids else (),
        )

    def repeat_scenes(self, copies: int) -> ScenarioTensor:
        """Each scene ``copies`` times in a row: ``B * copies`` scenes, scene-major (like ``repeat_interleave``).

        With one scene (B = 1) the copies are expanded views that share its memory, the map raster included:
        read-only, fine for scoring, not for in-place edits. With B > 1 they are copies.
        """
        check_copies(copies)
        if self.num_scenes != 1:
            return self[torch.arange(self.num_scenes).repeat_interleave(copies)]

        def grow(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t.expand(copies, *t.shape[1:])

        return self.replace_unchecked(
            states=grow(self.states), valid=grow(self.valid), extent=grow(self.extent),
            agent_type=grow(self.agent_type), controlled=grow(self.controlled), origin=grow(self.origin),
            map=None if self.map is None else self.map.repeat_scenes(copies),
            scene_ids=self.scene_ids * copies, agent_ids=self.agent_ids * copies)

    def __len__(self) -> int:
        return self.num_scenes

    @staticmethod
    def concat(scenarios: Sequence[ScenarioTensor]) -> ScenarioTensor:
        """Stack scenes along B, padding agents (A) and steps (T at the end) with invalid entries.

        All inputs must share ``dt`` and ``current_index``.
        """
        if not scenarios:
            raise ScenarioValidationError("`scenarios` is empty; pass at least one ScenarioTensor to concatenate.")
        first = scenarios[0]
        for other in scenarios[1:]:
            if other.dt != first.dt or other.current_index != first.current_index:
                raise ScenarioValidationError(
                    f"cannot concatenate scenarios with dt/current_index {first.dt}/{first.current_index} and "
                    f"{other.dt}/{other.current_index}; load them with the same source config."
                )
        a = max(s.num_agents for s in scenarios)
        t = max(s.num_steps for s in scenarios)

        def pad(x: torch.Tensor, s: ScenarioTensor, time_axis: bool) -> torch.Tensor:
            widths = [0, 0] * (x.dim() - 2 - int(time_axis))
            if time_axis:
                widths += [0, t - s.num_steps]
            widths += [0, a - s.num_agents]
            return torch.nn.functional.pad(x, widths)

        maps = [s.map for s in scenarios]
        has_map = all(m is not None for m in maps)
        origins = [s.origin for s in scenarios]
        return ScenarioTensor(
            states=torch.cat([pad(s.states, s, True) for s in scenarios]),
            valid=torch.cat([pad(s.valid, s, True) for s in scenarios]),
            extent=torch.cat([pad(s.extent, s, False) for s in scenarios]),
            agent_type=torch.cat([pad(s.agent_type, s, False) for s in scenarios]),
            controlled=torch.cat([pad(s.controlled, s, False) for s in scenarios]),
            dt=first.dt,
            current_index=first.current_index,
            map=MapRaster.concat(maps) if has_map else None,  # type: ignore[arg-type]
            origin=torch.cat(origins) if all(o is not None for o in origins) else None,  # type: ignore[arg-type]
            scene_ids=tuple(i for s in scenarios for i in (s.scene_ids or ("",) * s.num_scenes)),
            agent_ids=tuple(
                tuple(ids) + ("",) * (a - len(ids))
                for s in scenarios
                for ids in (s.agent_ids or (("",) * s.num_agents,) * s.num_scenes)
            ),
            source=first.source if all(s.source == first.source for s in scenarios) else "mixed",
            extras=dict(first.extras),
        )

    # ------------------------------------------------------------------ io
    def save(self, path: str) -> None:
        """Write to ``path`` as safetensors (tensors) with the metadata as JSON strings."""
        save_scenario(self, path)

    @staticmethod
    def load(path: str, device: str | torch.device = "cpu") -> ScenarioTensor:
        """Read a file written by :meth:`save`; corrupt or truncated files raise ``DataFormatError``."""
        return load_scenario(path, device)


# ---------------------------------------------------------------------- file format
# safetensors: the tensors as they are, the metadata as JSON strings in the header
FORMAT_VERSION = "1"
_TENSOR_FIELDS = ("states", "valid", "extent", "agent_type", "controlled", "origin")
_MAP_FIELDS = ("world_to_pixel", "polylines", "polyline_valid", "polyline_type")


def save_scenario(scenario: ScenarioTensor, path: str | os.PathLike[str]) -> None:
    """Write ``scenario`` to ``path`` (a ``.safetensors`` file)."""
    tensors, metadata = scenario_tensors(scenario)
    save_file(tensors, os.fspath(path), metadata=metadata)


def scenario_to_bytes(scenario: ScenarioTensor) -> bytes:
    """``scenario`` as the bytes of a safetensors file (what :func:`save_scenario` writes), e.g. for a database."""
    tensors, metadata = scenario_tensors(scenario)
    return save_bytes(tensors, metadata=metadata)


def scenario_from_bytes(data: bytes, name: str = "<bytes>") -> ScenarioTensor:
    """Read bytes written by :func:`scenario_to_bytes`; ``name`` labels the blob in error messages."""
    try:
        tensors = load_bytes(bytes(data))
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
        scene_map = scenario.map  # the file stores one zero-padded raster per scene and each one's own size
        tensors["map.raster"] = scene_map.padded().detach().cpu().contiguous()
        tensors["map.sizes"] = scene_map.scene_sizes().detach().cpu().contiguous()
        for name in _MAP_FIELDS:
            value = getattr(scene_map, name)
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
                raster=tensors["map.raster"], sizes=tensors.get("map.sizes"),
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
