"""Reader for the AgentFormer-preprocessed nuScenes prediction scenes."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, FileEncodingError, MapMismatchError
from trafficrlhf_sdk.scenario import AgentType, MapRaster, ScenarioSource, ScenarioTensor, default_data_root
from trafficrlhf_sdk.scenario.checks import check_agent_count, check_on_map

__all__ = ["KEYFRAME_DT", "LabelTable", "NuScenesPredSource", "parse_label_file"]

KEYFRAME_DT = 0.5  # s between labelled keyframes (2 Hz)
NUM_COLUMNS = 18
# The PNGs were written by OpenCV from a (drivable, road divider, lane divider) array, i.e. stored as B, G, R;
# read back as RGB the drivable layer is channel 2.
PNG_CHANNEL_OF_LAYER = {"drivable": 2, "road_divider": 1, "lane_divider": 0}
# Bounds that keep a bad file from looking valid or from taking the machine's memory (the bundled data stays far
# inside each: at most 41 keyframes, 42 tracks, 27 m/s between keyframes, 380 m from the map corner, 1.6 M pixels).
MAX_FRAME = 10_000  # keyframe index (83 min at 2 Hz)
MAX_GRID = 500_000  # tracks x keyframes of one scene
MAX_COORDINATE_M = 100_000.0  # |x|, |y| in the map frame
MAX_SPEED_MPS = 70.0  # between consecutive keyframes of a track (252 km/h)
MAX_BOX_M = 30.0  # box length and width
MAX_MAP_PIXELS = 25_000_000  # map PNG width x height
MAP_MARGIN_M = 1_000.0  # how far outside its map raster an agent may be


@dataclass(frozen=True)
class LabelTable:
    """Parsed rows of one label file: arrays of length N (rows)."""

    frame: np.ndarray  # int keyframe index
    track: np.ndarray  # int track id
    category: list[str]
    length: np.ndarray
    width: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    line: np.ndarray | None = None  # 1-based line number of each row, for error messages


def _check_rows(path: str, table: LabelTable) -> None:
    """Refuse duplicate (frame, track) rows, impossible speeds and scenes too large to hold, naming the lines."""
    line = table.line if table.line is not None else np.arange(1, len(table.frame) + 1)
    order = np.lexsort((table.frame, table.track))
    track, frame = table.track[order], table.frame[order]
    same = (track[1:] == track[:-1]) & (frame[1:] == frame[:-1])
    if same.any():
        k = int(np.argmax(same))
        raise DataFormatError(f"{path}:{line[order[k + 1]]}: track {track[k]} has a second row for frame {frame[k]} "
                              f"(the first is line {line[order[k]]}); keep one row per (frame, track).")
    num_tracks, num_frames = len(np.unique(table.track)), int(table.frame.max()) + 1
    if num_tracks * num_frames > MAX_GRID:
        raise DataFormatError(f"{path}: {num_tracks} tracks over {num_frames} keyframes ({num_tracks * num_frames:,} "
                              f"cells, more than {MAX_GRID:,}); the frame numbers or track ids are wrong.")
    step = (track[1:] == track[:-1]) & (frame[1:] == frame[:-1] + 1)
    x, y = table.x[order], table.y[order]
    speed = np.where(step, np.hypot(x[1:] - x[:-1], y[1:] - y[:-1]) / KEYFRAME_DT, 0.0)
    if (speed > MAX_SPEED_MPS).any():
        k = int(np.argmax(speed))
        raise DataFormatError(f"{path}:{line[order[k + 1]]}: track {track[k]} moves {speed[k]:.1f} m/s since line "
                              f"{line[order[k]]} (more than {MAX_SPEED_MPS:.0f} m/s); fix the coordinates.")


def parse_label_file(path: str) -> LabelTable:
    """Parse an 18-column label file; a malformed row raises ``DataFormatError`` naming file and line.

    Besides the format, a row is refused for a frame that is not an integer in ``0 .. MAX_FRAME``, a fractional
    track id, a box size of 0 or less (or above ``MAX_BOX_M``), an unknown agent class, a position beyond
    ``MAX_COORDINATE_M``, a second row of the same (frame, track), or a speed above ``MAX_SPEED_MPS`` between
    consecutive keyframes; a file whose tracks x keyframes exceed ``MAX_GRID`` is refused too.
    """
    frames, tracks, cats, lengths, widths, xs, ys, yaws, lines = [], [], [], [], [], [], [], [], []
    with open(path, "rb") as handle:
        for lineno, raw in enumerate(handle, start=1):
            try:
                line = raw.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise FileEncodingError(
                    f"{path}:{lineno}: not UTF-8 text (byte {raw[exc.start]:#04x} at column {exc.start + 1}); a label "
                    "file is plain text with 18 space-separated columns per row. Re-export it as UTF-8 (or ASCII) "
                    "text, or check that the path names a label file."
                ) from exc
            parts = line.split()
            if not parts:
                continue
            if len(parts) != NUM_COLUMNS:
                raise DataFormatError(
                    f"{path}:{lineno}: expected {NUM_COLUMNS} space-separated columns, found {len(parts)}: "
                    f"{line.strip()!r}"
                )
            try:
                values = [float(parts[i]) for i in (0, 1, 10, 12, 13, 15, 16)]
            except ValueError as exc:
                raise DataFormatError(f"{path}:{lineno}: non-numeric value ({exc}) in {line.strip()!r}") from exc
            if not all(math.isfinite(v) for v in values):
                raise DataFormatError(f"{path}:{lineno}: NaN or inf in {line.strip()!r}")
            frame, track, width, length, x, y, yaw = values
            if frame < 0 or frame != int(frame) or frame > MAX_FRAME:
                raise DataFormatError(f"{path}:{lineno}: frame must be an integer from 0 to {MAX_FRAME:,}, got "
                                      f"{parts[0]!r}")
            if track != int(track) or abs(track) > 2**53:
                raise DataFormatError(f"{path}:{lineno}: track id must be an integer, got {parts[1]!r}")
            if not (0 < width <= MAX_BOX_M and 0 < length <= MAX_BOX_M):
                raise DataFormatError(f"{path}:{lineno}: box width {parts[10]} and length {parts[12]} must be above 0 "
                                      f"and at most {MAX_BOX_M:.0f} m")
            if abs(x) > MAX_COORDINATE_M or abs(y) > MAX_COORDINATE_M:
                raise DataFormatError(f"{path}:{lineno}: position ({parts[13]}, {parts[15]}) is more than "
                                      f"{MAX_COORDINATE_M:,.0f} m from the map origin; fix the coordinates")
            if AgentType.from_name(parts[2]) == AgentType.OTHER:
                raise DataFormatError(f"{path}:{lineno}: unknown agent class {parts[2]!r}; use a nuScenes class such "
                                      "as Car, Truck, Bus, Pedestrian or Bicycle")
            lines.append(lineno)
            frames.append(int(frame))
            tracks.append(int(track))
            cats.append(parts[2])
            widths.append(width)
            lengths.append(length)
            xs.append(x)
            ys.append(y)
            yaws.append(yaw)
    if not frames:
        raise DataFormatError(f"{path}: the label file has no rows.")
    table = LabelTable(np.array(frames), np.array(tracks), cats, np.array(lengths), np.array(widths),
                       np.array(xs), np.array(ys), np.array(yaws), np.array(lines))
    _check_rows(path, table)
    return table


def _keyframe_speed(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, present: np.ndarray) -> np.ndarray:
    """Signed speed along the heading at keyframes ``(A, F)`` from the past only.

    At a keyframe whose track was also present at the previous keyframe, the speed is the displacement since that
    keyframe along the current heading over 0.5 s (a backward difference). At a track's first keyframe (or the
    first after a gap) there is no past observation and the speed is 0. A state never reads a later keyframe, so
    the state at "now" carries no information about the future (a central difference would carry 0.25 s of it).
    """
    prv = np.zeros_like(present)
    prv[:, 1:] = present[:, :-1] & present[:, 1:]
    bwd = np.zeros_like(x)
    bwd[:, 1:] = ((x[:, 1:] - x[:, :-1]) * np.cos(yaw[:, 1:]) + (y[:, 1:] - y[:, :-1]) * np.sin(yaw[:, 1:])) \
        / KEYFRAME_DT
    return np.where(prv, bwd, 0.0)


class NuScenesPredSource(ScenarioSource):
    """nuScenes prediction scenes, resampled from 2 Hz keyframes to ``config.dt`` (positions linear, yaw
    unwrapped, speed from the motion since the previous keyframe), in a scene frame whose origin is the map
    raster's corner.

    Every state up to a keyframe reads that keyframe and earlier ones only: "now" (``history_s``) must fall on a
    keyframe, and the speed at a keyframe is a backward difference (0 at a track's first keyframe).
    """

    name = "nuscenes_pred"

    @property
    def root(self) -> str:
        """``config.root`` or ``<data root>/nuscenes_pred``."""
        return self.config.root or os.path.join(default_data_root(), "nuscenes_pred")

    def _check_root(self) -> None:
        if not os.path.isdir(os.path.join(self.root, "label")):
            raise DataNotFoundError(
                f"nuscenes_pred data not found: looked for {os.path.join(self.root, 'label')!r}. Point to the "
                "directory holding label/ and maps/ with --root DIR (or root=...), or set TRAFFICRLHF_DATA to the "
                "folder that contains nuscenes_pred/."
            )

    def splits(self) -> list[str]:
        """Sub-folders of ``label/`` (train, val, test where present)."""
        self._check_root()
        label = os.path.join(self.root, "label")
        return sorted(d for d in os.listdir(label) if os.path.isdir(os.path.join(label, d)))

    def _num_keyframes(self, split: str) -> dict[str, int]:
        """Keyframe count of every scene of ``split`` (read once per source object)."""
        cache: dict[str, dict[str, int]] = self.__dict__.setdefault("_keyframe_cache", {})
        if split not in cache:
            self.check_split(split)
            folder = os.path.join(self.root, "label", split)
            cache[split] = {
                name[:-4]: int(parse_label_file(os.path.join(folder, name)).frame.max()) + 1
                for name in sorted(os.listdir(folder))
                if name.endswith(".txt")
            }
        return cache[split]

    def all_scene_ids(self, split: str) -> list[str]:
        """Every scene of ``split``, long enough or not, sorted by name."""
        return list(self._num_keyframes(split))

    def scene_ids(self, split: str) -> list[str]:
        """Scenes of ``split`` lasting at least ``history_s + min_future_s``, sorted by name."""
        needed = self.config.history_s + self.config.min_future_s
        return [s for s, n in self._num_keyframes(split).items() if (n - 1) * KEYFRAME_DT >= needed - 1e-6]

    def load_scene(self, split: str, scene_id: str) -> ScenarioTensor:
        """Scene ``scene_id`` of ``split`` as a ScenarioTensor with B = 1."""
        self.check_split(split)
        label_path = os.path.join(self.root, "label", split, f"{scene_id}.txt")
        if not os.path.isfile(label_path):
            raise DataNotFoundError(f"scene {scene_id!r} not found in split {split!r}: no file {label_path!r}.")
        table = parse_label_file(label_path)
        check_agent_count(len(np.unique(table.track)), self.config.max_agents, label_path)
        scene_map, origin = self._load_map(scene_id)

        _check_on_map(label_path, table, scene_map, origin, self.config.min_on_map_share > 0)
        tracks = np.unique(table.track)
        num_frames = int(table.frame.max()) + 1
        a_idx = np.searchsorted(tracks, table.track)
        present = np.zeros((len(tracks), num_frames), bool)
        present[a_idx, table.frame] = True
        grid = lambda values: np.zeros((len(tracks), num_frames)) if values is None else _scatter(  # noqa: E731
            values, a_idx, table.frame, (len(tracks), num_frames))
        kx, ky = grid(table.x - origin[0]), grid(table.y - origin[1])
        kyaw = np.unwrap(grid(table.yaw), axis=1)  # unwrap along each track; gaps hold 0 but stay invalid
        kspeed = _keyframe_speed(kx, ky, kyaw, present)

        factor = round(KEYFRAME_DT / self.config.dt)
        if abs(factor * self.config.dt - KEYFRAME_DT) > 1e-9:
            raise DataFormatError(f"dt={self.config.dt} must divide the keyframe interval {KEYFRAME_DT} s.")
        if self.config.history_steps % factor:
            raise DataFormatError(
                f"history_s={self.config.history_s} puts 'now' between two {KEYFRAME_DT} s keyframes, so the state "
                f"at 'now' would be interpolated from the next (future) keyframe; use a multiple of {KEYFRAME_DT} s."
            )
        states, valid = _upsample(np.stack([kx, ky, kspeed, kyaw], -1), present, factor)
        states[..., 3] = (states[..., 3] + np.pi) % (2 * np.pi) - np.pi

        first = {int(t): i for i, t in reversed(list(enumerate(a_idx)))}
        extent = np.array([[table.length[first[a]], table.width[first[a]]] for a in range(len(tracks))])
        types = np.array([int(AgentType.from_name(table.category[first[a]])) for a in range(len(tracks))])
        meta = os.path.join(self.root, "maps", f"meta_{scene_id}.txt")
        # the whole logged track against the map, whatever window of it is loaded (a short window holds few
        # positions, and its share says little about the map)
        whole = torch.from_numpy(valid)[None]
        check_on_map(ScenarioTensor(states=torch.from_numpy(states).float()[None] * whole[..., None], valid=whole,
                                    extent=torch.from_numpy(extent).float()[None],
                                    agent_type=torch.from_numpy(types).long()[None],
                                    controlled=torch.zeros(whole.shape[:2], dtype=torch.bool), dt=self.config.dt,
                                    map=scene_map),
                     self.config.min_on_map_share, label_path,
                     f"the origin 'x_min y_min' (or the scale) in {meta}, or the map image beside it")

        t_total = states.shape[1]
        if self.config.max_future_s is not None:
            t_total = min(t_total, self.config.history_steps + 1 + round(self.config.max_future_s / self.config.dt))
        states, valid = states[:, :t_total], valid[:, :t_total]
        current = self.config.history_steps
        if current >= t_total:
            raise DataFormatError(f"scene {scene_id!r} is shorter than the {self.config.history_s} s of history.")

        valid_t = torch.from_numpy(valid)[None]
        scene = ScenarioTensor(
            states=torch.from_numpy(states).float()[None] * valid_t[..., None],
            valid=valid_t,
            extent=torch.from_numpy(extent).float()[None],
            agent_type=torch.from_numpy(types).long()[None],
            controlled=(valid_t[:, :, current] & (torch.from_numpy(types)[None] == AgentType.VEHICLE)),
            dt=self.config.dt,
            current_index=current,
            map=scene_map,
            origin=torch.tensor([origin], dtype=torch.float64),
            scene_ids=(scene_id,),
            agent_ids=(tuple(str(t) for t in tracks),),
            source=self.name,
            extras={"split": split, "native_dt": KEYFRAME_DT},
        )
        return scene

    def _load_map(self, scene_id: str) -> tuple[MapRaster, tuple[float, float]]:
        png = os.path.join(self.root, "maps", f"{scene_id}.png")
        meta = os.path.join(self.root, "maps", f"meta_{scene_id}.txt")
        for path in (png, meta):
            if not os.path.isfile(path):
                raise DataNotFoundError(f"map file missing for {scene_id!r}: {path!r}.")
        try:
            with open(meta, encoding="utf-8") as handle:
                x_min, y_min, scale = (float(v) for v in handle.read(1024).split())
        except (ValueError, UnicodeDecodeError) as exc:
            raise DataFormatError(f"{meta}: expected three numbers 'x_min y_min scale' ({exc}).") from exc
        if not all(math.isfinite(v) for v in (x_min, y_min, scale)) or not 0 < scale <= 100:
            raise DataFormatError(f"{meta}: 'x_min y_min scale' = {x_min} {y_min} {scale}; the origin must be finite "
                                  "and the scale (pixels per metre) above 0 and at most 100.")
        try:
            with Image.open(png) as handle:
                width, height = handle.size
                if width * height > MAX_MAP_PIXELS:
                    raise DataFormatError(f"{png}: the map image declares {width} x {height} pixels, more than "
                                          f"{MAX_MAP_PIXELS:,}; it is not a map of one scene.")
                image = np.asarray(handle.convert("RGB"))
        except (OSError, Image.DecompressionBombError, ValueError) as exc:
            raise DataFormatError(f"{png}: cannot read the map image ({exc}).") from exc
        layers = ("drivable", "road_divider", "lane_divider")
        raster = np.stack([image[..., PNG_CHANNEL_OF_LAYER[name]] > 0 for name in layers])
        if not raster[0].any():
            raise DataFormatError(f"{png}: the drivable layer is empty (no pixel set in channel "
                                  f"{PNG_CHANNEL_OF_LAYER['drivable']}); every agent would count as off-road and "
                                  "none would be driven. Restore the map image.")
        # scene frame origin = raster corner, so pixel (i, j) = (x * scale, y * scale); x runs along rows.
        world_to_pixel = torch.tensor([[scale, 0.0, 0.0], [0.0, scale, 0.0], [0.0, 0.0, 1.0]])
        return (
            MapRaster(raster=torch.from_numpy(raster.astype(np.uint8))[None], world_to_pixel=world_to_pixel[None],
                      layers=layers),
            (x_min, y_min),
        )


def _check_on_map(label_path: str, table: LabelTable, scene_map: MapRaster, origin: tuple[float, float],
                  need_road: bool = True) -> None:
    """Refuse a scene whose agents lie far outside its map raster, or (``need_road``) whose vehicles are never on
    its drivable layer: the map's origin or scale (``maps/meta_<scene>.txt``) does not belong to the labels."""
    line = table.line if table.line is not None else np.arange(1, len(table.frame) + 1)
    extent = int(scene_map.sizes[0].max()) / float(scene_map.world_to_pixel[0, 0, 0])
    x, y = table.x - origin[0], table.y - origin[1]
    outside = (np.minimum(x, y) < -MAP_MARGIN_M) | (np.maximum(x, y) > extent + MAP_MARGIN_M)
    if outside.any():
        k = int(np.argmax(outside))
        raise DataFormatError(f"{label_path}:{line[k]}: position ({table.x[k]}, {table.y[k]}) lies more than "
                              f"{MAP_MARGIN_M:.0f} m outside the map raster (origin {origin}, {extent:.0f} m across); "
                              "the coordinates or the map's meta file are wrong.")
    vehicle = np.array([AgentType.from_name(c) == AgentType.VEHICLE for c in table.category])
    if need_road and vehicle.any():
        xy = torch.from_numpy(np.stack([x[vehicle], y[vehicle]], -1))[None].double()
        if not bool(scene_map.lookup(xy).any()):
            raise MapMismatchError(f"{label_path}: none of the scene's {int(vehicle.sum())} vehicle rows lies on the "
                                   "drivable layer of its map, so no agent would be driven; the map's origin or scale "
                                   "(maps/meta_<scene>.txt) does not belong to these labels. To load it as it is, set "
                                   "min_on_map_share=0.")


def _scatter(values: np.ndarray, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    out = np.zeros(shape)
    out[rows, cols] = values
    return out


def _upsample(key_states: np.ndarray, present: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation between consecutive present keyframes: ``(A, F, 4)`` -> ``(A, (F-1)*factor+1, 4)``."""
    num_agents, num_frames, _ = key_states.shape
    t_total = (num_frames - 1) * factor + 1
    states = np.zeros((num_agents, t_total, 4))
    valid = np.zeros((num_agents, t_total), bool)
    states[:, ::factor] = key_states
    valid[:, ::factor] = present
    both = present[:, :-1] & present[:, 1:]  # (A, F-1)
    for k in range(1, factor):
        w = k / factor
        interp = (1 - w) * key_states[:, :-1] + w * key_states[:, 1:]
        states[:, k::factor] = np.where(both[..., None], interp, 0.0)
        valid[:, k::factor] = both
    return states, valid
