"""Rasterize and vectorize a ScenarioNet vector map in a scene frame.

ScenarioNet ``map_features`` are ``{id: {"type": ..., "polyline": (N, 2|3), "polygon": (M, 2), ...}}`` in world
metres. Only the first two polyline columns are used (in the nuScenes export the third column of lane
centerlines is the lane heading, not a height). Each feature gets a *role*, which says where it is drawn:

- ``lane``: ``LANE_*`` except ``LANE_BIKE_LANE``. Drivable: its ``polygon`` when present (nuScenes lanes),
  else its centerline drawn ``lane_width_m`` wide (nuScenes lane connectors, Waymo lanes). LANE_CENTER.
- ``road_edge``: ``ROAD_EDGE_*``, and ``ROAD_LINE_*`` features with an id ``boundary_<n>`` (ScenarioNet's
  nuScenes converter writes the outline of the mapped road surface that way). Closed
  ``boundary_*`` rings are filled into drivable with the even-odd rule (outer outlines fill, holes clear).
  ROAD_EDGE.
- ``road_divider``: other ``ROAD_LINE_*`` whose type says ``YELLOW`` (lines between opposite directions).
  Layer road_divider, 1 px wide. ROAD_LINE.
- ``lane_divider``: the remaining ``ROAD_LINE_*`` (white, unknown). Layer lane_divider, 1 px wide. ROAD_LINE.
- ``surface``: ``CROSSWALK``, ``SPEED_BUMP``, ``DRIVEWAY`` polygons, filled into drivable. CROSSWALK or OTHER.
- ``other``: anything else with a polyline (bike lanes, ...): vector map only, as OTHER. Features without a
  polyline or polygon (stop signs, ...) are skipped.

The layer semantics follow the ``nuscenes_pred`` rasters: drivable surface, yellow (direction-separating)
dividers, white lane dividers. Pixel convention is the SDK's: with the scene frame origin at the raster corner,
fractional pixel index ``(i, j) = (x * ppm, y * ppm)``; ``i`` indexes rows (H) and ``j`` columns (W).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Mapping
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.scenario import PolylineType

__all__ = ["LAYERS", "MapFeature", "parse_map_features", "rasterize", "vectorize"]

LAYERS: tuple[str, ...] = ("drivable", "road_divider", "lane_divider")
SURFACE_TYPES = {"CROSSWALK": PolylineType.CROSSWALK, "SPEED_BUMP": PolylineType.OTHER,
                 "DRIVEWAY": PolylineType.OTHER}


@dataclass(frozen=True)
class MapFeature:
    """One map feature in world metres: ``polyline`` ``(N, 2)`` float64, ``polygon`` ``(M, 2)`` or None."""

    feature_id: str
    role: str
    polyline_type: int
    polyline: np.ndarray
    polygon: np.ndarray | None


MAX_SEGMENT_M = 10_000.0  # between consecutive points of a map feature (densifying 1e9 m asks for 21 GiB)


def classify(feature_id: str, feature_type: str) -> tuple[str, int]:
    """(role, PolylineType code) of a ScenarioNet feature; see the module docstring for the table."""
    kind = feature_type.upper()
    if kind.startswith("LANE_"):
        return ("other", PolylineType.OTHER) if "BIKE" in kind else ("lane", PolylineType.LANE_CENTER)
    if kind.startswith("ROAD_EDGE") or (kind.startswith("ROAD_LINE") and feature_id.startswith("boundary")):
        return "road_edge", PolylineType.ROAD_EDGE
    if kind.startswith("ROAD_LINE"):
        return ("road_divider" if "YELLOW" in kind else "lane_divider"), PolylineType.ROAD_LINE
    if kind in SURFACE_TYPES:
        return "surface", SURFACE_TYPES[kind]
    return "other", PolylineType.OTHER


def _points(value: Any, what: str, source: str) -> np.ndarray | None:
    """``value`` as a finite float64 ``(N, 2)`` array (first two columns), or None when absent/empty."""
    if value is None:
        return None
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{source}: {what} is not a numeric array ({exc}).") from exc
    if array.size == 0:
        return None
    if array.ndim != 2 or array.shape[1] < 2:
        raise DataFormatError(f"{source}: {what} must have shape (N, 2) or (N, 3); got {array.shape}.")
    array = array[:, :2]
    array = array[np.isfinite(array).all(1)]
    return array if len(array) else None


def parse_map_features(features: Mapping[str, Any], source: str) -> list[MapFeature]:
    """Parse ScenarioNet ``map_features`` (``source`` names the file in errors); features without geometry
    (stop signs, ...) are skipped."""
    if not isinstance(features, Mapping):
        raise DataFormatError(f"{source}: 'map_features' must be a dict, got {type(features).__name__}.")
    parsed = []
    for feature_id, feature in features.items():
        if not isinstance(feature, Mapping) or "type" not in feature:
            raise DataFormatError(f"{source}: map feature {feature_id!r} is not a dict with a 'type'.")
        role, code = classify(str(feature_id), str(feature["type"]))
        polyline = _points(feature.get("polyline"), f"map feature {feature_id!r} polyline", source)
        polygon = _points(feature.get("polygon"), f"map feature {feature_id!r} polygon", source)
        if polygon is not None and len(polygon) < 3:
            polygon = None
        if polyline is None and polygon is not None:
            polyline = np.concatenate([polygon, polygon[:1]])  # outline of a polygon-only feature
        if polyline is None:
            continue
        longest = float(np.linalg.norm(np.diff(polyline, axis=0), axis=1).max()) if len(polyline) > 1 else 0.0
        if longest > MAX_SEGMENT_M:
            raise DataFormatError(f"{source}: map feature {feature_id!r} has a segment of {longest:,.0f} m (more than "
                                  f"{MAX_SEGMENT_M:,.0f} m between two points); a coordinate is wrong.")
        parsed.append(MapFeature(str(feature_id), role, int(code), polyline, polygon))
    return parsed


def _pil_xy(points: np.ndarray, origin: np.ndarray, ppm: float) -> list[tuple[float, float]]:
    """World ``(N, 2)`` m -> PIL ``(column, row)`` = ``(j, i)`` fractional pixel indices (PIL truncates them to
    the containing pixel, as ``MapRaster.lookup`` floors)."""
    scene = (points - origin) * ppm
    return [(float(j), float(i)) for i, j in scene]


def _overlaps(feature: MapFeature, low: np.ndarray, high: np.ndarray) -> bool:
    """Whether the bounding box of the feature's geometry (world m) meets the box ``[low, high]``."""
    points = feature.polyline if feature.polygon is None else np.concatenate([feature.polyline, feature.polygon])
    return bool((points.max(0) >= low).all() and (points.min(0) <= high).all())


def _is_closed_ring(points: np.ndarray) -> bool:
    return len(points) >= 4 and float(np.linalg.norm(points[0] - points[-1])) < 0.5


def rasterize(features: list[MapFeature], origin: np.ndarray, shape: tuple[int, int], pixels_per_meter: float,
              lane_width_m: float) -> np.ndarray:
    """Draw ``features`` into a uint8 ``(3, H, W)`` raster (layers :data:`LAYERS`, values 0/1).

    ``origin`` (2,) is the world position (m) of pixel corner (0, 0); ``shape`` is (H, W).
    """
    h, w = shape
    ppm = pixels_per_meter
    images = {name: Image.new("L", (w, h), 0) for name in LAYERS}  # PIL size is (width, height)
    draw = {name: ImageDraw.Draw(image) for name, image in images.items()}
    rings = np.zeros((h, w), bool)
    lane_px = max(1, round(lane_width_m * ppm))
    low, high = origin - lane_width_m, origin + np.array([h, w]) / ppm + lane_width_m
    for feature in features:
        if not _overlaps(feature, low, high):
            continue
        if feature.role == "lane":
            if feature.polygon is not None:
                draw["drivable"].polygon(_pil_xy(feature.polygon, origin, ppm), fill=1, outline=1)
            elif len(feature.polyline) >= 2:
                draw["drivable"].line(_pil_xy(feature.polyline, origin, ppm), fill=1, width=lane_px, joint="curve")
        elif feature.role == "surface" and feature.polygon is not None:
            draw["drivable"].polygon(_pil_xy(feature.polygon, origin, ppm), fill=1, outline=1)
        elif feature.role == "road_edge" and feature.feature_id.startswith("boundary") \
                and _is_closed_ring(feature.polyline):
            ring = Image.new("L", (w, h), 0)
            ImageDraw.Draw(ring).polygon(_pil_xy(feature.polyline, origin, ppm), fill=1)
            rings ^= np.asarray(ring, bool)  # even-odd: outer outlines fill, holes inside them clear
        elif feature.role in ("road_divider", "lane_divider") and len(feature.polyline) >= 2:
            draw[feature.role].line(_pil_xy(feature.polyline, origin, ppm), fill=1, width=1)
    raster = np.stack([np.asarray(images[name], np.uint8) for name in LAYERS])
    raster[0] |= rings.astype(np.uint8)
    return raster


def _resample(points: np.ndarray, num: int) -> np.ndarray:
    """``num`` points evenly spaced by arc length along ``points`` ``(N, 2)``."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], num)
    return np.stack([np.interp(t, s, points[:, 0]), np.interp(t, s, points[:, 1])], -1)


def _pieces(points: np.ndarray, extent: np.ndarray, max_length_m: float) -> list[np.ndarray]:
    """Runs of ``points`` (scene frame, densified) inside ``[0, extent]``, split into pieces <= max length."""
    inside = ((points >= 0) & (points <= extent)).all(1)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], inside.astype(np.int8), [0]])))
    out = []
    for start, stop in zip(edges[::2], edges[1::2]):
        run = points[start:stop]
        if len(run) < 2:
            continue
        length = float(np.linalg.norm(np.diff(run, axis=0), axis=1).sum())
        if length <= 0:
            continue
        count = max(1, math.ceil(length / max_length_m))
        bounds = np.linspace(0, len(run) - 1, count + 1).round().astype(int)
        out.extend(run[a:b + 1] for a, b in zip(bounds[:-1], bounds[1:]) if b > a)
    return out


def vectorize(features: list[MapFeature], origin: np.ndarray, extent: np.ndarray, focus: np.ndarray,
              num_points: int, max_length_m: float, max_polylines: int) -> tuple[np.ndarray, np.ndarray]:
    """Vector map in the scene frame, clipped to ``[0, extent]`` (m, (2,)).

    Each feature polyline is densified (0.5 m), cut to the runs inside the bounds, split into pieces of at most
    ``max_length_m`` and resampled to ``num_points`` by arc length. At most ``max_polylines`` pieces are kept,
    those nearest ``focus`` (2,) first. Returns ``polylines`` float32 ``(P, L, 2)`` and ``types`` int64 ``(P,)``.
    """
    pieces: list[np.ndarray] = []
    types: list[int] = []
    for feature in features:
        scene = feature.polyline - origin
        if len(scene) < 2 or not _overlaps(feature, origin, origin + extent):
            continue
        length = float(np.linalg.norm(np.diff(scene, axis=0), axis=1).sum())
        dense = _resample(scene, max(2, math.ceil(length / 0.5) + 1))
        for piece in _pieces(dense, extent, max_length_m):
            pieces.append(_resample(piece, num_points))
            types.append(feature.polyline_type)
    if not pieces:
        return np.zeros((0, num_points, 2), np.float32), np.zeros((0,), np.int64)
    polylines = np.stack(pieces)
    kinds = np.array(types, np.int64)
    if len(pieces) > max_polylines:
        distance = np.linalg.norm(polylines - focus, axis=-1).min(1)
        keep = np.sort(np.argsort(distance, kind="stable")[:max_polylines])
        polylines, kinds = polylines[keep], kinds[keep]
    return polylines.astype(np.float32), kinds
