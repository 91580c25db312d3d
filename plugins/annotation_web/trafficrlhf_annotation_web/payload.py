"""What the page receives for one item: a north-up map image, the agents, the shared history and the N
candidate futures, all in a local metric frame centred on the view (so the numbers stay small).

The logged future is never sent, nor whether an item is a gold item, nor which model made which candidate.
Candidates are listed in the annotator's display order (slot 1..N), so the page never learns the candidate
indices behind the slots. ``view`` is the whole area (the map image covers it); ``focus`` is the default view:
the controlled agents over the shown history and every candidate future, plus a margin.
"""

from __future__ import annotations

import base64
import io
from typing import Any

import numpy as np
import torch
from PIL import Image

from trafficrlhf_sdk.feedback.store import Assignment, ContextRecord
from trafficrlhf_sdk.scenario.agents import AgentType

__all__ = ["item_base", "item_payload", "map_image", "playback_seconds"]

HISTORY_SHOWN_S = 2.0  # history played before the candidates start (s)
VIEW_MARGIN_M = 12.0
FOCUS_MARGIN_M = 6.0  # around the controlled agents and their futures in the default view
FOCUS_MIN_M = 30.0  # the default view spans at least this much in each direction
MAP_PX_PER_M = 4.0
MAX_MAP_PX = 1400
LAYER_RGB = (("drivable", (205, 205, 205)), ("lane_divider", (255, 255, 255)), ("road_divider", (236, 192, 52)))
BACKGROUND_RGB = (241, 239, 232)


def map_image(record: ContextRecord, view: tuple[float, float, float, float]) -> str | None:
    """A PNG data URL of the map under ``view = (x0, x1, y0, y1)`` (scene-frame m), north up (+y at the top),
    resampled (nearest) from the raster through its world-to-pixel transform, so any raster orientation works."""
    scene_map = record.scenario.map
    if scene_map is None:
        return None
    x0, x1, y0, y1 = view
    res = min(MAP_PX_PER_M, MAX_MAP_PX / max(x1 - x0, y1 - y0))
    w, h = max(1, int((x1 - x0) * res)), max(1, int((y1 - y0) * res))
    xs = x0 + (np.arange(w) + 0.5) / res
    ys = y1 - (np.arange(h) + 0.5) / res
    grid = np.stack(np.meshgrid(xs, ys), -1).reshape(1, -1, 2)  # (1, h*w, 2), rows top to bottom
    rgb = np.empty((h * w, 3), np.uint8)
    rgb[:] = BACKGROUND_RGB
    points = torch.from_numpy(grid)
    for layer, colour in LAYER_RGB:
        if layer in scene_map.layers:
            on = scene_map.lookup(points, layer)[0].numpy()
            rgb[on] = colour
    buffer = io.BytesIO()
    Image.fromarray(rgb.reshape(h, w, 3)).save(buffer, format="PNG", optimize=True)
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


def _track(states: torch.Tensor, valid: torch.Tensor, centre: tuple[float, float]) -> dict[str, Any]:
    """Per agent lists ``x, y, yaw`` (rounded) and ``valid`` (0/1) over time from ``(A, T, 4)``, ``(A, T)``."""
    s = states.double().numpy()
    ok = valid.numpy()
    x = np.where(ok, np.round(s[..., 0] - centre[0], 2), 0.0)
    y = np.where(ok, np.round(s[..., 1] - centre[1], 2), 0.0)
    yaw = np.where(ok, np.round(s[..., 3], 3), 0.0)
    return {"x": x.tolist(), "y": y.tolist(), "yaw": yaw.tolist(), "valid": ok.astype(int).tolist()}


def item_base(record: ContextRecord) -> dict[str, Any]:
    """The permutation-free part of an item's payload (cacheable per item)."""
    scenario = record.scenario
    now = scenario.current_index
    first = max(0, now - round(HISTORY_SHOWN_S / scenario.dt))
    history_states = scenario.states[0, :, first : now + 1]
    history_valid = scenario.valid[0, :, first : now + 1]
    shown = [history_states[..., :2][history_valid], record.candidates[..., :2][record.candidate_valid]]
    xy = torch.cat(shown).double()
    if xy.numel() == 0:
        xy = torch.zeros(1, 2, dtype=torch.float64)
    lo, hi = xy.min(0).values - VIEW_MARGIN_M, xy.max(0).values + VIEW_MARGIN_M
    centre = (float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2)
    world_view = (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))
    controlled = record.controlled
    focus_xy = torch.cat([history_states[controlled][..., :2][history_valid[controlled]],
                          record.candidates[:, controlled][..., :2][record.candidate_valid[:, controlled]]]).double()
    if focus_xy.numel() == 0:
        focus_xy = xy
    f_lo, f_hi = focus_xy.min(0).values - FOCUS_MARGIN_M, focus_xy.max(0).values + FOCUS_MARGIN_M
    grow = (FOCUS_MIN_M - (f_hi - f_lo)).clamp_min(0) / 2
    f_lo, f_hi = torch.maximum(f_lo - grow, lo), torch.minimum(f_hi + grow, hi)
    present = scenario.valid[0].any(-1) | record.candidate_valid.any(0).any(-1)
    ids = scenario.agent_ids[0] if scenario.agent_ids else tuple(str(a) for a in range(scenario.num_agents))
    agents = []
    for a in range(scenario.num_agents):
        try:
            kind = AgentType(int(scenario.agent_type[0, a])).name.lower()
        except ValueError:
            kind = "other"
        agents.append({"id": ids[a] or str(a), "length": round(float(scenario.extent[0, a, 0]), 2),
                       "width": round(float(scenario.extent[0, a, 1]), 2),
                       "controlled": bool(record.controlled[a]), "type": kind, "present": bool(present[a])})
    return {
        "item": record.id,
        "scene": f"{record.source}/{record.split}/{record.scene_id}",
        "dt": scenario.dt,
        "num_candidates": record.num_candidates,
        "history_steps": int(history_states.shape[1]),  # frames 0 .. history_steps-1; the last one is "now"
        "future_steps": int(record.candidates.shape[2]),
        "agents": agents,
        "view": {"x0": world_view[0] - centre[0], "x1": world_view[1] - centre[0],
                 "y0": world_view[2] - centre[1], "y1": world_view[3] - centre[1]},
        "focus": {"x0": float(f_lo[0]) - centre[0], "x1": float(f_hi[0]) - centre[0],
                  "y0": float(f_lo[1]) - centre[1], "y1": float(f_hi[1]) - centre[1]},
        "map": map_image(record, world_view),
        "history": _track(history_states, history_valid, centre),
        "futures": [_track(record.candidates[k], record.candidate_valid[k], centre)
                    for k in range(record.num_candidates)],
    }


def playback_seconds(payload: dict[str, Any]) -> float:
    """How long one play-through of an item takes at 1x speed (s): the shown history and the future."""
    return float((payload["history_steps"] + payload["future_steps"] - 1) * payload["dt"])


def item_payload(base: dict[str, Any], assignment: Assignment, progress: dict[str, int]) -> dict[str, Any]:
    """The page's view of one item for one annotator: candidates in their shuffled display order."""
    out = {k: v for k, v in base.items() if k != "futures"}
    out["candidates"] = [{"slot": slot + 1, **base["futures"][index]}
                         for slot, index in enumerate(assignment.permutation)]
    answer: int | str | None = "tie" if assignment.slot == -1 else assignment.slot
    out.update({"position": assignment.position, "status": assignment.status, "answer": answer,
                "skip_reason": assignment.skip_reason, "progress": progress, "done": False})
    return out
