"""A tiny, model-free feedback campaign for tests of stores, annotators and annotation frontends.

:func:`make_tiny_campaign` writes contexts of three cars on a straight three-lane road whose candidates are
deliberately different: a faithful copy of the log, one with a car leaving the road, one with a lane change
into a neighbour (collision), one with a car stopping dead (stall + hard braking), one with a car weaving in its
lane (a mild lateral-acceleration excess). A realism judge should rank the faithful copy first.
"""

from __future__ import annotations

import math

import torch

from trafficrlhf_sdk.feedback.store import Campaign, FeedbackStore
from trafficrlhf_sdk.scenario.map import MapRaster
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["VARIANTS", "make_tiny_campaign", "tiny_context"]

VARIANTS = ("faithful", "offroad", "collision", "stall", "weave")
DT = 0.1
HISTORY = 10  # steps before "now"
HORIZON = 30  # candidate steps (3 s)


def _road_map() -> MapRaster:
    """x in [-60, 160) m, y in [-20, 20) m at 2 px/m: drivable for |y| < 6, lane dividers at y = +-2."""
    h, w = 440, 80
    raster = torch.zeros(1, 3, h, w, dtype=torch.uint8)
    ys = (torch.arange(w) + 0.5) / 2 - 20
    raster[0, 0, :, ys.abs() < 6] = 1
    raster[0, 2, :, ((ys.abs() - 2).abs() < 0.25)] = 1
    m = torch.tensor([[[2.0, 0.0, 120.0], [0.0, 2.0, 40.0], [0.0, 0.0, 1.0]]])
    return MapRaster(raster=raster, world_to_pixel=m)


def _drive(x0: float, y0: float, v: float, steps: int, lateral: torch.Tensor | None = None,
           speed: torch.Tensor | None = None) -> torch.Tensor:
    """States ``(steps, 4)`` of a car heading +x; optional per-step ``lateral`` offset and ``speed`` profile."""
    speeds = torch.full((steps,), v) if speed is None else speed
    x = x0 + torch.cumsum(speeds * DT, 0) - speeds[0] * DT
    y = torch.full((steps,), y0) if lateral is None else y0 + lateral
    dy = torch.diff(y, prepend=y[:1]) / DT
    yaw = torch.atan2(dy, speeds.clamp_min(0.1))
    return torch.stack([x, y, speeds, yaw], -1)


def tiny_context(variant_of: list[str], scene_index: int = 0) -> tuple[ScenarioTensor, torch.Tensor, torch.Tensor,
                                                                        torch.Tensor, torch.Tensor]:
    """One context (three cars) and candidates following ``variant_of`` (names from :data:`VARIANTS`).

    Returns ``(scenario, candidates (N, 3, H, 4), candidate_valid, logged (3, H, 4), logged_valid)`` with
    ``scenario.current_index = 10`` and H = 30.
    """
    total = HISTORY + 1 + HORIZON
    offset = 3.0 * scene_index
    cars = [(offset, -4.0, 10.0), (offset + 2.0, 0.0, 10.0), (offset + 8.0, 4.0, 11.0)]
    full = torch.stack([_drive(x - HISTORY * v * DT, y, v, total) for x, y, v in cars])  # (3, T, 4)
    logged = full[:, HISTORY + 1 :].clone()
    t = torch.arange(HORIZON, dtype=torch.float32) * DT
    candidates = []
    for name in variant_of:
        c = logged.clone()
        if name == "offroad":  # car 0 drifts 8 m right, off the road
            c[0] = _drive(float(logged[0, 0, 0]), -4.0, 10.0, HORIZON, lateral=-8.0 * (t / t[-1]) ** 2)
        elif name == "collision":  # car 1 cuts into car 0's lane next to it
            c[1] = _drive(float(logged[1, 0, 0]), 0.0, 10.0, HORIZON, lateral=-4.0 * torch.clamp(t / 1.0, max=1.0))
        elif name == "stall":  # car 2 brakes hard to a stop and stays
            c[2] = _drive(float(logged[2, 0, 0]), 4.0, 11.0, HORIZON, speed=torch.clamp(11.0 - 9.0 * t, min=0.0))
        elif name == "weave":  # car 1 weaves within its lane
            c[1] = _drive(float(logged[1, 0, 0]), 0.0, 10.0, HORIZON, lateral=1.0 * torch.sin(2 * math.pi * t / 2.5))
        elif name != "faithful":
            raise ValueError(f"unknown variant {name!r}; pick from {VARIANTS}.")
        candidates.append(c)
    scenario = ScenarioTensor(
        states=full[None].float(), valid=torch.ones(1, 3, total, dtype=torch.bool),
        extent=torch.tensor([[[4.5, 1.9], [4.6, 1.9], [4.8, 2.0]]]), agent_type=torch.ones(1, 3, dtype=torch.long),
        controlled=torch.ones(1, 3, dtype=torch.bool), dt=DT, current_index=HISTORY, map=_road_map(),
        scene_ids=(f"tiny-{scene_index:04d}",), agent_ids=(("a", "b", "c"),), source="tiny",
    )
    stacked = torch.stack(candidates).float()
    return (scenario, stacked, torch.ones(stacked.shape[:3], dtype=torch.bool), logged.float(),
            torch.ones(logged.shape[:2], dtype=torch.bool))


def make_tiny_campaign(store: FeedbackStore, name: str = "tiny", num_contexts: int = 4, num_candidates: int = 5,
                       seed: int = 0, labels_per_item: int | None = None) -> Campaign:
    """Create campaign ``name`` with ``num_contexts`` tiny contexts; candidate k of context i is variant
    ``VARIANTS[(i + k) % 5]`` (so the faithful one moves around)."""
    config = {"name": name, "model": "tiny", "guidance": None, "source": "tiny", "split": "test",
              "num_candidates": num_candidates, "candidate_seconds": HORIZON * DT, "seed": seed,
              "labels_per_item": labels_per_item, "history_seconds": HISTORY * DT, "map_margin_m": 0.0}
    campaign = store.create_campaign(name, "tiny", None, seed, num_candidates, config, "test")
    for i in range(num_contexts):
        variants = [VARIANTS[(i + k) % len(VARIANTS)] for k in range(num_candidates)]
        scenario, cands, cand_valid, logged, logged_valid = tiny_context(variants, i)
        store.add_context(campaign, "tiny", "test", scenario.scene_ids[0], seed + i, scenario, cands, cand_valid,
                          logged, logged_valid, "test")
    return store.campaign(name)
