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


@dataclass(frozen=True, init=False)
class MapRaster:
    """Semantic map layers of a batch of scenes, each raster at its own size.

    Shapes (B = scenes, R = raster rows, C = layers, P = polylines, L = points per polyline):

    - ``pixels`` uint8 ``(C, N)``: the layers of every raster row, packed. Row r is an ``H_r x W_r`` image whose
      pixels are ``pixels[:, offsets[r] : offsets[r] + H_r * W_r]`` in row-major order; 1 where the layer is
      present, 0 elsewhere. Rows keep their own size, so a batch of maps of different extents holds no padding.
    - ``sizes`` int64 ``(R, 2)``: each row's ``(H_r, W_r)``; ``offsets`` int64 ``(R,)``: where each row starts
      (derived from ``sizes``).
    - ``rows`` int64 ``(B,)`` or None: the raster row each scene reads (None: scene b reads row b). Scenes cut
      from the same map share a row: ``index`` and ``repeat_scenes`` select rows and never copy pixels
      (``benchmarks/bench_map_rows.py`` measures what that saves).
    - ``world_to_pixel`` float32 ``(B, 3, 3)``: affine map from scene-frame metres to *fractional pixel
      indices*: ``(i, j, 1) = M @ (x, y, 1)`` where ``i`` indexes H and ``j`` indexes W. The pixel that contains a
      point is ``(floor(i), floor(j))``; a pixel outside its scene's ``H_r x W_r`` reads 0 in every layer.
    - ``layers``: the name of each of the C channels, e.g. ``("drivable", "road_divider", "lane_divider")``.
    - ``polylines`` float32 ``(B, P, L, 2)`` scene-frame metres, ``polyline_valid`` bool ``(B, P, L)`` and
      ``polyline_type`` int64 ``(B, P)`` (:class:`PolylineType`): optional vector map, ``None`` when absent.

    Build one from an image batch, ``MapRaster(raster=(R, C, H, W) uint8, world_to_pixel=...)`` (with
    ``sizes`` when the rows are zero-padded to a common size: each row keeps only its ``(H_r, W_r)`` corner).
    Read pixels through :meth:`read`, :meth:`lookup`, :meth:`lookup_points`, :meth:`scene_raster` or
    ``models.features.map_crops``; :meth:`padded` and :meth:`layer` give a rectangular (zero-padded) copy.
    """

    pixels: torch.Tensor
    sizes: torch.Tensor
    world_to_pixel: torch.Tensor
    layers: tuple[str, ...]
    polylines: torch.Tensor | None
    polyline_valid: torch.Tensor | None
    polyline_type: torch.Tensor | None
    rows: torch.Tensor | None
    offsets: torch.Tensor = field(init=False, repr=False, compare=False)

    def __init__(self, raster: torch.Tensor | None = None, world_to_pixel: torch.Tensor | None = None,
                 layers: tuple[str, ...] = DEFAULT_LAYERS, polylines: torch.Tensor | None = None,
                 polyline_valid: torch.Tensor | None = None, polyline_type: torch.Tensor | None = None,
                 rows: torch.Tensor | None = None, *, pixels: torch.Tensor | None = None,
                 sizes: torch.Tensor | None = None) -> None:
        layers = tuple(layers)
        if raster is not None:
            if pixels is not None:
                raise ScenarioValidationError("pass the map as `raster` (R, C, H, W) or as `pixels` (C, N) with "
                                              "`sizes`, not both (`dataclasses.replace` passes `pixels` and "
                                              "`sizes`: build a new MapRaster from a new raster instead).")
            pixels, sizes = _pack(raster, sizes, layers)
        elif pixels is None or sizes is None:
            raise ScenarioValidationError("a MapRaster needs `raster` (uint8 (R, C, H, W)) or `pixels` (uint8 "
                                          "(C, N)) with `sizes` (int64 (R, 2)).")
        if world_to_pixel is None:
            raise ScenarioValidationError("a MapRaster needs `world_to_pixel` (float32 (B, 3, 3)).")
        sizes = sizes.to(pixels.device)  # offsets and every per-scene look-up live beside the pixels
        _check_packed(pixels, sizes, layers)
        values = {"pixels": pixels, "sizes": sizes, "world_to_pixel": world_to_pixel, "layers": layers,
                  "polylines": polylines, "polyline_valid": polyline_valid, "polyline_type": polyline_type,
                  "rows": rows, "offsets": torch.cumsum(sizes[:, 0] * sizes[:, 1], 0) - sizes[:, 0] * sizes[:, 1]}
        for name, value in values.items():
            object.__setattr__(self, name, value)
        self._check()

    def _check(self) -> None:
        if self.rows is not None:
            rows = self.rows
            if rows.dim() != 1 or rows.dtype != torch.int64:
                raise ScenarioValidationError(f"`map.rows` must be an int64 tensor of shape (B,); got dtype "
                                              f"{rows.dtype}, shape {tuple(rows.shape)}.")
            if rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= self.num_rows):
                raise ScenarioValidationError(f"`map.rows` must index the {self.num_rows} raster rows; got values "
                                              f"from {int(rows.min())} to {int(rows.max())}.")
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
        return self.num_rows if self.rows is None else int(self.rows.shape[0])

    @property
    def num_rows(self) -> int:
        """Number of raster rows R."""
        return int(self.sizes.shape[0])

    def scene_rows(self) -> torch.Tensor:
        """``(B,)`` int64: the raster row each scene reads."""
        if self.rows is None:
            return torch.arange(self.num_rows, device=self.pixels.device)
        return self.rows

    def scene_sizes(self) -> torch.Tensor:
        """``(B, 2)`` int64: each scene's raster ``(H, W)``."""
        return self.sizes[self.scene_rows()]

    def row_raster(self, row: int) -> torch.Tensor:
        """Raster row ``row``'s layers, uint8 ``(C, H_r, W_r)`` (a view, no copy)."""
        h, w = (int(v) for v in self.sizes[row])
        start = int(self.offsets[row])
        return self.pixels[:, start : start + h * w].view(len(self.layers), h, w)

    def scene_raster(self, b: int) -> torch.Tensor:
        """Scene ``b``'s layers, uint8 ``(C, H, W)`` at its own size (a view, no copy)."""
        return self.row_raster(b if self.rows is None else int(self.rows[b]))

    def padded(self) -> torch.Tensor:
        """Every scene's layers as one uint8 ``(B, C, H, W)`` tensor, zero-padded to the largest scene (a copy)."""
        return self._padded(list(range(len(self.layers))))

    def layer(self, name: str) -> torch.Tensor:
        """The layer called ``name`` as a bool ``(B, H, W)`` tensor, zero-padded to the largest scene (a copy)."""
        return self._padded([self._layer_index(name)])[:, 0].bool()

    def _padded(self, channels: list[int]) -> torch.Tensor:
        sizes = self.scene_sizes()
        h, w = (int(v) for v in sizes.max(0).values) if len(sizes) else (0, 0)
        out = torch.zeros(self.num_scenes, len(channels), h, w, dtype=torch.uint8, device=self.pixels.device)
        for b in range(self.num_scenes):
            scene = self.scene_raster(b)[channels]
            out[b, :, : scene.shape[1], : scene.shape[2]] = scene
        return out

    def dense(self) -> MapRaster:
        """The same map with one raster row per scene (``rows`` None); copies the shared rows."""
        if self.rows is None:
            return self
        return _from_rows(self, [self.scene_raster(b) for b in range(self.num_scenes)], rows=None)

    def _layer_index(self, name: str) -> int:
        if name not in self.layers:
            raise ScenarioValidationError(f"map layer {name!r} not found; available layers: {list(self.layers)}.")
        return self.layers.index(name)

    def to_pixel(self, xy: torch.Tensor) -> torch.Tensor:
        """Fractional pixel indices ``(B, ..., 2)`` (i along H, j along W) of scene-frame points ``xy (B, ..., 2)``."""
        m = self.world_to_pixel.to(xy.dtype)
        shape = xy.shape
        flat = xy.reshape(shape[0], -1, 2)
        ij = torch.einsum("bkc,bnc->bnk", m[:, :2, :2], flat) + m[:, None, :2, 2]
        return ij.reshape(shape)

    def inside(self, scene: torch.Tensor, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
        """Whether integer pixel ``(i, j)`` lies in scene ``scene``'s raster (all three broadcast together)."""
        return self._locate(scene, i, j)[1]

    def _locate(self, scene: torch.Tensor, i: torch.Tensor, j: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(flat, inside)``: each pixel's index into ``pixels``' second axis (clamped into its scene's raster) and
        whether it lies inside that raster. Per-scene quantities are gathered at the scenes' own shape and broadcast
        in the arithmetic."""
        rows = self.scene_rows()[scene]
        h, w = self.sizes[rows, 0], self.sizes[rows, 1]
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
        flat = self.offsets[rows] + torch.minimum(i.clamp_min(0), h - 1) * w + torch.minimum(j.clamp_min(0), w - 1)
        return flat, inside

    def read(self, scene: torch.Tensor, i: torch.Tensor, j: torch.Tensor,
             layers: Sequence[int] | None = None) -> torch.Tensor:
        """uint8 ``(C', ...)``: the layers ``layers`` (indices; default all C) at integer pixel ``(i, j)`` of scene
        ``scene`` (int64 tensors that broadcast to ``...``); a pixel outside its scene's raster reads 0."""
        i, j = torch.broadcast_tensors(i, j)
        flat, inside = self._locate(scene, i, j)
        if layers is None:
            values = self.pixels[:, flat]
        elif len(layers) == 1:
            values = self.pixels[layers[0]][flat][None]
        else:
            channel = torch.as_tensor(list(layers), device=flat.device).reshape((-1,) + (1,) * flat.dim())
            values = self.pixels[channel, flat[None]]
        return values * inside[None]

    def lookup(self, xy: torch.Tensor, layer: str = "drivable") -> torch.Tensor:
        """Whether each scene-frame point ``xy (B, ..., 2)`` (m) lies on ``layer``; ``(B, ...)`` bool.

        Points outside the scene's raster count as *not* on the layer.
        """
        index = self._layer_index(layer)
        ij = torch.floor(self.to_pixel(xy)).long()
        scene = torch.arange(xy.shape[0], device=xy.device).reshape((-1,) + (1,) * (xy.dim() - 2))
        return self.read(scene, ij[..., 0], ij[..., 1], [index])[0] > 0

    def lookup_points(self, scene: torch.Tensor, xy: torch.Tensor, layer: str = "drivable") -> torch.Tensor:
        """Like :meth:`lookup` for a flat list of points: ``xy (N, 2)`` (m) in scenes ``scene (N,)``; ``(N,)`` bool.

        Cheaper than :meth:`lookup` when most agent slots are padding: only the listed points are transformed.
        """
        index = self._layer_index(layer)
        m = self.world_to_pixel.to(xy.dtype)[scene]  # (N, 3, 3)
        ij = torch.floor(torch.einsum("nkc,nc->nk", m[:, :2, :2], xy) + m[:, :2, 2]).long()
        return self.read(scene, ij[:, 0], ij[:, 1], [index])[0] > 0

    # ----------------------------------------------------------- batch ops
    def to(self, device: torch.device | str) -> MapRaster:
        """The same map on ``device``."""
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return replace(
            self,
            pixels=self.pixels.to(device),
            sizes=self.sizes.to(device),
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
            index = index.to(self.pixels.device)
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
        return self.index(torch.arange(self.num_scenes, device=self.pixels.device).repeat_interleave(copies))

    @staticmethod
    def concat(maps: Sequence[MapRaster]) -> MapRaster:
        """Stack maps along B; each keeps its rasters at their own size (once per distinct row its scenes read)
        and polylines are zero-padded to the largest P, L."""
        layers = maps[0].layers
        for m in maps[1:]:
            if m.layers != layers:
                raise ScenarioValidationError(
                    f"cannot concatenate maps with different layers: {layers} vs {m.layers}; rasterize all scenes"
                    " with the same layer set."
                )
        pixels, sizes, rows, offset = [], [], [], 0
        for m in maps:
            if m.rows is None:
                pixels.append(m.pixels)
                sizes.append(m.sizes)
                rows.append(offset + m.scene_rows())
            else:
                used, local = m.rows.unique(return_inverse=True)
                if len(used) == m.num_rows:  # every row is read: keep the buffer as it is
                    used, local = torch.arange(m.num_rows, device=m.pixels.device), m.rows
                    pixels.append(m.pixels)
                else:  # only the rows its scenes read (none for an empty selection)
                    pixels.append(torch.cat([m.pixels.new_zeros(len(layers), 0)]
                                            + [m.row_raster(int(r)).reshape(len(layers), -1) for r in used], 1))
                sizes.append(m.sizes[used])
                rows.append(offset + local)
            offset += len(sizes[-1])
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
            pixels=torch.cat(pixels, 1),
            sizes=torch.cat(sizes),
            rows=torch.cat(rows) if shared else None,
            world_to_pixel=torch.cat([m.world_to_pixel for m in maps]),
            layers=layers,
            polylines=polylines,
            polyline_valid=polyline_valid,
            polyline_type=polyline_type,
        )


def _pack(raster: torch.Tensor, sizes: torch.Tensor | None, layers: tuple[str, ...]) -> tuple[torch.Tensor, ...]:
    """``(pixels, sizes)`` of an image batch ``raster (R, C, H, W)``, each row cut to ``sizes`` (default H, W)."""
    if raster.dim() != 4 or raster.dtype != torch.uint8:
        raise ScenarioValidationError(
            f"`map.raster` must be a uint8 tensor of shape (B, C, H, W); got dtype {raster.dtype}, shape "
            f"{tuple(raster.shape)}. Convert with `raster.to(torch.uint8)` and add the batch axis."
        )
    r, c, h, w = raster.shape
    if c != len(layers):
        raise ScenarioValidationError(f"`map.layers` names {len(layers)} layers {layers} but `map.raster` has {c}"
                                      " channels; pass one name per channel.")
    if sizes is None:
        sizes = torch.tensor([[h, w]] * r, dtype=torch.int64, device=raster.device).reshape(r, 2)
        return raster.permute(1, 0, 2, 3).reshape(c, -1), sizes
    if tuple(sizes.shape) != (r, 2) or sizes.dtype != torch.int64:
        raise ScenarioValidationError(f"`map.sizes` must be an int64 tensor of shape ({r}, 2); got dtype "
                                      f"{sizes.dtype}, shape {tuple(sizes.shape)}.")
    if r and (int(sizes.min()) < 1 or int(sizes[:, 0].max()) > h or int(sizes[:, 1].max()) > w):
        raise ScenarioValidationError(f"`map.sizes` must lie between 1 and the raster's ({h}, {w}); got "
                                      f"{sizes.tolist()}.")
    parts = [raster[k, :, : int(sizes[k, 0]), : int(sizes[k, 1])].reshape(c, -1) for k in range(r)]
    return torch.cat(parts, 1) if parts else raster.new_zeros(c, 0), sizes


def _check_packed(pixels: torch.Tensor, sizes: torch.Tensor, layers: tuple[str, ...]) -> None:
    if pixels.dim() != 2 or pixels.dtype != torch.uint8 or pixels.shape[0] != len(layers):
        raise ScenarioValidationError(f"`map.pixels` must be a uint8 tensor of shape (C={len(layers)}, N); got "
                                      f"dtype {pixels.dtype}, shape {tuple(pixels.shape)}.")
    if sizes.dim() != 2 or sizes.shape[1] != 2 or sizes.dtype != torch.int64:
        raise ScenarioValidationError(f"`map.sizes` must be an int64 tensor of shape (R, 2); got dtype "
                                      f"{sizes.dtype}, shape {tuple(sizes.shape)}.")
    if len(sizes) and int(sizes.min()) < 1:
        raise ScenarioValidationError(f"`map.sizes` must be at least 1 pixel each way; got {sizes.tolist()}.")
    if int((sizes[:, 0] * sizes[:, 1]).sum()) != pixels.shape[1]:
        raise ScenarioValidationError(f"`map.pixels` holds {pixels.shape[1]} pixels per layer but `map.sizes` "
                                      f"adds up to {int((sizes[:, 0] * sizes[:, 1]).sum())}.")


def _from_rows(like: MapRaster, rasters: Sequence[torch.Tensor], **changes: object) -> MapRaster:
    """``like`` with the raster rows ``rasters`` (each uint8 ``(C, H_r, W_r)``) and ``changes``."""
    c = len(like.layers)
    pixels = torch.cat([like.pixels.new_zeros(c, 0)] + [r.reshape(c, -1) for r in rasters], 1)
    sizes = torch.tensor([list(r.shape[1:]) for r in rasters], dtype=torch.int64, device=pixels.device)
    return replace(like, pixels=pixels, sizes=sizes.reshape(-1, 2), **changes)


def crop_map(scene_map: MapRaster, xy: torch.Tensor, margin_m: float) -> MapRaster:
    """Keep the raster pixels under the bounding box of ``xy (K, 2)`` (scene-frame m) plus ``margin_m``.

    One scene (B = 1). The transform is shifted so every world point keeps its map value. Polylines are
    dropped: a cropped map is a raster-only map.
    """
    if xy.numel() == 0:
        return scene_map
    raster = scene_map.scene_raster(0)
    lo, hi = xy.min(0).values.double() - margin_m, xy.max(0).values.double() + margin_m
    corners = torch.tensor([[x, y] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])], dtype=torch.float64)
    ij = scene_map.to_pixel(corners[None].to(scene_map.world_to_pixel.dtype))[0].double()
    h, w = raster.shape[-2:]
    i0, i1 = max(math.floor(ij[:, 0].min()), 0), min(math.ceil(ij[:, 0].max()) + 1, h)
    j0, j1 = max(math.floor(ij[:, 1].min()), 0), min(math.ceil(ij[:, 1].max()) + 1, w)
    if i0 >= i1 or j0 >= j1:  # agents entirely off the raster: keep one empty pixel
        i0, i1, j0, j1 = 0, 1, 0, 1
    m = scene_map.world_to_pixel.clone()
    m[:, 0, 2] -= i0
    m[:, 1, 2] -= j0
    return MapRaster(raster=raster[None, :, i0:i1, j0:j1].contiguous(), world_to_pixel=m, layers=scene_map.layers)
