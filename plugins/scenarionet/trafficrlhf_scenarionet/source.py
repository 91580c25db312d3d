"""Reader for ScenarioNet scenario pickles (nuScenes, Waymo, nuPlan, Argoverse 2 exports)."""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from pydantic import Field

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, InputLimitError
from trafficrlhf_sdk.scenario import (
    AgentType,
    MapRaster,
    ScenarioSource,
    ScenarioTensor,
    SourceConfig,
    default_data_root,
)
from trafficrlhf_sdk.scenario.checks import OPTIONS_HINT, check_agent_count, check_on_map
from trafficrlhf_scenarionet.map_raster import LAYERS, parse_map_features, rasterize, vectorize
from trafficrlhf_scenarionet.unpickler import restricted_load

__all__ = ["ROOT_SPLIT", "ScenarioNetConfig", "ScenarioNetSource", "Tracks", "read_scenario", "read_tracks"]

ROOT_SPLIT = "all"  # split name of the pickles lying directly in the root
SUMMARY_FILES = frozenset({"dataset_summary.pkl", "dataset_mapping.pkl"})
REQUIRED_KEYS = ("length", "metadata", "tracks", "map_features")
# Limits checked before allocating (fields of ScenarioNetConfig; the nuScenes-mini scenes hold at most 201 steps, 226
# tracks and 1.2 M map pixels).
MAX_STEPS = 100_000
MAX_MAP_PIXELS = 25_000_000  # 1,667 m x 1,667 m at 3 px/m; 75 MB of layers


class ScenarioNetConfig(SourceConfig):
    """Options of the ``scenarionet`` source (on top of the common :class:`SourceConfig`)."""

    pixels_per_meter: float = Field(3.0, gt=0, description="Resolution of the rasterized map (pixels per metre).")
    margin_m: float = Field(20.0, ge=0, description="Map kept around the box of all valid agent positions (m).")
    lane_width_m: float = Field(
        4.0, gt=0, description="Width drawn as drivable around lane centerlines that carry no polygon (m)."
    )
    polyline_points: int = Field(20, ge=2, description="Points per vector-map polyline (L), by arc length.")
    polyline_max_length_m: float = Field(30.0, gt=0, description="Longer map polylines are split into pieces (m).")
    max_polylines: int = Field(1024, ge=1, description="Vector-map pieces kept (P), nearest the SDC first.")
    listing_read_limit: int = Field(
        2000, ge=0, description="Splits with more scenario files than this are listed by file name only, without "
        "reading any file (a folder of 100,000 scenarios is not loaded to list it); scenes too short for a window "
        "are then skipped, and counted, when they are streamed (iter_batches).")
    rasterize_map: bool = Field(True, description="Rasterize the map of each scene; False reads tracks only "
                                "(map=None), for statistics over many scenes.")
    max_steps: int = Field(MAX_STEPS, ge=1, description="Logged steps (the pickle's `length`) one scene may hold, "
                           "checked before any per-step array is allocated (100,000 steps = 2.8 h at 0.1 s).")
    max_map_pixels: int = Field(MAX_MAP_PIXELS, ge=1, description="Pixels (H x W) of one scene's map raster, checked "
                                "before it is allocated; the raster spans the agents' positions plus `margin_m`.")


def read_scenario(path: str) -> dict[str, Any]:
    """Read one ScenarioNet pickle through the restricted unpickler and check its top-level structure."""
    data = restricted_load(path)
    if not isinstance(data, Mapping):
        raise DataFormatError(f"{path}: a ScenarioNet scenario must be a dict, got {type(data).__name__}.")
    missing = [key for key in REQUIRED_KEYS if key not in data]
    if missing:
        raise DataFormatError(f"{path}: not a ScenarioNet scenario; missing key(s) {missing}.")
    if not isinstance(data["tracks"], Mapping) or not isinstance(data["metadata"], Mapping):
        raise DataFormatError(f"{path}: 'tracks' and 'metadata' must be dicts.")
    try:
        length = int(data["length"])
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{path}: 'length' must be a number of steps, got {data['length']!r}.") from exc
    if length < 1:
        raise DataFormatError(f"{path}: 'length' must be at least 1 step, got {length}.")
    return {**data, "length": length}


def _sample_rate(data: Mapping[str, Any], path: str) -> float:
    """Seconds between logged steps: ``metadata.sample_rate``, else the spacing of ``metadata.ts``."""
    meta = data["metadata"]
    rate = meta.get("sample_rate")
    if rate is None and meta.get("ts") is not None and len(meta["ts"]) > 1:
        rate = float(np.median(np.diff(np.asarray(meta["ts"], dtype=np.float64))))
    try:
        rate = float(rate)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        rate = float("nan")
    if not (rate > 0 and math.isfinite(rate)):
        raise DataFormatError(
            f"{path}: metadata has no usable 'sample_rate' (or 'ts'); got {meta.get('sample_rate')!r}."
        )
    return rate


def _state(track: Mapping[str, Any], key: str, num_steps: int, width: int, path: str, agent: str) -> np.ndarray:
    """``track['state'][key]`` as float64 ``(T, width)``."""
    try:
        value = np.asarray(track["state"][key], dtype=np.float64).reshape(num_steps, -1)
    except (KeyError, TypeError, ValueError) as exc:
        raise DataFormatError(f"{path}: track {agent!r} has no usable state[{key!r}] of {num_steps} steps ({exc}).") \
            from exc
    if value.shape[1] < width:
        raise DataFormatError(f"{path}: track {agent!r} state[{key!r}] has {value.shape[1]} columns, needs {width}.")
    return value[:, :width]


def _wrap_float32(angle: np.ndarray) -> np.ndarray:
    """Angles (rad, any shape) wrapped to [-pi, pi) *after* rounding to float32 (float32(pi) > pi)."""
    wrapped = ((np.asarray(angle, np.float64) + np.pi) % (2 * np.pi) - np.pi).astype(np.float32)
    low = np.nextafter(np.float32(-np.pi), np.float32(0))  # the float32 nearest -pi that is >= -pi
    out_of_range = (wrapped.astype(np.float64) >= np.pi) | (wrapped.astype(np.float64) < -np.pi)
    return np.where(out_of_range, low, wrapped)


class ScenarioNetSource(ScenarioSource):
    """ScenarioNet scenarios: every track (the SDC first), strided to ``config.dt``, in a scene frame whose
    origin is the corner of the rasterized map; see :mod:`trafficrlhf_scenarionet.map_raster` for the map."""

    name = "scenarionet"
    Config = ScenarioNetConfig
    config: ScenarioNetConfig

    def __init__(self, config: SourceConfig | None = None, **options: object) -> None:
        """Options as for :class:`ScenarioNetConfig`; a plain ``SourceConfig`` is upgraded with its defaults."""
        super().__init__(config, **options)
        if not isinstance(self.config, ScenarioNetConfig):
            self.config = ScenarioNetConfig(**self.config.model_dump())

    @property
    def root(self) -> str:
        """``config.root`` or ``<data root>/nuscenes_mini_scenarionet``."""
        return self.config.root or os.path.join(default_data_root(), "nuscenes_mini_scenarionet")

    def _check_root(self) -> None:
        if not os.path.isdir(self.root):
            raise DataNotFoundError(
                f"scenarionet data not found: looked for the directory {self.root!r}. Point to a folder of ScenarioNet"
                " scenario pickles (or of split sub-folders holding them) with --root DIR (or root=...), or set"
                " TRAFFICRLHF_DATA to the folder that contains nuscenes_mini_scenarionet/."
            )

    def _split_dir(self, split: str) -> str:
        return self.root if split == ROOT_SPLIT else os.path.join(self.root, split)

    @staticmethod
    def _pickles(folder: str) -> list[str]:
        """Scenario pickle file names of ``folder``, sorted (ScenarioNet's summary/mapping files excluded)."""
        return sorted(n for n in os.listdir(folder) if n.endswith(".pkl") and n not in SUMMARY_FILES
                      and os.path.isfile(os.path.join(folder, n)))

    def splits(self) -> list[str]:
        """``"all"`` if pickles lie directly in the root, plus every sub-folder that holds pickles."""
        self._check_root()
        found = [ROOT_SPLIT] if self._pickles(self.root) else []
        for name in sorted(os.listdir(self.root)):
            folder = os.path.join(self.root, name)
            if name != ROOT_SPLIT and os.path.isdir(folder) and self._pickles(folder):
                found.append(name)
        return found

    @functools.lru_cache(maxsize=8)  # noqa: B019 - one source object lists each split once
    def all_scene_ids(self, split: str) -> list[str]:
        """File stems of every scenario of ``split``, sorted, long enough or not; reads no file."""
        self.check_split(split)
        return [name[:-4] for name in self._pickles(self._split_dir(split))]

    def is_lazy(self, split: str) -> bool:
        """Whether ``split`` has more files than ``listing_read_limit`` (listed by name, checked when read)."""
        return len(self.all_scene_ids(split)) > self.config.listing_read_limit

    def iter_batches(self, split: str, batch_size: int = 64, scene_ids: Sequence[str] | None = None,
                     skipped: list[str] | None = None) -> Iterator[ScenarioTensor]:
        """Stream ``scene_ids`` (default: every file of ``split``) as batches of up to ``batch_size`` scenes, one
        shard in memory at a time. Scenes too short for ``history_s + min_future_s`` are skipped and appended to
        ``skipped`` (when given), never dropped silently."""
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size!r}.")
        needed = self.config.history_s + self.config.min_future_s
        shard: list[ScenarioTensor] = []
        for scene_id in scene_ids if scene_ids is not None else self.all_scene_ids(split):
            scene = self.load_scene(split, scene_id)
            if (scene.num_steps - 1) * scene.dt < needed - 1e-6:
                if skipped is not None:
                    skipped.append(scene_id)
                continue
            shard.append(scene)
            if len(shard) == batch_size:
                yield ScenarioTensor.concat(shard)
                shard = []
        if shard:
            yield ScenarioTensor.concat(shard)

    @functools.lru_cache(maxsize=8)  # noqa: B019 - one source object reads each split once
    def _durations(self, split: str) -> dict[str, float]:
        """Scene id -> logged duration (s) at ``config.dt`` for every pickle of ``split``."""
        self.check_split(split)
        folder = self._split_dir(split)
        out = {}
        for name in self._pickles(folder):
            path = os.path.join(folder, name)
            data = read_scenario(path)
            stride = self._stride(_sample_rate(data, path), path)
            out[name[:-4]] = ((int(data["length"]) - 1) // stride) * self.config.dt
        return out

    def scene_ids(self, split: str) -> list[str]:
        """File stems of the scenes of ``split`` lasting at least ``history_s + min_future_s``, sorted. A split
        with more files than ``listing_read_limit`` is listed by name without reading (see :meth:`iter_batches`
        for streaming it, which skips and counts the short scenes)."""
        if self.is_lazy(split):
            return self.all_scene_ids(split)
        needed = self.config.history_s + self.config.min_future_s
        return [s for s, d in self._durations(split).items() if d >= needed - 1e-6]

    def _stride(self, sample_rate: float, path: str) -> int:
        stride = round(self.config.dt / sample_rate)
        if stride < 1 or abs(stride * sample_rate - self.config.dt) > 1e-6:
            raise DataFormatError(
                f"{path}: dt={self.config.dt} s must be a positive integer multiple of the data's sample rate"
                f" {sample_rate} s; choose dt={sample_rate} or a multiple of it."
            )
        return stride

    def load_scene(self, split: str, scene_id: str) -> ScenarioTensor:
        """Scene ``scene_id`` (file stem) of ``split`` as a ScenarioTensor with B = 1."""
        self._check_root()
        path = os.path.join(self._split_dir(split), f"{scene_id}.pkl")
        if not os.path.isfile(path):
            self.check_split(split)
            raise DataNotFoundError(f"scene {scene_id!r} not found in split {split!r}: no file {path!r}.")
        data = read_scenario(path)
        cfg = self.config
        num_steps = int(data["length"])
        if num_steps > cfg.max_steps:
            raise InputLimitError(f"{path}: 'length' is {num_steps:,} logged steps, more than max_steps="
                                  f"{cfg.max_steps:,}; fix 'length' (it must equal the length of every track's state "
                                  f"arrays), or raise the limit with {OPTIONS_HINT.format(option='max_steps')}.")
        check_agent_count(len(data["tracks"]), cfg.max_agents, path)
        stride = self._stride(_sample_rate(data, path), path)
        current = cfg.history_steps
        t_total = (num_steps - 1) // stride + 1
        if cfg.max_future_s is not None:
            t_total = min(t_total, current + 1 + round(cfg.max_future_s / cfg.dt))
        if current >= t_total:
            raise DataFormatError(f"{path}: scene is shorter than the {cfg.history_s} s of history.")
        tracks = read_tracks(data, path, np.arange(t_total) * stride)

        points = tracks.xy[tracks.valid]
        ppm = cfg.pixels_per_meter
        if not cfg.rasterize_map:
            return self._tensor(tracks, points.min(0) - cfg.margin_m, None, scene_id, split, data)
        origin = points.min(0) - cfg.margin_m  # world position of pixel corner (0, 0) = scene frame origin
        span = np.maximum(np.ceil((points.max(0) + cfg.margin_m - origin) * ppm), 1)  # float: inf for far points
        _check_raster_size(tuple(float(v) for v in span), cfg, tracks, path)
        shape = tuple(int(v) for v in span)
        features = parse_map_features(data["map_features"], path)
        raster = rasterize(features, origin, shape, ppm, cfg.lane_width_m)  # type: ignore[arg-type]
        focus = tracks.xy[0, current] if tracks.valid[0, current] else points.mean(0)
        polylines, poly_types = vectorize(features, origin, np.array(shape) / ppm, focus - origin,
                                          cfg.polyline_points, cfg.polyline_max_length_m, cfg.max_polylines)
        poly_t = torch.from_numpy(polylines)[None]
        scene_map = MapRaster(
            raster=torch.from_numpy(raster)[None],
            world_to_pixel=torch.tensor([[[ppm, 0.0, 0.0], [0.0, ppm, 0.0], [0.0, 0.0, 1.0]]], dtype=torch.float32),
            layers=LAYERS,
            polylines=poly_t,
            polyline_valid=torch.ones(poly_t.shape[:3], dtype=torch.bool),
            polyline_type=torch.from_numpy(poly_types)[None],
        )

        scene = self._tensor(tracks, origin, scene_map, scene_id, split, data)
        check_on_map(scene, cfg.min_on_map_share, path, "the pickle's 'map_features' (they must share the tracks' "
                     "world frame and metres)")
        return scene

    def _tensor(self, tracks: Tracks, origin: np.ndarray, scene_map: MapRaster | None, scene_id: str, split: str,
                data: Mapping[str, Any]) -> ScenarioTensor:
        cfg = self.config
        current = cfg.history_steps
        states = np.zeros(tracks.xy.shape[:2] + (4,), np.float32)
        states[..., :2] = tracks.xy - origin
        states[..., 2] = tracks.speed
        states[..., 3] = tracks.yaw
        valid = torch.from_numpy(tracks.valid)[None]
        agent_type = torch.from_numpy(tracks.agent_type)[None]
        return ScenarioTensor(
            states=torch.from_numpy(states)[None] * valid[..., None],
            valid=valid,
            extent=torch.from_numpy(tracks.extent)[None],
            agent_type=agent_type,
            controlled=valid[:, :, current] & (agent_type == AgentType.VEHICLE),
            dt=cfg.dt,
            current_index=current,
            map=scene_map,
            origin=torch.from_numpy(origin.astype(np.float64))[None],
            scene_ids=(scene_id,),
            agent_ids=(tracks.ids,),
            source=self.name,
            extras={"split": split, "dataset": str(data["metadata"].get("dataset", ""))},
        )


def _check_raster_size(shape: tuple[float, ...], cfg: ScenarioNetConfig, tracks: Tracks, path: str) -> None:
    """Refuse a map raster of more than ``cfg.max_map_pixels`` pixels before it is allocated, naming the agent
    position farthest from the others (a wrong coordinate makes the raster span it; ``shape`` is in float, so a
    span too large for an integer is refused rather than overflowing)."""
    pixels = math.prod(shape)
    if pixels <= cfg.max_map_pixels:
        return
    xy = np.where(tracks.valid[..., None], tracks.xy, np.nan)
    centre = np.nanmedian(xy.reshape(-1, 2), axis=0)
    distance = np.where(tracks.valid, np.linalg.norm(np.nan_to_num(xy - centre), axis=-1), -1.0)
    agent, step = np.unravel_index(int(np.argmax(distance)), distance.shape)
    size_m = np.array(shape) / cfg.pixels_per_meter
    raise InputLimitError(
        f"{path}: the agents' positions span {size_m[0]:,.0f} m x {size_m[1]:,.0f} m, a map raster of {pixels:,} "
        f"pixels at {cfg.pixels_per_meter} px/m, more than max_map_pixels={cfg.max_map_pixels:,}; the farthest "
        f"position is track {tracks.ids[agent]!r} at step {step} ({tracks.xy[agent, step, 0]:,.1f}, "
        f"{tracks.xy[agent, step, 1]:,.1f}), {distance[agent, step]:,.0f} m from the others' median. Fix that "
        f"coordinate, lower pixels_per_meter, or raise the limit with {OPTIONS_HINT.format(option='max_map_pixels')}."
    )


@dataclass(frozen=True)
class Tracks:
    """Agents of one scene at the selected steps (A agents, T steps), world frame.

    ``xy`` float64 ``(A, T, 2)`` m; ``speed`` ``(A, T)`` m/s signed along the heading; ``yaw`` float32 ``(A, T)``
    rad in [-pi, pi); ``valid`` bool ``(A, T)``; ``extent`` float32 ``(A, 2)`` length, width (m);
    ``agent_type`` int64 ``(A,)``; ``ids`` the object ids.
    """

    xy: np.ndarray
    speed: np.ndarray
    yaw: np.ndarray
    valid: np.ndarray
    extent: np.ndarray
    agent_type: np.ndarray
    ids: tuple[str, ...]


def read_tracks(data: Mapping[str, Any], path: str, steps: np.ndarray) -> Tracks:
    """Every track of ``data`` valid at some of ``steps`` (indices into the logged steps), the SDC first.

    Speed is the norm of the logged velocity, negative when it points against the heading. The extent is the
    box at the first valid step; a vehicle box wider than long is swapped (ScenarioNet's nuScenes export stores
    the ego's box as width, length). Steps with non-finite position or heading count as invalid.
    """
    num_steps = int(data["length"])
    sdc = str(data["metadata"].get("sdc_id", ""))
    keys = sorted(data["tracks"], key=lambda k: str(k) != sdc)  # SDC first, then file order (stable sort)
    ids: list[str] = []
    xy, speed, yaw, valid, extent, types = [], [], [], [], [], []
    seen: dict[int, str] = {}
    for key in keys:
        agent, track = str(key), data["tracks"][key]
        if id(track) in seen:  # one object under two keys: a shared reference, never written by a converter
            raise DataFormatError(f"{path}: tracks {seen[id(track)]!r} and {agent!r} are the same object (a shared "
                                  "reference in the pickle); a scenario holds one track object per agent. Re-export "
                                  "the scenario, or drop the duplicated track ids.")
        seen[id(track)] = agent
        if not isinstance(track, Mapping) or not isinstance(track.get("state"), Mapping):
            raise DataFormatError(f"{path}: track {agent!r} is not a dict with a 'state' dict.")
        pos = _state(track, "position", num_steps, 2, path, agent)[steps]
        vel = _state(track, "velocity", num_steps, 2, path, agent)[steps]
        heading = _state(track, "heading", num_steps, 1, path, agent)[steps, 0]
        ok = (_state(track, "valid", num_steps, 1, path, agent)[steps, 0] > 0.5)
        ok &= np.isfinite(pos).all(1) & np.isfinite(heading)
        if not ok.any():
            continue  # never present in this window
        first = steps[int(np.argmax(ok))]
        size = [float(_state(track, key_, num_steps, 1, path, agent)[first, 0]) for key_ in ("length", "width")]
        kind = AgentType.from_name(str(track.get("type", "")))
        if kind == AgentType.VEHICLE and size[1] > size[0]:
            size = size[::-1]
        vel = np.where(np.isfinite(vel), vel, 0.0)
        backwards = vel[:, 0] * np.cos(heading) + vel[:, 1] * np.sin(heading) < 0
        ids.append(agent)
        xy.append(np.where(ok[:, None], pos, 0.0))
        speed.append(np.where(ok, np.linalg.norm(vel, axis=1) * np.where(backwards, -1.0, 1.0), 0.0))
        yaw.append(np.where(ok, _wrap_float32(np.where(ok, heading, 0.0)), np.float32(0)))
        valid.append(ok)
        extent.append(size)
        types.append(int(kind))
    if not ids:
        raise DataFormatError(f"{path}: no track is valid in the scene window; nothing to load.")
    return Tracks(np.stack(xy), np.stack(speed), np.stack(yaw).astype(np.float32), np.stack(valid),
                  np.array(extent, np.float32), np.array(types, np.int64), tuple(ids))
