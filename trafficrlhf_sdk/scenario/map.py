"""Map rasters (and optional vector polylines) that travel with a :class:`ScenarioTensor`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from collections.abc import Sequence

import torch

from trafficrlhf_sdk.errors import ScenarioValidationError

__all__ = ["DEFAULT_LAYERS", "MapRaster", "PolylineType", "crop_map"]

DEFAULT_LAYERS: tuple[str, ...] = ("drivable", "road_divider", "lane_divider")


class PolylineType:
    """Codes stored in ``MapRaster.polyline_type``."""

    UNSET = 0
    LANE_CENTER = 1
    ROAD_EDGE = 2
    ROAD_LINE = 3
    CROSSWALK = 4
    OTHER = 5


def check_copies(copies: object) -> None:
    """Raise a ValueError unless ``copies`` (a ``repeat_scenes`` count) is a positive int."""
    if not (isinstance(copies, int) and not isinstance(copies, bool) and copies >= 1):
        raise ValueError(f"`copies` must be a positive int; got {copies!r}.")


@dataclass(frozen=True)
class MapRaster:
    """Semantic map layers of a batch of scenes.

    Shapes (B = scenes, C = layers, H x W = pixels, P = polylines, L = points per polyline):

    - ``raster`` uint8 ``(R, C, H, W)``: 1 where the layer is present, 0 elsewhere (and in padding). Without
      ``rows``, R = B and scene b reads row b.
    - ``rows`` int64 ``(B,)`` or None: the raster row each scene reads. Scenes cut from the same map share a row:
      ``index`` and ``repeat_scenes`` select rows and never copy pixels (``benchmarks/bench_map_rows.py`` measures
      what that saves). Read pixels through
      :meth:`lookup`, :meth:`lookup_points`, :meth:`layer`, :meth:`gather_pixels`, :meth:`scene_raster` or
      ``models.features.map_crops``; :meth:`dense` gives one row per scene.
    - ``world_to_pixel`` float32 ``(B, 3, 3)``: affine map from scene-frame metres to *fractional pixel
      indices*: ``(i, j, 1) = M @ (x, y, 1)`` where ``i`` indexes H and ``j`` indexes W. The pixel that contains a
      point is ``(floor(i), floor(j))``.
    - ``layers``: the name of each of the C channels, e.g. ``("drivable", "road_divider", "lane_divider")``.
    - ``polylines`` float32 ``(B, P, L, 2)`` scene-frame metres, ``polyline_valid`` bool ``(B, P, L)`` and
      ``polyline_type`` int64 ``(B, P)`` (:class:`PolylineType`): optional vector map, ``None`` when absent.
    """

    raster: torch.Tensor
    world_to_pixel: torch.Tensor
    layers: tuple[str, ...] = DEFAULT_LAYERS
    polylines: torch.Tensor | None = None
    polyline_valid: torch.Tensor | None = None
    polyline_type: torch.Tensor | None = None
    rows: torch.Tensor | None = None
    _checked: bool = field(default=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        r = self.raster
        if r.dim() != 4 or r.dtype != torch.uint8:
            raise ScenarioValidationError(
                f"`map.raster` must be a uint8 tensor of shape (B, C, H, W); got dtype {r.dtype}, shape "
                f"{tuple(r.shape)}. Convert with `raster.to(torch.uint8)` and add the batch axis."
            )
        if r.shape[1] != len(self.layers):
            raise ScenarioValidationError(
                f"`map.layers` names {len(self.layers)} layers {self.layers} but `map.raster` has {r.shape[1]}"
                " channels; pass one name per channel."
            )
        if self.rows is not None:
            rows = self.rows
            if rows.dim() != 1 or rows.dtype != torch.int64:
                raise ScenarioValidationError(f"`map.rows` must be an int64 tensor of shape (B,); got dtype "
                                              f"{rows.dtype}, shape {tuple(rows.shape)}.")
            if rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= r.shape[0]):
                raise ScenarioValidationError(f"`map.rows` must index the {r.shape[0]} raster rows; got values from "
                                              f"{int(rows.min())} to {int(rows.max())}.")
        b = self.num_scenes
        if tuple(self.world_to_pixel.shape) != (b, 3, 3):
            raise ScenarioValidationError(
                f"`map.world_to_pixel` must have shape ({b}, 3, 3); got {tuple(self.world_to_pixel.shape)}."
            )
        if not torch.isfinite(self.world_to_pixel).all():
            raise ScenarioValidationError("`map.world_to_pixel` contains NaN or inf; every transform must be finite.")
        if self.polylines is not None:
            p = self.polylines.shape[1] if self.polylines.dim() == 4 else -1
            if self.polylines.dim() != 4 or self.polylines.shape[0] != b or self.polylines.shape[-1] != 2:
                raise ScenarioValidationError(
                    f"`map.polylines` must have shape (B={b}, P, L, 2); got {tuple(self.polylines.shape)}."
                )
            if self.polyline_valid is None or self.polyline_valid.shape != self.polylines.shape[:3]:
                raise ScenarioValidationError(
                    "`map.polyline_valid` must be a bool tensor of shape (B, P, L) matching `map.polylines`."
                )
            if self.polyline_type is None or tuple(self.polyline_type.shape) != (b, p):
                raise ScenarioValidationError("`map.polyline_type` must be an int tensor of shape (B, P).")

    # ------------------------------------------------------------------ views
    @property
    def num_scenes(self) -> int:
        """Number of scenes B."""
        return int(self.raster.shape[0] if self.rows is None else self.rows.shape[0])

    def scene_rows(self) -> torch.Tensor:
        """``(B,)`` int64: the raster row each scene reads."""
        if self.rows is None:
            return torch.arange(self.raster.shape[0], device=self.raster.device)
        return self.rows

    def scene_raster(self, b: int) -> torch.Tensor:
        """Scene ``b``'s layers, uint8 ``(C, H, W)`` (a view, no copy)."""
        return self.raster[b if self.rows is None else int(self.rows[b])]

    def dense(self) -> MapRaster:
        """The same map with one raster row per scene (``rows`` None); copies the shared rows."""
        if self.rows is None:
            return self
        return replace(self, raster=self.raster[self.rows], rows=None)

    def layer(self, name: str) -> torch.Tensor:
        """The layer called ``name`` as a bool tensor ``(B, H, W)``."""
        if name not in self.layers:
            raise ScenarioValidationError(f"map layer {name!r} not found; available layers: {list(self.layers)}.")
        grid = self.raster[:, self.layers.index(name)]
        return (grid if self.rows is None else grid[self.rows]).bool()

    def to_pixel(self, xy: torch.Tensor) -> torch.Tensor:
        """Fractional pixel indices ``(B, ..., 2)`` (i along H, j along W) of scene-frame points ``xy (B, ..., 2)``."""
        m = self.world_to_pixel.to(xy.dtype)
        shape = xy.shape
        flat = xy.reshape(shape[0], -1, 2)
        ij = torch.einsum("bkc,bnc->bnk", m[:, :2, :2], flat) + m[:, None, :2, 2]
        return ij.reshape(shape)

    def lookup(self, xy: torch.Tensor, layer: str = "drivable") -> torch.Tensor:
        """Whether each scene-frame point ``xy (B, ..., 2)`` (m) lies on ``layer``; ``(B, ...)`` bool.

        Points outside the raster count as *not* on the layer.
        """
        if layer not in self.layers:
            raise ScenarioValidationError(f"map layer {layer!r} not found; available layers: {list(self.layers)}.")
        grid = self.raster[:, self.layers.index(layer)]  # uint8; avoids copying the whole layer to bool
        _, h, w = grid.shape
        ij = torch.floor(self.to_pixel(xy)).long()
        i, j = ij[..., 0], ij[..., 1]
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
        flat_index = i.clamp(0, h - 1) * w + j.clamp(0, w - 1)
        values = self.gather_pixels(flat_index.reshape(flat_index.shape[0], -1), self.layers.index(layer))
        return (values[:, 0].reshape(flat_index.shape) > 0) & inside

    def gather_pixels(self, flat_index: torch.Tensor, layer: int | None = None) -> torch.Tensor:
        """uint8 ``(B, C, K)`` (``(B, 1, K)`` for one ``layer``): each scene's layers at the flat pixel indices
        ``flat_index (B, K)`` (``i * W + j``, within ``0 .. H*W - 1``). Scenes sharing a raster row are gathered
        from it together, without copying the row."""
        raster = self.raster if layer is None else self.raster[:, layer : layer + 1]
        r, c = raster.shape[:2]
        b, k = flat_index.shape
        if self.rows is None:
            return raster.reshape(r, c, -1).gather(2, flat_index[:, None].expand(b, c, k))
        out = torch.empty(b, c, k, dtype=raster.dtype, device=raster.device)
        for row in self.rows.unique().tolist():
            scenes = (self.rows == row).nonzero().flatten()
            n = len(scenes)
            shared = raster[row : row + 1].reshape(1, c, -1).expand(n, c, -1)  # the row once, read n times
            first = int(scenes[0])
            if int(scenes[-1]) - first + 1 == n:  # a run of scenes (what repeat_scenes gives): no scatter
                torch.gather(shared, 2, flat_index[first : first + n, None].expand(n, c, k), out=out[first : first + n])
            else:
                out[scenes] = shared.gather(2, flat_index[scenes, None].expand(n, c, k))
        return out

    def lookup_points(self, scene: torch.Tensor, xy: torch.Tensor, layer: str = "drivable") -> torch.Tensor:
        """Like :meth:`lookup` for a flat list of points: ``xy (N, 2)`` (m) in scenes ``scene (N,)``; ``(N,)`` bool.

        Cheaper than :meth:`lookup` when most agent slots are padding: only the listed points are transformed.
        """
        if layer not in self.layers:
            raise ScenarioValidationError(f"map layer {layer!r} not found; available layers: {list(self.layers)}.")
        grid = self.raster[:, self.layers.index(layer)]
        _, h, w = grid.shape
        m = self.world_to_pixel.to(xy.dtype)[scene]  # (N, 3, 3)
        ij = torch.floor(torch.einsum("nkc,nc->nk", m[:, :2, :2], xy) + m[:, :2, 2]).long()
        i, j = ij[:, 0], ij[:, 1]
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
        rows = scene if self.rows is None else self.rows[scene]
        values = grid[rows, i.clamp(0, h - 1), j.clamp(0, w - 1)]
        return (values > 0) & inside

    # ----------------------------------------------------------- batch ops
    def to(self, device: torch.device | str) -> MapRaster:
        """The same map on ``device``."""
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return replace(
            self,
            raster=self.raster.to(device),
            rows=move(self.rows),
            world_to_pixel=self.world_to_pixel.to(device),
            polylines=move(self.polylines),
            polyline_valid=move(self.polyline_valid),
            polyline_type=move(self.polyline_type),
        )

    def index(self, index: torch.Tensor | slice | int) -> MapRaster:
        """Select scenes along B (an int keeps the batch axis). The selection shares this map's raster rows."""
        if isinstance(index, int):
            index = slice(index, index + 1)
        pick = lambda t: None if t is None else t[index]  # noqa: E731
        if isinstance(index, torch.Tensor):
            index = index.to(self.raster.device)
        return replace(
            self,
            rows=self.scene_rows()[index],
            world_to_pixel=self.world_to_pixel[index],
            polylines=pick(self.polylines),
            polyline_valid=pick(self.polyline_valid),
            polyline_type=pick(self.polyline_type),
        )

    def repeat_scenes(self, copies: int) -> MapRaster:
        """Each scene's map ``copies`` times in a row (``B * copies`` scenes), sharing this map's raster rows."""
        check_copies(copies)
        return self.index(torch.arange(self.num_scenes, device=self.raster.device).repeat_interleave(copies))

    @staticmethod
    def concat(maps: Sequence[MapRaster]) -> MapRaster:
        """Stack maps along B, zero-padding rasters to the largest H, W and polylines to the largest P, L."""
        layers = maps[0].layers
        for m in maps[1:]:
            if m.layers != layers:
                raise ScenarioValidationError(
                    f"cannot concatenate maps with different layers: {layers} vs {m.layers}; rasterize all scenes"
                    " with the same layer set."
                )
        h = max(m.raster.shape[2] for m in maps)
        w = max(m.raster.shape[3] for m in maps)
        # keep only the rows each map's scenes read, once per distinct row
        parts, rows, offset = [], [], 0
        for m in maps:
            used, local = m.scene_rows().unique(return_inverse=True) if m.rows is not None else (None, None)
            kept = m.raster if used is None else m.raster[used]
            parts.append(torch.nn.functional.pad(kept, (0, w - kept.shape[3], 0, h - kept.shape[2])))
            rows.append(offset + (m.scene_rows() if local is None else local))
            offset += kept.shape[0]
        raster = torch.cat(parts)
        shared = any(m.rows is not None for m in maps)
        polylines = polyline_valid = polyline_type = None
        if all(m.polylines is not None for m in maps):
            p = max(m.polylines.shape[1] for m in maps)  # type: ignore[union-attr]
            length = max(m.polylines.shape[2] for m in maps)  # type: ignore[union-attr]

            def pad(t: torch.Tensor, dims: int) -> torch.Tensor:
                extra = [0, length - t.shape[2], 0, p - t.shape[1]] if dims == 3 else [0, p - t.shape[1]]
                return torch.nn.functional.pad(t, ([0, 0] if t.dim() == 4 else []) + extra)

            polylines = torch.cat([pad(m.polylines, 3) for m in maps])  # type: ignore[arg-type]
            polyline_valid = torch.cat([pad(m.polyline_valid, 3) for m in maps])  # type: ignore[arg-type]
            polyline_type = torch.cat([pad(m.polyline_type, 1) for m in maps])  # type: ignore[arg-type]
        return MapRaster(
            raster=raster,
            rows=torch.cat(rows) if shared else None,
            world_to_pixel=torch.cat([m.world_to_pixel for m in maps]),
            layers=layers,
            polylines=polylines,
            polyline_valid=polyline_valid,
            polyline_type=polyline_type,
        )


def crop_map(scene_map: MapRaster, xy: torch.Tensor, margin_m: float) -> MapRaster:
    """Keep the raster pixels under the bounding box of ``xy (K, 2)`` (scene-frame m) plus ``margin_m``.

    One scene (B = 1). The transform is shifted so every world point keeps its map value. Polylines are
    dropped: a cropped map is a raster-only map.
    """
    if xy.numel() == 0:
        return scene_map
    scene_map = scene_map.dense()
    lo, hi = xy.min(0).values.double() - margin_m, xy.max(0).values.double() + margin_m
    corners = torch.tensor([[x, y] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])], dtype=torch.float64)
    ij = scene_map.to_pixel(corners[None].to(scene_map.world_to_pixel.dtype))[0].double()
    h, w = scene_map.raster.shape[-2:]
    i0, i1 = max(math.floor(ij[:, 0].min()), 0), min(math.ceil(ij[:, 0].max()) + 1, h)
    j0, j1 = max(math.floor(ij[:, 1].min()), 0), min(math.ceil(ij[:, 1].max()) + 1, w)
    if i0 >= i1 or j0 >= j1:  # agents entirely off the raster: keep one empty pixel
        i0, i1, j0, j1 = 0, 1, 0, 1
    m = scene_map.world_to_pixel.clone()
    m[:, 0, 2] -= i0
    m[:, 1, 2] -= j0
    return MapRaster(raster=scene_map.raster[:, :, i0:i1, j0:j1].contiguous(), world_to_pixel=m,
                     layers=scene_map.layers)
