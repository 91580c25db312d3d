"""Pictures of a candidate set for sharing: a PNG strip (the N candidates side by side at one moment) and an
animation (GIF through Pillow; MP4 when ``imageio`` and ``imageio-ffmpeg`` are installed).

Panels show the candidates in storage order (candidate 1..N), optionally followed by the logged future, over
the same map crop and the same view, with labeled vehicle boxes (a white triangle marks the front) and trails
of the last 3 s. Built on matplotlib's Agg canvas (no window, no global backend change).
"""

from __future__ import annotations

import io
import os
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure

from trafficrlhf_sdk.feedback.store import ContextRecord
from trafficrlhf_sdk.render import (
    BACKGROUND_RGB,
    CONTROLLED_COLOUR,
    agent_colour,
    box_corners,
    draw_map,
    hex_colour,
    short_id,
    to_world,
    valid_runs,
    view_box,
)

__all__ = ["candidate_frames", "save_candidate_animation", "save_candidate_strip"]

TRAIL_S = 3.0  # seconds of trail behind each vehicle
HISTORY_SHOWN_S = 1.0  # animations start this long before the candidates do


def _panels(record: ContextRecord, include_logged: bool) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(title, states (A, T, 4), valid (A, T)) per panel: history + each candidate's future."""
    out = []
    for k in list(range(record.num_candidates)) + ([None] if include_logged else []):
        scene = record.candidate_scenario(k)
        title = "logged future" if k is None else f"candidate {k + 1}"
        out.append((title, scene.states[0].double().numpy(), scene.valid[0].numpy()))
    return out


class _Strip:
    """A figure of one row of panels whose moving parts are redrawn per frame."""

    def __init__(self, record: ContextRecord, include_logged: bool, panel_inches: float = 3.6) -> None:
        self.record = record
        self.panels = _panels(record, include_logged)
        scenario = record.scenario
        self.extent = scenario.extent[0].double().numpy()
        self.ids = scenario.agent_ids[0] if scenario.agent_ids else tuple(str(a) for a in range(scenario.num_agents))
        controlled = scenario.controlled[0].numpy()
        self.colours = [agent_colour(int(t), bool(c)) for t, c in zip(scenario.agent_type[0].numpy(), controlled)]
        all_states = np.concatenate([p[1] for p in self.panels], 0)
        all_valid = np.concatenate([p[2] for p in self.panels], 0)
        view = view_box(all_states, all_valid, None, None, scenario.map, 0)
        ratio = (view[3] - view[2]) / (view[1] - view[0])
        n = len(self.panels)
        self.fig = Figure(figsize=(panel_inches * n, panel_inches * ratio + 0.5), dpi=100, layout="constrained")
        FigureCanvasAgg(self.fig)
        self.axes = self.fig.subplots(1, n, squeeze=False)[0]
        for ax, (title, _, _) in zip(self.axes, self.panels):
            ax.set_facecolor(hex_colour(BACKGROUND_RGB))
            if scenario.map is not None:
                draw_map(ax, scenario.map, 0, view)
            ax.set_xlim(view[0], view[1])
            ax.set_ylim(view[2], view[3])
            ax.set_aspect("equal", adjustable="box")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(title, fontsize=11, color=CONTROLLED_COLOUR if title.startswith("cand") else "#333333")
        self._artists: list[Any] = []
        self.trail_steps = round(TRAIL_S / scenario.dt)

    def draw(self, step: int) -> None:
        """Draw every panel at time step ``step`` (index into history + future)."""
        for artist in self._artists:
            artist.remove()
        self._artists = []
        t0 = max(0, step - self.trail_steps)
        dt = self.record.scenario.dt
        now = self.record.scenario.current_index
        for ax, (_, states, valid) in zip(self.axes, self.panels):
            segments, seg_colours = [], []
            for a in range(len(states)):
                for run in valid_runs(states[a, t0 : step + 1, :2], valid[a, t0 : step + 1]):
                    segments.append(run)
                    seg_colours.append(self.colours[a])
            if segments:
                self._artists.append(ax.add_collection(LineCollection(segments, colors=seg_colours, linewidths=1.5,
                                                                      alpha=0.8, zorder=3)))
            at = np.flatnonzero(valid[:, step])
            if len(at):
                boxes = box_corners(states[at, step], self.extent[at])
                self._artists.append(ax.add_collection(PolyCollection(
                    boxes, facecolors=[self.colours[a] for a in at], edgecolors="#202020", linewidths=0.7, zorder=5)))
                half_l = self.extent[at, 0] / 2
                back = half_l - np.minimum(0.8 * half_l, 1.6)
                lx = np.stack([half_l * 0.92, back, back], 1)
                ly = np.stack([np.zeros_like(half_l), 0.3 * self.extent[at, 1], -0.3 * self.extent[at, 1]], 1)
                self._artists.append(ax.add_collection(PolyCollection(to_world(states[at, step], lx, ly),
                                                                      facecolors="white", zorder=6)))
                tops = boxes[..., 1].max(-1)
                for a, top in zip(at, tops):
                    self._artists.append(ax.annotate(
                        short_id(self.ids[a] or str(a)), (states[a, step, 0], top), xytext=(0, 2),
                        textcoords="offset points", ha="center", va="bottom", fontsize=6.5, zorder=8,
                        bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7}))
            self._artists.append(ax.text(0.02, 0.02, f"t = {(step - now) * dt:+.1f} s", transform=ax.transAxes,
                                         fontsize=8, zorder=9, bbox={"fc": "white", "ec": "none", "alpha": 0.8}))

    def rgb(self) -> np.ndarray:
        """The figure as an ``(H, W, 3)`` uint8 array."""
        canvas = self.fig.canvas
        canvas.draw()  # type: ignore[attr-defined]
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()  # type: ignore[attr-defined]


def _last_step(record: ContextRecord) -> int:
    return record.scenario.current_index + int(record.candidates.shape[2])


def _default_step(record: ContextRecord) -> int:
    """The latest step at which as many agents are present as at any step of the candidates (agents whose log
    ends leave replayed scenes early, and a strip of empty roads says little)."""
    present = record.candidate_valid.sum(1).min(0).values  # (H,): agents present in every candidate
    best = int(present.max())
    last = max(h for h in range(len(present)) if int(present[h]) == best)
    return record.scenario.current_index + 1 + last


def save_candidate_strip(record: ContextRecord, path: str | os.PathLike[str], step: int | None = None,
                         include_logged: bool = False, dpi: int = 110) -> str:
    """Write a PNG of the N candidates side by side at ``step`` (default: the latest step with every agent
    present) with 3 s trails; returns the path."""
    strip = _Strip(record, include_logged)
    strip.draw(_default_step(record) if step is None else int(np.clip(step, 0, _last_step(record))))
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    strip.fig.savefig(path, dpi=dpi, format="png", facecolor="white")
    return path


def candidate_frames(record: ContextRecord, every: int = 2, include_logged: bool = False) -> list[np.ndarray]:
    """RGB frames ``(H, W, 3)`` from 1 s before the candidates start to their end, one per ``every`` steps."""
    strip = _Strip(record, include_logged)
    now = record.scenario.current_index
    first = max(0, now - round(HISTORY_SHOWN_S / record.scenario.dt))
    last = now + record.candidates.shape[2]
    frames = []
    for step in range(first, last + 1, max(1, every)):
        strip.draw(step)
        frames.append(strip.rgb())
    return frames


def save_candidate_animation(record: ContextRecord, path: str | os.PathLike[str], every: int = 2,
                             include_logged: bool = False, speed: float = 1.0) -> str:
    """Write the candidate set as an animated ``.gif`` or ``.mp4`` (real time at ``speed`` 1); returns the path."""
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".gif", ".mp4"):
        raise ValueError(f"animation `path` must end in .gif or .mp4; got {path!r}.")
    if speed <= 0:
        raise ValueError(f"`speed` must be positive; got {speed!r}.")
    frames = candidate_frames(record, every, include_logged)
    frame_s = every * record.scenario.dt / speed
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if ext == ".gif":
        from PIL import Image

        images = [Image.fromarray(f).quantize(colors=128, method=Image.Quantize.MEDIANCUT) for f in frames]
        images[0].save(path, save_all=True, append_images=images[1:], duration=round(frame_s * 1000), loop=0,
                       optimize=False)
        return path
    try:
        import imageio.v2 as imageio
    except ImportError as exc:
        raise ImportError("MP4 output needs `imageio` and `imageio-ffmpeg` (pip install imageio imageio-ffmpeg); "
                          "or write a .gif instead.") from exc
    even = [f[: f.shape[0] // 2 * 2, : f.shape[1] // 2 * 2] for f in frames]  # yuv420p needs even sizes
    imageio.mimwrite(path, even, fps=1.0 / frame_s, codec="libx264", quality=8, macro_block_size=2)
    return path


def png_bytes(record: ContextRecord, step: int | None = None) -> bytes:
    """The strip of :func:`save_candidate_strip` as PNG bytes."""
    strip = _Strip(record, False)
    strip.draw(_default_step(record) if step is None else step)
    buffer = io.BytesIO()
    strip.fig.savefig(buffer, format="png", facecolor="white")
    return buffer.getvalue()
