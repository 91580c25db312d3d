"""Matplotlib pictures of scenes: map raster, agent boxes, logged trails and optional simulated trajectories.

Rendering never opens a window: figures are built on matplotlib's Agg canvas directly (no ``pyplot``, no change
of the global backend), so this works on headless machines and inside notebooks alike.

Example::

    from trafficrlhf_sdk.render import save_scene_png
    save_scene_png(scenario, "scene.png")               # boxes at ``current_index``
    fig = render_scene(scenario, index=3, step=80)      # a matplotlib Figure to show or save
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.transforms import Affine2D

from trafficrlhf_sdk.errors import ScenarioValidationError
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.map import MapRaster, PolylineType
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["agent_colour", "box_corners", "draw_map", "hex_colour", "render_scene", "save_scene_png", "short_id",
           "to_world", "valid_runs", "view_box"]

MARGIN_M = 15.0  # view = agents' extent + this margin on every side
MAX_LABELS = 25  # with more agents on screen, only controlled ones get an id label
MAX_ID_CHARS = 9  # longer ids (hashes) are cut
MIN_ASPECT, MAX_ASPECT = 0.55, 1.6  # height / width of the view; the shorter side is widened to fit

BACKGROUND_RGB = (244, 243, 238)
MAP_LAYER_RGB = {  # drawn in this order, later layers on top
    "drivable": (196, 196, 196),
    "lane_divider": (255, 255, 255),
    "road_divider": (233, 190, 40),
}
POLYLINE_STYLE = {  # vector map (where a source provides one): colour, line width, line style
    PolylineType.LANE_CENTER: ("#9aa7b8", 0.6, ":"),
    PolylineType.ROAD_EDGE: ("#555555", 0.9, "-"),
    PolylineType.ROAD_LINE: ("#ffffff", 0.8, "--"),
    PolylineType.CROSSWALK: ("#8a8a8a", 0.8, "-"),
    PolylineType.OTHER: ("#b0b0b0", 0.5, "-"),
}
CONTROLLED_COLOUR = "#1f5fbf"
REPLAYED_COLOURS = {
    AgentType.VEHICLE: "#f28e2b",
    AgentType.PEDESTRIAN: "#d62728",
    AgentType.CYCLIST: "#2ca02c",
    AgentType.OTHER: "#8c6d31",
    AgentType.UNSET: "#7f7f7f",
}
SIM_COLOUR = "#9b3fd1"


# --------------------------------------------------------------------------------------------- public API
def render_scene(
    scenario: ScenarioTensor,
    index: int = 0,
    step: int | None = None,
    ax: Axes | None = None,
    title: str | None = None,
    show_ids: bool = True,
    sim_states: torch.Tensor | np.ndarray | ScenarioTensor | None = None,
) -> Figure:
    """Draw scene ``index`` of ``scenario`` and return the matplotlib Figure.

    Args:
        scenario: the batch holding the scene.
        index: which scene of the batch (B axis).
        step: time step at which the agent boxes are drawn; defaults to ``scenario.current_index``.
            Trails are solid up to ``current_index`` (history) and dashed after it (logged future).
        ax: an existing Axes to draw into; a new Agg-backed Figure is made when None.
        title: the axes title; a default names the source, scene and step.
        show_ids: label each agent with its id (``scenario.agent_ids``, else its slot index).
        sim_states: optional simulated states ``(A, T', 4)`` or ``(B, A, T', 4)`` drawn over the log in another
            colour (trajectories, and outlined boxes at ``step``). Pass a ScenarioTensor (e.g. a rollout) to use
            its ``valid`` mask; for bare arrays, agents valid at ``current_index`` are drawn and entries that are
            non-finite or all zero (the padding convention) are skipped. When ``T' == T`` only steps from
            ``current_index`` on are drawn (before it the rollout is the log).

    Raises:
        ScenarioValidationError: ``index``, ``step`` or ``sim_states`` does not fit the scenario.
    """
    b = _check_index(scenario, index)
    num_steps = scenario.num_steps
    step = scenario.current_index if step is None else int(step)
    if not 0 <= step < num_steps:
        raise ScenarioValidationError(
            f"`step` must be in 0..{num_steps - 1} (the scene has {num_steps} steps of {scenario.dt} s); got {step}."
        )

    states = scenario.states[b].detach().to("cpu", torch.float64).numpy()  # (A, T, 4)
    valid = scenario.valid[b].detach().cpu().numpy()  # (A, T)
    extent = scenario.extent[b].detach().to("cpu", torch.float64).numpy()  # (A, 2)
    agent_type = scenario.agent_type[b].detach().cpu().numpy()
    controlled = scenario.controlled[b].detach().cpu().numpy()
    sim_xy_states, sim_valid = _sim_arrays(sim_states, scenario, b)

    view = view_box(states, valid, sim_xy_states, sim_valid, scenario.map, b)
    if ax is None:
        ratio = (view[3] - view[2]) / (view[1] - view[0])
        fig = Figure(figsize=(8.0, max(4.5, 8.0 * ratio) + 0.4), dpi=100, layout="constrained")
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
    else:
        fig = ax.figure  # type: ignore[assignment]

    ax.set_facecolor(hex_colour(BACKGROUND_RGB))
    if scenario.map is not None:
        draw_map(ax, scenario.map, b, view)

    colours = [agent_colour(int(agent_type[a]), bool(controlled[a])) for a in range(len(states))]
    _draw_trails(ax, states, valid, colours, scenario.current_index)
    if sim_xy_states is not None and sim_valid is not None:
        _draw_sim(ax, sim_xy_states, sim_valid, extent, step)
    at_step = np.flatnonzero(valid[:, step])
    _draw_boxes(ax, states[at_step, step], extent[at_step], [colours[a] for a in at_step])
    if show_ids:
        ids = scenario.agent_ids[b] if scenario.agent_ids else tuple(str(a) for a in range(len(states)))
        labelled = at_step if len(at_step) <= MAX_LABELS else at_step[controlled[at_step]][:MAX_LABELS]
        tops = box_corners(states[labelled, step], extent[labelled])[..., 1].max(-1)  # label above each box
        for a, top in zip(labelled, tops):
            ax.annotate(short_id(ids[a] or str(a)), (states[a, step, 0], top), xytext=(0, 3),
                        textcoords="offset points", ha="center", va="bottom", fontsize=7, zorder=8,
                        color="#1a1a1a", bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none",
                                               "alpha": 0.7})

    ax.set_xlim(view[0], view[1])
    ax.set_ylim(view[2], view[3])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title if title is not None else _default_title(scenario, b, step), fontsize=10)
    _legend(ax, agent_type, controlled, valid, sim_xy_states is not None)
    return fig


def save_scene_png(scenario: ScenarioTensor, path: str | os.PathLike[str], dpi: int = 110, **kw: Any) -> str:
    """Render with :func:`render_scene` (keyword arguments ``kw``) and write a PNG to ``path``; returns the path."""
    if kw.get("ax") is not None:
        raise ValueError("save_scene_png makes its own figure; call render_scene(ax=...) to draw into an Axes.")
    fig = render_scene(scenario, **kw)
    path = os.fspath(path)
    parent = os.path.dirname(os.path.abspath(path))
    os.makedirs(parent, exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png", facecolor="white")
    return path


# ---------------------------------------------------------------------------------------------- helpers
def _check_index(scenario: ScenarioTensor, index: int) -> int:
    b = scenario.num_scenes
    if not -b <= index < b:
        raise ScenarioValidationError(f"scene `index` {index} is out of range for a batch of {b} scenes.")
    return index % b


def short_id(agent_id: str) -> str:
    """``agent_id`` cut to :data:`MAX_ID_CHARS` characters (long ids are hashes)."""
    return agent_id if len(agent_id) <= MAX_ID_CHARS else agent_id[: MAX_ID_CHARS - 2] + "…"


def hex_colour(rgb: Sequence[int]) -> str:
    """``"#rrggbb"`` of an RGB triple (0-255)."""
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def agent_colour(code: int, is_controlled: bool) -> str:
    """The drawing colour of an agent: :data:`CONTROLLED_COLOUR` when a model drives it, else its type's."""
    if is_controlled:
        return CONTROLLED_COLOUR
    try:
        return REPLAYED_COLOURS[AgentType(code)]
    except ValueError:
        return REPLAYED_COLOURS[AgentType.OTHER]


def _type_name(code: int) -> str:
    try:
        return AgentType(code).name.lower()
    except ValueError:
        return "other"


def _sim_arrays(sim: torch.Tensor | np.ndarray | ScenarioTensor | None, scenario: ScenarioTensor,
                b: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Simulated ``states (A, T', 4)`` and ``valid (A, T')`` as numpy, or (None, None)."""
    if sim is None:
        return None, None
    sim_valid = None
    if isinstance(sim, ScenarioTensor):
        if sim.num_scenes != scenario.num_scenes and sim.num_scenes != 1:
            raise ScenarioValidationError(
                f"`sim_states` holds {sim.num_scenes} scenes but the scenario holds {scenario.num_scenes}."
            )
        sb = b if sim.num_scenes == scenario.num_scenes else 0
        sim_valid = sim.valid[sb].detach().cpu().numpy()
        sim = sim.states[sb]
    arr = sim.detach().to("cpu", torch.float64).numpy() if isinstance(sim, torch.Tensor) else np.asarray(sim, float)
    if arr.ndim == 4:
        arr = arr[b if arr.shape[0] == scenario.num_scenes else 0]
    if arr.ndim != 3 or arr.shape[0] != scenario.num_agents or arr.shape[-1] < 2:
        raise ScenarioValidationError(
            f"`sim_states` must have shape (A={scenario.num_agents}, T, 4) (or (B, A, T, 4)); got {arr.shape}."
        )
    keep = np.isfinite(arr[..., :2]).all(-1)
    log_valid = scenario.valid[b].detach().cpu().numpy()
    if sim_valid is not None:
        keep &= sim_valid & log_valid.any(-1)[:, None]  # padding slots are never drawn
    else:  # no mask given: agents present "now", and not the zeros that fill invalid entries
        keep &= log_valid[:, scenario.current_index, None] & (arr != 0).any(-1)
    if arr.shape[1] == scenario.num_steps:  # same time grid as the log: the history is the log itself
        keep[:, : scenario.current_index] = False
    return arr, keep


def view_box(states: np.ndarray, valid: np.ndarray, sim: np.ndarray | None, sim_valid: np.ndarray | None,
              scene_map: MapRaster | None, b: int) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): every valid position (logged and simulated) plus the margin, widened to a sane aspect."""
    points = [states[valid][:, :2]]
    if sim is not None and sim_valid is not None:
        points.append(sim[sim_valid][:, :2])
    xy = np.concatenate(points) if points else np.zeros((0, 2))
    if len(xy):
        x0, y0 = xy.min(0) - MARGIN_M
        x1, y1 = xy.max(0) + MARGIN_M
    elif scene_map is not None:  # no agent: show the whole map
        x0, x1, y0, y1 = _map_world_bounds(scene_map, b)
    else:
        x0, x1, y0, y1 = -50.0, 50.0, -50.0, 50.0
    dx, dy = x1 - x0, y1 - y0
    ratio = min(max(dy / dx, MIN_ASPECT), MAX_ASPECT)
    if dy < ratio * dx:  # too flat: grow y
        grow = (ratio * dx - dy) / 2
        y0, y1 = y0 - grow, y1 + grow
    else:  # too tall: grow x
        grow = (dy / ratio - dx) / 2
        x0, x1 = x0 - grow, x1 + grow
    return float(x0), float(x1), float(y0), float(y1)


def _map_world_bounds(scene_map: MapRaster, b: int) -> tuple[float, float, float, float]:
    h, w = scene_map.scene_raster(b).shape[-2:]
    inv = np.linalg.inv(scene_map.world_to_pixel[b].detach().to("cpu", torch.float64).numpy())
    corners = np.array([[i, j, 1.0] for i in (0, h) for j in (0, w)]) @ inv.T
    return corners[:, 0].min(), corners[:, 0].max(), corners[:, 1].min(), corners[:, 1].max()


def draw_map(ax: Axes, scene_map: MapRaster, b: int, view: tuple[float, float, float, float]) -> None:
    """Draw the raster layers (cropped to the view) and any vector polylines."""
    m = scene_map.world_to_pixel[b].detach().to("cpu", torch.float64).numpy()
    raster = scene_map.scene_raster(b)
    _, h, w = raster.shape
    # Crop to the pixels under the view (a little padding so aspect adjustments never show an edge).
    pad_x, pad_y = 0.1 * (view[1] - view[0]), 0.1 * (view[3] - view[2])
    corners = np.array([[x, y, 1.0] for x in (view[0] - pad_x, view[1] + pad_x)
                        for y in (view[2] - pad_y, view[3] + pad_y)]) @ m.T
    i0 = int(np.clip(math.floor(corners[:, 0].min()), 0, h))
    i1 = int(np.clip(math.ceil(corners[:, 0].max()) + 1, 0, h))
    j0 = int(np.clip(math.floor(corners[:, 1].min()), 0, w))
    j1 = int(np.clip(math.ceil(corners[:, 1].max()) + 1, 0, w))
    if i0 < i1 and j0 < j1:
        sub = raster[:, i0:i1, j0:j1].detach().cpu().numpy()
        rgba = np.empty(sub.shape[1:] + (4,), np.uint8)
        rgba[...] = (*BACKGROUND_RGB, 255)
        for name, rgb in MAP_LAYER_RGB.items():
            if name in scene_map.layers:
                rgba[sub[scene_map.layers.index(name)] > 0, :3] = rgb
        _imshow_pixels(ax, rgba, m, (i0, i1, j0, j1))
    if scene_map.polylines is not None:
        _draw_polylines(ax, scene_map, b)


def _imshow_pixels(ax: Axes, rgba: np.ndarray, m: np.ndarray, box: tuple[int, int, int, int]) -> None:
    """Show ``rgba[i - i0, j - j0]`` (pixels ``i0:i1, j0:j1``) where ``world_to_pixel`` ``m`` puts them.

    ``(i, j, 1) = m @ (x, y, 1)``: an axis-aligned scale + offset (either axis order, any sign) goes through
    ``extent``; any other affine map goes through an image transform.
    """
    i0, i1, j0, j1 = box
    a = m[:2, :2]
    tol = 1e-9 * np.abs(a).max()
    common = {"origin": "lower", "interpolation": "nearest", "zorder": 0, "resample": False}
    if abs(a[0, 1]) <= tol and abs(a[1, 0]) <= tol:  # i from x, j from y: show x (rows) horizontally
        x_of = lambda i: (i - m[0, 2]) / a[0, 0]  # noqa: E731
        y_of = lambda j: (j - m[1, 2]) / a[1, 1]  # noqa: E731
        ax.imshow(rgba.transpose(1, 0, 2), extent=(x_of(i0), x_of(i1), y_of(j0), y_of(j1)), **common)
    elif abs(a[0, 0]) <= tol and abs(a[1, 1]) <= tol:  # i from y, j from x: columns already run along x
        x_of = lambda j: (j - m[1, 2]) / a[1, 0]  # noqa: E731
        y_of = lambda i: (i - m[0, 2]) / a[0, 1]  # noqa: E731
        ax.imshow(rgba, extent=(x_of(j0), x_of(j1), y_of(i0), y_of(i1)), **common)
    else:  # rotated / sheared: image coordinates (u = j, v = i) -> world through the inverse map
        inv = np.linalg.inv(m)
        to_world = Affine2D(np.array([[inv[0, 1], inv[0, 0], inv[0, 2]],
                                      [inv[1, 1], inv[1, 0], inv[1, 2]],
                                      [0.0, 0.0, 1.0]]))
        common["resample"] = True
        ax.imshow(rgba, extent=(j0, j1, i0, i1), transform=to_world + ax.transData, **common)


def _draw_polylines(ax: Axes, scene_map: MapRaster, b: int) -> None:
    lines = scene_map.polylines[b].detach().to("cpu", torch.float64).numpy()  # type: ignore[index]
    ok = scene_map.polyline_valid[b].detach().cpu().numpy()  # type: ignore[index]
    kinds = scene_map.polyline_type[b].detach().cpu().numpy()  # type: ignore[index]
    for kind, (colour, width, style) in POLYLINE_STYLE.items():
        segments = [run for p in np.flatnonzero(kinds == kind) for run in valid_runs(lines[p], ok[p])]
        if segments:
            ax.add_collection(LineCollection(segments, colors=colour, linewidths=width, linestyles=style,
                                             zorder=1))


def valid_runs(points: np.ndarray, mask: np.ndarray) -> list[np.ndarray]:
    """Contiguous stretches (of at least two points) of ``points[mask]``."""
    idx = np.flatnonzero(mask)
    if len(idx) < 2:
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1) + 1
    return [points[chunk] for chunk in np.split(idx, breaks) if len(chunk) >= 2]


def _draw_trails(ax: Axes, states: np.ndarray, valid: np.ndarray, colours: list[str], current: int) -> None:
    """History (solid, steps ``0..current``) and logged future (dashed, ``current..T-1``) of every agent."""
    for part, style, width, alpha in (("history", "-", 1.6, 0.9), ("future", (0, (4, 3)), 1.2, 0.75)):
        window = slice(0, current + 1) if part == "history" else slice(current, None)
        segments, seg_colours = [], []
        for a in range(len(states)):
            for run in valid_runs(states[a, window, :2], valid[a, window]):
                segments.append(run)
                seg_colours.append(colours[a])
        if segments:
            ax.add_collection(LineCollection(segments, colors=seg_colours, linewidths=width, linestyles=style,
                                             alpha=alpha, zorder=3, capstyle="round"))


def _draw_sim(ax: Axes, sim: np.ndarray, sim_valid: np.ndarray, extent: np.ndarray, step: int) -> None:
    segments = [run for a in range(len(sim)) for run in valid_runs(sim[a, :, :2], sim_valid[a])]
    if segments:
        ax.add_collection(LineCollection(segments, colors=SIM_COLOUR, linewidths=1.6, alpha=0.9, zorder=4))
    if step < sim.shape[1] and sim.shape[-1] >= 4:
        at = np.flatnonzero(sim_valid[:, step] & np.isfinite(sim[:, step, 3]))
        if len(at):
            polys = box_corners(sim[at, step], extent[at])
            ax.add_collection(PolyCollection(polys, facecolors="none", edgecolors=SIM_COLOUR, linewidths=1.3,
                                             zorder=6))


def box_corners(states: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """Corners ``(N, 4, 2)`` of boxes centred at ``states[:, :2]`` with length along ``states[:, 3]`` (yaw)."""
    half = np.nan_to_num(extent, nan=0.0) / 2
    lx = half[:, :1] * np.array([1.0, 1.0, -1.0, -1.0])
    ly = half[:, 1:] * np.array([1.0, -1.0, -1.0, 1.0])
    return to_world(states, lx, ly)


def to_world(states: np.ndarray, lx: np.ndarray, ly: np.ndarray) -> np.ndarray:
    """Points ``(N, K, 2)`` at offsets ``(lx, ly)`` (``(N, K)``, m) in the frames of ``states`` ``(N, 4)``."""
    c, s = np.cos(states[:, 3])[:, None], np.sin(states[:, 3])[:, None]
    return np.stack([states[:, 0, None] + c * lx - s * ly, states[:, 1, None] + s * lx + c * ly], -1)


def _draw_boxes(ax: Axes, states: np.ndarray, extent: np.ndarray, colours: list[str]) -> None:
    """Filled oriented boxes with a white heading triangle at the front."""
    if not len(states):
        return
    ax.add_collection(PolyCollection(box_corners(states, extent), facecolors=colours, edgecolors="#202020",
                                     linewidths=0.7, alpha=0.95, zorder=5))
    half_l = np.nan_to_num(extent[:, 0], nan=0.0) / 2
    half_w = np.nan_to_num(extent[:, 1], nan=0.0) / 2
    back = half_l - np.minimum(0.4 * 2 * half_l, 1.6)
    lx = np.stack([half_l * 0.92, back, back], 1)
    ly = np.stack([np.zeros_like(half_w), 0.6 * half_w, -0.6 * half_w], 1)
    ax.add_collection(PolyCollection(to_world(states, lx, ly), facecolors="white", edgecolors="none",
                                     alpha=0.9, zorder=6))


def _default_title(scenario: ScenarioTensor, b: int, step: int) -> str:
    scene = scenario.scene_ids[b] if scenario.scene_ids and scenario.scene_ids[b] else f"scene {b}"
    prefix = f"{scenario.source} / " if scenario.source else ""
    t = (step - scenario.current_index) * scenario.dt
    return f"{prefix}{scene}: step {step}/{scenario.num_steps - 1} (t = {t:+.1f} s from 'now')"


def _legend(ax: Axes, agent_type: np.ndarray, controlled: np.ndarray, valid: np.ndarray, with_sim: bool) -> None:
    present = valid.any(-1)
    handles: list[Any] = []
    if (controlled & present).any():
        handles.append(Patch(facecolor=CONTROLLED_COLOUR, edgecolor="#202020", label="controlled"))
    for code in sorted({int(c) for c in agent_type[present & ~controlled]}):
        handles.append(Patch(facecolor=agent_colour(code, False), edgecolor="#202020",
                             label=f"replayed {_type_name(code)}"))
    handles += [Line2D([], [], color="#444444", lw=1.6, label="history"),
                Line2D([], [], color="#444444", lw=1.2, linestyle=(0, (4, 3)), label="logged future")]
    if with_sim:
        handles.append(Line2D([], [], color=SIM_COLOUR, lw=1.6, label="simulated"))
    ax.legend(handles=handles, loc="upper right", fontsize=7.5, framealpha=0.85)
