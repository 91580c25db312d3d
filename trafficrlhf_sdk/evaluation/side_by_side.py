"""Qualitative figures: models side by side in closed loop from the same logged start, on the scenes where the
first model (the base) fails.

Every model runs the evaluation protocol (:func:`~trafficrlhf_sdk.evaluation.runs.evaluate_seeds`, batched over
scenes) on the same scenes with the same seed; the scenes where a controlled agent of the base collides or leaves
the road are drawn, the most failing first. Per scene:

- an animated GIF, one panel per model over the same map crop: the logged history, every agent's box per frame
  and its simulated trail, controlled agents in blue, failing agents ringed in red from their first failure on
  (x: collision, o: off-road), each panel titled with the model and its failures so far, the time in the title;
- a PNG still at the base's first failure, with each model's whole simulated run drawn faintly.

``trafficrlhf render compare`` is :func:`render_side_by_side` plus printing. From Python::

    from trafficrlhf_sdk.evaluation.side_by_side import SideBySideRequest, panel_specs, render_side_by_side

    request = SideBySideRequest(panels=panel_specs(checkpoints=["ctg-4s", "ctg-baseline"]),
                                guidance="no_collision", num_scenes=100, worst=3)
    outcome = render_side_by_side(request, "out/compare")
    [(scene.scene_id, scene.animation, scene.still) for scene in outcome.scenes]

The parts work on policies and scenes you already hold: :func:`simulate_side_by_side` -> :class:`SideBySide`,
:func:`failing_scenes`, :func:`save_side_by_side_animation`, :func:`save_side_by_side_still`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.evaluation.failures import FirstFailures, first_failures
from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig
from trafficrlhf_sdk.evaluation.runs import SceneSelection, check_out_dir, evaluate_seeds
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.simulator import Rollout

__all__ = ["PanelSpec", "SceneFigure", "SideBySide", "SideBySideOutcome", "SideBySideRequest", "failing_scenes",
           "panel_specs", "render_side_by_side", "save_side_by_side_animation", "save_side_by_side_still",
           "side_by_side_frames", "simulate_side_by_side"]

FAILING_COLOUR = "#e3001b"
OK_COLOUR = "#1b7f3b"  # a panel title while its model has no failure
LEAD_IN_S = 1.0  # animations start this long before the closed loop does (the log leading in)
HOLD_LAST_S = 1.5  # the last frame of an animation stays this long before it loops
PANEL_INCHES = 4.6  # width of one panel; the layout around the panels, in inches:
GAP_INCHES, SIDE_INCHES, TOP_INCHES, LEGEND_ROW_INCHES = 0.12, 0.06, 0.78, 0.2
SUMMARY = "side_by_side.json"


# ------------------------------------------------------------------------------------------------ the request
class PanelSpec(BaseModel):
    """One model of the comparison: a registered model and/or a checkpoint, and its name on the panel."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    model: str | None = Field(None, description="Registered traffic model or built-in policy; None: the one "
                              "`checkpoint` was saved by.")
    checkpoint: str | None = Field(None, description="Weights: a folder, or a bundled checkpoint's name.")
    label: str | None = Field(None, description="Panel title; None: the checkpoint's name (a folder's base name) or "
                              "the model's.")

    @property
    def name(self) -> str:
        """The panel's title."""
        if self.label:
            return self.label
        if self.checkpoint:
            return os.path.basename(os.path.normpath(self.checkpoint)) or self.checkpoint
        return self.model or "model"


def panel_specs(models: Sequence[str] = (), checkpoints: Sequence[str] = ()) -> tuple[PanelSpec, ...]:
    """The panels of ``--model`` / ``--checkpoint`` options, base first: one per checkpoint (with the one model
    given for all of them, or the models paired in order), or one per model when no checkpoint is given."""
    models, checkpoints = list(models), list(checkpoints)
    if not checkpoints:
        if not models:
            raise TrafficRLHFError("no model to draw: pass --checkpoint twice or more (the base first), e.g. "
                                   "--checkpoint ctg-4s --checkpoint ctg-baseline, or --model NAME per panel.")
        return tuple(PanelSpec(model=m) for m in models)
    if len(models) not in (0, 1, len(checkpoints)):
        raise TrafficRLHFError(f"--model was given {len(models)} times ({', '.join(models)}) for {len(checkpoints)} "
                               f"--checkpoint values; give --model once (for all), once per --checkpoint (in the "
                               "same order), or not at all (each checkpoint names its model).")
    paired = models * len(checkpoints) if len(models) == 1 else models or [None] * len(checkpoints)
    return tuple(PanelSpec(model=m, checkpoint=c) for m, c in zip(paired, checkpoints))


class SideBySideRequest(SceneSelection):
    """Everything :func:`render_side_by_side` needs: the models, the scenes, the protocol and the drawing."""

    panels: tuple[PanelSpec, ...] = Field(min_length=1, description="The models, the base first (its failures "
                                          "choose the scenes).")
    guidance: str | None = Field(None, description="Guidance for every model that supports it; None keeps the one "
                                 "a bundled checkpoint's card was measured with, 'none' turns it off.")
    model_options: dict[str, Any] = Field(default_factory=dict, description="Other options for every model.")
    scene_ids: tuple[str, ...] = Field((), description="Simulate and draw exactly these scenes (failing or not), "
                                       "in this order; overrides `num_scenes` and `worst`.")
    worst: int = Field(3, ge=1, description="Draw at most this many of the scenes where the base fails.")
    seed: int = Field(0, description="The seed of every model's run (the same start, the same seed).")
    frame_hz: float = Field(5.0, ge=0.5, le=10.0, description="Animation frames per simulated second.")
    speed: float = Field(1.0, gt=0.0, le=10.0, description="Playback speed (1: real time).")
    dpi: int = Field(100, ge=40, le=300, description="Resolution of the animations and stills.")


# --------------------------------------------------------------------------------------------- simulation
@dataclass
class SideBySide:
    """Closed-loop runs of several models on the same scenes from the same start with the same seed.

    Fields: ``labels`` (one per model, the base first), ``rollouts`` (one :class:`Rollout` per model, scenes in
    the same order), ``failures`` (each rollout's :class:`FirstFailures`), ``failure_rates`` (each model's failure
    rate over the scenes), ``seed``, ``note`` (e.g. the guidance, shown in the figures' titles).
    """

    labels: list[str]
    rollouts: list[Rollout]
    failures: list[FirstFailures]
    failure_rates: list[float]
    seed: int = 0
    note: str = ""

    @property
    def num_scenes(self) -> int:
        """Scenes in every rollout."""
        return self.rollouts[0].simulated.num_scenes

    def scene_id(self, index: int) -> str:
        """The name of scene ``index`` (``scene <index>`` when the scenes have none)."""
        ids = self.rollouts[0].logged.scene_ids
        return str(ids[index]) if ids and ids[index] else f"scene {index}"

    def failing_agents(self, model: int, index: int) -> int:
        """How many controlled agents of ``model`` fail in scene ``index``."""
        return int((self.failures[model].step[index] >= 0).sum())

    def scenes_failing(self, model: int) -> int:
        """In how many scenes a controlled agent of ``model`` fails."""
        return int((self.failures[model].step >= 0).any(-1).sum())

    def first_failure(self, model: int, index: int) -> int | None:
        """The first step at which a controlled agent of ``model`` fails in scene ``index`` (None: none fails)."""
        steps = self.failures[model].step[index]
        return int(steps[steps >= 0].min()) if bool((steps >= 0).any()) else None


def simulate_side_by_side(policies: Sequence[Any], scenario: ScenarioTensor, labels: Sequence[str],
                          seed: int = 0, config: EvaluationConfig | None = None, progress: bool = False,
                          log: Callable[[str], None] | None = None, note: str = "") -> SideBySide:
    """Run each policy in closed loop on ``scenario`` with the same ``seed`` (the evaluation protocol).

    Args:
        policies: the models, the base first; each a policy, or a function of the seed that builds one (built
            when its turn comes, so only one model is in memory at a time).
        scenario: the logged scenes ``(B, A, T)``.
        labels: one name per policy (the panels' titles).
        seed: the seed of every run.
        config: the protocol (batch size, simulation); only the failure metric is computed.
        progress: show the simulation's progress bars; ``log`` hears which model runs.
        note: a line for the figures' titles (e.g. the guidance).
    """
    if len(labels) != len(policies):
        raise ValueError(f"`labels` has {len(labels)} names for {len(policies)} policies; give one per policy.")
    config = (config or EvaluationConfig()).model_copy(update={"metrics": ("failure",), "rollouts": 1, "meta": None})
    rollouts, failures, rates = [], [], []
    for k, (policy, label) in enumerate(zip(policies, labels)):
        if log is not None:
            log(f"simulating {label} ({k + 1}/{len(policies)}) on {scenario.num_scenes} scenes, seed {seed}")
        build = policy if callable(policy) and not hasattr(policy, "plan") else (lambda _seed, p=policy: p)
        report = evaluate_seeds(build, scenario, [seed], config, progress=progress).reports[0]
        assert report.rollout is not None
        rollouts.append(report.rollout)
        failures.append(first_failures(report.rollout))
        rates.append(float(report.values.get("failure_rate", float("nan"))))
    return SideBySide(list(labels), rollouts, failures, rates, seed, note)


def failing_scenes(runs: SideBySide, top: int | None = None) -> list[int]:
    """Indices of the scenes where a controlled agent of the base (the first model) fails, the most failing agents
    first; ties go to the scenes where the other models fail least, then to the earliest failure. ``top`` keeps
    that many."""
    keyed = []
    for b in range(runs.num_scenes):
        failing = runs.failing_agents(0, b)
        if failing:
            others = sum(runs.failing_agents(m, b) for m in range(1, len(runs.rollouts)))
            keyed.append((-failing, others, runs.first_failure(0, b), b))
    return [key[-1] for key in sorted(keyed)][:top]


# ---------------------------------------------------------------------------------------------------- drawing
class _Panels:
    """One figure of one panel per model over the same view; the moving parts are redrawn per frame."""

    def __init__(self, runs: SideBySide, index: int, dpi: int, faint_runs: bool = False) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        from trafficrlhf_sdk.render import BACKGROUND_RGB, agent_colour, draw_map, hex_colour, view_box

        self.runs, self.index = runs, index
        first = runs.rollouts[0]
        logged = first.logged
        self.start, self.end, self.dt = first.start_index, first.end_index, logged.dt
        self.extent = logged.extent[index].double().numpy()
        self.log_states = logged.states[index].double().numpy()
        self.log_valid = logged.valid[index].numpy().copy()
        self.log_valid[:, self.start + 1:] = False  # the log's history only
        self.sims = [(r.simulated.states[index].double().numpy(), r.simulated.valid[index].numpy())
                     for r in runs.rollouts]
        self.controlled = [r.controlled[index].numpy() for r in runs.rollouts]
        self.steps = [f.step[index].numpy() for f in runs.failures]
        self.kinds = [(f.collision[index].numpy(), f.offroad[index].numpy()) for f in runs.failures]
        agent_type = logged.agent_type[index].numpy()
        self.colours = [[agent_colour(int(agent_type[a]), bool(c[a])) for a in range(len(c))]
                        for c in self.controlled]
        focus = np.zeros(len(self.extent), bool)
        for c in self.controlled:
            focus |= c
        if not focus.any():
            focus[:] = True
        states = np.concatenate([self.log_states[focus]] + [s[focus] for s, _ in self.sims])
        valid = np.concatenate([self.log_valid[focus]] + [v[focus] for _, v in self.sims])
        self.view = view_box(states, valid, None, None, logged.map, index)
        ratio = (self.view[3] - self.view[2]) / (self.view[1] - self.view[0])
        # a fixed layout (inches), the same in every frame: title band, one row of panels, legend band
        n, panel_h = len(runs.rollouts), PANEL_INCHES * ratio
        handles = self._legend_handles(faint_runs)
        columns = min(len(handles), 4 if n == 1 else 7)
        bottom = 0.14 + LEGEND_ROW_INCHES * -(-len(handles) // columns)
        width = n * PANEL_INCHES + (n - 1) * GAP_INCHES + 2 * SIDE_INCHES
        height = TOP_INCHES + panel_h + bottom
        self.fig = Figure(figsize=(width, height), dpi=dpi)
        FigureCanvasAgg(self.fig)
        self.axes = [self.fig.add_axes(((SIDE_INCHES + m * (PANEL_INCHES + GAP_INCHES)) / width, bottom / height,
                                        PANEL_INCHES / width, panel_h / height)) for m in range(n)]
        self.fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.02 / height), ncol=columns,
                        fontsize=8, frameon=False, handlelength=1.8, columnspacing=1.4)
        self._suptitle_y = 1.0 - 0.1 / height
        for m, ax in enumerate(self.axes):
            ax.set_facecolor(hex_colour(BACKGROUND_RGB))
            if logged.map is not None:
                draw_map(ax, logged.map, index, self.view)
            self._trails(ax, self.log_states, self.log_valid, self.colours[m], 0, self.start, width=1.3, alpha=0.55,
                         style=(0, (3, 2)))
            if faint_runs:
                sim, valid = self.sims[m]
                self._trails(ax, sim, valid, self.colours[m], self.start, self.end, width=1.0, alpha=0.28)
            ax.set_xlim(self.view[0], self.view[1])
            ax.set_ylim(self.view[2], self.view[3])
            ax.set_aspect("equal", adjustable="box")
            ax.set_xticks([])
            ax.set_yticks([])
        self._artists: list[Any] = []

    @staticmethod
    def _trails(ax: Any, states: np.ndarray, valid: np.ndarray, colours: list[str], t0: int, t1: int,
                width: float, alpha: float, style: Any = "-") -> list[Any]:
        from matplotlib.collections import LineCollection

        from trafficrlhf_sdk.render import valid_runs

        segments, seg_colours = [], []
        for a in range(len(states)):
            for run in valid_runs(states[a, t0 : t1 + 1, :2], valid[a, t0 : t1 + 1]):
                segments.append(run)
                seg_colours.append(colours[a])
        if not segments:
            return []
        return [ax.add_collection(LineCollection(segments, colors=seg_colours, linewidths=width, alpha=alpha,
                                                 linestyles=style, zorder=3, capstyle="round"))]

    def _legend_handles(self, faint_runs: bool) -> list[Any]:
        from matplotlib.lines import Line2D
        from matplotlib.patches import Patch

        from trafficrlhf_sdk.render import CONTROLLED_COLOUR, agent_colour
        from trafficrlhf_sdk.scenario.agents import AgentType

        logged = self.runs.rollouts[0].logged
        present = self.log_valid.any(-1)
        replayed = present & ~np.logical_or.reduce(self.controlled)
        handles: list[Any] = [Patch(facecolor=CONTROLLED_COLOUR, edgecolor="#202020", label="driven by the model")]
        for code in sorted({int(c) for c in logged.agent_type[self.index].numpy()[replayed]}):
            try:
                name = AgentType(code).name.lower()
            except ValueError:
                name = "other"
            handles.append(Patch(facecolor=agent_colour(code, False), edgecolor="#202020", label=f"replayed {name}"))
        handles += [
            Line2D([], [], color="#555555", lw=1.3, linestyle=(0, (3, 2)), label="logged history"),
            Line2D([], [], color="#555555", lw=1.6, label="simulated"),
            Line2D([], [], color=FAILING_COLOUR, marker="o", markersize=9, markerfacecolor=(0.89, 0.0, 0.1, 0.2),
                   lw=0, label="failing agent"),
            Line2D([], [], color=FAILING_COLOUR, marker="x", markersize=7, markeredgewidth=2, lw=0,
                   label="collision"),
            Line2D([], [], color=FAILING_COLOUR, marker="o", markersize=7, markerfacecolor="none",
                   markeredgewidth=2, lw=0, label="off-road"),
        ]
        if faint_runs:
            handles.append(Line2D([], [], color="#555555", lw=1.0, alpha=0.35, label="whole simulated run"))
        return handles

    def _title(self, m: int, step: int) -> tuple[str, str]:
        controlled = int(self.controlled[m].sum())
        failed = (self.steps[m] >= 0) & (self.steps[m] <= step)
        collisions = int((failed & self.kinds[m][0]).sum())
        offroad = int((failed & self.kinds[m][1]).sum())
        count = int(failed.sum())
        if not count:
            return f"{self.runs.labels[m]}\nno failure so far ({controlled} driven)", OK_COLOUR
        kinds = ", ".join(part for part in (f"{collisions} collision{'s' if collisions > 1 else ''}" if collisions
                                            else "", f"{offroad} off-road" if offroad else "") if part)
        return f"{self.runs.labels[m]}\n{count} of {controlled} driven failed ({kinds})", FAILING_COLOUR

    def draw(self, step: int, caption: str = "") -> None:
        """Draw every panel at absolute time step ``step``."""
        from matplotlib.collections import PolyCollection

        from trafficrlhf_sdk.render import box_corners, to_world

        for artist in self._artists:
            artist.remove()
        self._artists = []
        for m, ax in enumerate(self.axes):
            sim, valid = self.sims[m]
            colours = self.colours[m]
            if step > self.start:
                self._artists += self._trails(ax, sim, valid, colours, self.start, step, width=1.6, alpha=0.9)
            at = np.flatnonzero(valid[:, step])
            if len(at):
                self._artists.append(ax.add_collection(PolyCollection(
                    box_corners(sim[at, step], self.extent[at]), facecolors=[colours[a] for a in at],
                    edgecolors="#202020", linewidths=0.6, zorder=5)))
                half_l = np.nan_to_num(self.extent[at, 0]) / 2
                back = half_l - np.minimum(0.8 * half_l, 1.6)
                lx = np.stack([half_l * 0.92, back, back], 1)
                half_w = np.nan_to_num(self.extent[at, 1]) / 2
                ly = np.stack([np.zeros_like(half_w), 0.6 * half_w, -0.6 * half_w], 1)
                self._artists.append(ax.add_collection(PolyCollection(to_world(sim[at, step], lx, ly),
                                                                      facecolors="white", alpha=0.9, zorder=6)))
            self._failures(ax, m, step)
            title, colour = self._title(m, step)
            ax.set_title(title, fontsize=10, color=colour, pad=4)
        t = (step - self.start) * self.dt
        when = " (the log, before the closed loop)" if step < self.start else ""
        self.fig.suptitle("   ·   ".join([f"{self.runs.scene_id(self.index)}", f"t = {t:+.1f} s{when}"]
                                         + ([caption] if caption else [])), fontsize=11, y=self._suptitle_y, va="top")

    def _failures(self, ax: Any, m: int, step: int) -> None:
        """Rings around agents that have failed by ``step`` (where they are now) and marks where they first did."""
        from matplotlib.patches import Circle

        sim, valid = self.sims[m]
        for a in np.flatnonzero((self.steps[m] >= 0) & (self.steps[m] <= step)):
            first = int(self.steps[m][a])
            radius = 0.5 * float(np.nan_to_num(self.extent[a]).max()) + 1.6
            if valid[a, step]:
                self._artists.append(ax.add_patch(Circle((sim[a, step, 0], sim[a, step, 1]), radius,
                                                         facecolor=(0.89, 0.0, 0.1, 0.18),
                                                         edgecolor=FAILING_COLOUR, linewidth=1.6, zorder=7)))
            collided = bool(self.kinds[m][0][a])
            (mark,) = ax.plot([sim[a, first, 0]], [sim[a, first, 1]], marker="x" if collided else "o",
                              markersize=9, markeredgewidth=2.2, color=FAILING_COLOUR, markerfacecolor="none",
                              zorder=9, linestyle="none")
            self._artists.append(mark)

    def rgb(self) -> np.ndarray:
        """The figure as an ``(H, W, 3)`` uint8 array."""
        canvas = self.fig.canvas
        canvas.draw()  # type: ignore[attr-defined]
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()  # type: ignore[attr-defined]


def _frame_steps(runs: SideBySide, frame_hz: float) -> list[int]:
    rollout = runs.rollouts[0]
    dt = rollout.logged.dt
    every = max(1, round(1.0 / (frame_hz * dt)))
    first = max(0, rollout.start_index - round(LEAD_IN_S / dt))
    steps = list(range(first, rollout.end_index + 1, every))
    if steps[-1] != rollout.end_index:
        steps.append(rollout.end_index)
    return steps


def side_by_side_frames(runs: SideBySide, index: int, frame_hz: float = 5.0, dpi: int = 100) -> list[np.ndarray]:
    """RGB frames ``(H, W, 3)`` of scene ``index``: from 1 s before the closed loop starts to its end,
    ``frame_hz`` frames per simulated second (the last step always included)."""
    _check_scene(runs, index)
    panels = _Panels(runs, index, dpi)
    steps = _frame_steps(runs, frame_hz)
    caption = runs.note
    frames = []
    for step in steps:
        panels.draw(step, caption)
        frames.append(panels.rgb())
    return frames


def save_side_by_side_animation(runs: SideBySide, index: int, path: str | os.PathLike[str], frame_hz: float = 5.0,
                                speed: float = 1.0, dpi: int = 100) -> str:
    """Write scene ``index`` as an animated GIF (:func:`side_by_side_frames`, real time at ``speed`` 1, the last
    frame held 1.5 s, looping); returns the path."""
    path = os.fspath(path)
    if os.path.splitext(path)[1].lower() != ".gif":
        raise ValueError(f"animation `path` must end in .gif; got {path!r}.")
    if speed <= 0:
        raise ValueError(f"`speed` must be positive; got {speed!r}.")
    frames = side_by_side_frames(runs, index, frame_hz, dpi)
    steps = _frame_steps(runs, frame_hz)
    dt = runs.rollouts[0].logged.dt
    durations = [round(1000 * (b - a) * dt / speed) for a, b in zip(steps, steps[1:])]
    durations.append(round(1000 * HOLD_LAST_S))
    palette = _gif_palette([frames[0], frames[len(frames) // 2], frames[-1]])
    images = [_indexed(f, palette) for f in frames]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=durations, loop=0, optimize=True)
    return path


def _gif_palette(frames: list[np.ndarray], size: int = 64) -> np.ndarray:
    """One palette for every frame: the colours that must stay exact (white, text, the failure red, the titles'
    green, the agents' and the map's colours), however few pixels use them, then the commonest others of a few
    frames (anti-aliased edges, translucent trails); ``(size, 3)`` uint8."""
    from PIL import Image

    from trafficrlhf_sdk.render import BACKGROUND_RGB, CONTROLLED_COLOUR, MAP_LAYER_RGB, REPLAYED_COLOURS

    named = ["#ffffff", "#000000", "#202020", FAILING_COLOUR, OK_COLOUR, CONTROLLED_COLOUR, *REPLAYED_COLOURS.values()]
    exact = [tuple(int(c[i : i + 2], 16) for i in (1, 3, 5)) for c in named] + [BACKGROUND_RGB, *MAP_LAYER_RGB.values()]
    exact = list(dict.fromkeys(exact))
    adaptive = Image.fromarray(np.concatenate(frames, 0)).quantize(colors=size - len(exact),
                                                                   method=Image.Quantize.MEDIANCUT)
    rest = np.array(adaptive.getpalette()[: 3 * (size - len(exact))], np.uint8).reshape(-1, 3)
    return np.concatenate([np.array(exact, np.uint8), rest])


def _indexed(frame: np.ndarray, palette: np.ndarray) -> Any:
    """``frame`` as a "P" image on ``palette``, each colour mapped to its nearest entry (computed once per
    distinct colour: exact colours stay exact, which Pillow's own palette mapping does not guarantee)."""
    from PIL import Image

    packed = (frame.astype(np.int32) << np.array([16, 8, 0])).sum(-1)
    colours, inverse = np.unique(packed, return_inverse=True)
    rgb = np.stack([(colours >> 16) & 255, (colours >> 8) & 255, colours & 255], -1)
    nearest = ((rgb[:, None, :] - palette[None].astype(np.int32)) ** 2).sum(-1).argmin(1).astype(np.uint8)
    image = Image.fromarray(nearest[inverse.reshape(frame.shape[:2])], mode="P")
    image.putpalette(palette.flatten().tolist())
    return image


def save_side_by_side_still(runs: SideBySide, index: int, path: str | os.PathLike[str], step: int | None = None,
                            dpi: int = 110) -> str:
    """Write a PNG of scene ``index`` at ``step`` (default: the base's first failure, else the last step), each
    model's whole simulated run drawn faintly under its run so far; returns the path."""
    _check_scene(runs, index)
    rollout = runs.rollouts[0]
    first = runs.first_failure(0, index)
    if step is None:
        step = first if first is not None else rollout.end_index
    if not 0 <= step <= rollout.end_index:
        raise ValueError(f"`step` must be in 0..{rollout.end_index}; got {step}.")
    panels = _Panels(runs, index, dpi, faint_runs=True)
    parts = (["the base's first failure"] if step == first else []) + ([runs.note] if runs.note else [])
    caption = "   ·   ".join(parts)
    panels.draw(step, caption)
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    panels.fig.savefig(path, dpi=dpi, format="png", facecolor="white")
    return path


def _check_scene(runs: SideBySide, index: int) -> None:
    if not 0 <= index < runs.num_scenes:
        raise ValueError(f"scene `index` {index} is out of range for {runs.num_scenes} scenes.")


# ----------------------------------------------------------------------------------------------- end to end
@dataclass
class SceneFigure:
    """The files drawn for one scene: its rank, name and index, each model's failing agents, the GIF and PNG."""

    rank: int
    scene_id: str
    index: int
    failing_agents: list[int]
    animation: str
    still: str


@dataclass
class SideBySideOutcome:
    """What :func:`render_side_by_side` made: the runs, the scenes drawn (most failing first) and the summary."""

    runs: SideBySide
    scenes: list[SceneFigure] = field(default_factory=list)
    summary: str | None = None


def render_side_by_side(request: SideBySideRequest, out_dir: str, log: Callable[[str], None] | None = None,
                        progress: bool = True) -> SideBySideOutcome:
    """Simulate every model of ``request`` on the same scenes from the same start with the same seed, choose the
    scenes where the base fails (the most failing first, at most ``request.worst``; or ``request.scene_ids`` as
    given) and write ``out_dir/<rank>_<scene>.gif`` and ``.png`` per scene plus ``side_by_side.json`` (models,
    seed, failure rates, the scenes and their failing agents). Every model is built before any data is read, so a
    bad name or option fails at once; ``log`` hears the progress."""
    from trafficrlhf_sdk.plugins import build_policy

    check_out_dir(out_dir)
    say = log or (lambda _line: None)

    # every model is built first: a wrong name, checkpoint or option fails before any data is read
    policies = [build_policy(panel.model, {**request.model_options, "guidance": request.guidance,
                                           "checkpoint": panel.checkpoint, "seed": request.seed})
                for panel in request.panels]
    labels = _unique([panel.name for panel in request.panels])
    scenario, _ = request.load(say)
    config = EvaluationConfig(simulation=request.simulation, batch_size=request.batch_size)
    note = f"seed {request.seed}" + (f", guidance {request.guidance}" if request.guidance else "")
    runs = simulate_side_by_side(policies, scenario, labels, request.seed, config, progress, say, note)
    chosen = list(range(runs.num_scenes)) if request.scene_ids else failing_scenes(runs, request.worst)
    if not chosen:
        say(f"{labels[0]} fails in none of the {runs.num_scenes} scenes (seed {request.seed}); nothing to draw. "
            "Raise --scenes or try another --seed.")
    outcome = SideBySideOutcome(runs)
    for rank, index in enumerate(chosen, start=1):
        name = runs.scene_id(index)
        say(f"drawing {name} ({rank}/{len(chosen)}): {labels[0]} fails with {runs.failing_agents(0, index)} agents")
        stem = os.path.join(out_dir, f"{rank:02d}_{name}")
        outcome.scenes.append(SceneFigure(
            rank, name, index, [runs.failing_agents(m, index) for m in range(len(labels))],
            save_side_by_side_animation(runs, index, stem + ".gif", request.frame_hz, request.speed, request.dpi),
            save_side_by_side_still(runs, index, stem + ".png", dpi=request.dpi)))
    outcome.summary = _write_summary(request, runs, outcome.scenes, out_dir)
    return outcome


def _unique(labels: list[str]) -> list[str]:
    """Labels made distinct by a suffix (`ctg`, `ctg (2)`)."""
    out: list[str] = []
    for label in labels:
        out.append(label if label not in out else f"{label} ({len(out) + 1})")
    return out


def _write_summary(request: SideBySideRequest, runs: SideBySide, scenes: list[SceneFigure], out_dir: str) -> str:
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, SUMMARY)
    ids = [runs.scene_id(b) for b in range(runs.num_scenes)]
    summary = {
        "models": [{"label": label, **panel.model_dump(exclude={"label"}), "failure_rate": rate,
                    "scenes_failing": runs.scenes_failing(m)}
                   for m, (label, panel, rate) in enumerate(zip(runs.labels, request.panels, runs.failure_rates))],
        "guidance": request.guidance, "seed": request.seed, "source": request.source, "split": request.split,
        "scene_ids": ids,
        "drawn": [{"rank": s.rank, "scene_id": s.scene_id, "failing_agents": dict(zip(runs.labels, s.failing_agents)),
                   "controlled_agents": int(runs.rollouts[0].controlled[s.index].sum()),
                   "animation": os.path.basename(s.animation), "still": os.path.basename(s.still)} for s in scenes],
    }
    with open(path, "w", encoding="utf-8") as handle:
        json.dump(summary, handle, indent=2)
    return path
