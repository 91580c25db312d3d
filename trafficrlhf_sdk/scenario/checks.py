"""Checks of a loaded scene against the world it describes and against the limits of its source.

A scene is checked against its own map: the logged positions of its moving vehicles must mostly lie on the
drivable layer, otherwise the map's origin, scale or orientation does not belong to the tracks and every
off-road and on-road number of the scene would be wrong. A map that passes that share but fits the tracks much
better when moved by a few metres is misregistered too (an origin off by 10 m along a road's side leaves most
positions on the road and puts most agents off it at some step). The agent limit is checked by the sources before they
allocate any per-agent array. ``docs/reference/limits.md`` lists every limit, its default and the option that
raises it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from trafficrlhf_sdk.errors import InputLimitError, MapMismatchError
from trafficrlhf_sdk.scenario.agents import AgentType

if TYPE_CHECKING:
    from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["MAX_AGENTS", "MAX_REGISTRATION_GAIN", "MIN_ON_MAP_SHARE", "MOVING_SPEED_MPS", "check_agent_count",
           "check_on_map", "on_map_share"]

# Real scenes measure 0.907 to 1 (660 nuScenes prediction scenes) and 0.935 to 1 (10 ScenarioNet nuScenes-mini
# scenes); docs/reference/limits.md gives the distribution.
MIN_ON_MAP_SHARE = 0.8
# A map moved by up to REGISTRATION_REACH_M that puts this much more of the positions on the drivable layer is
# misregistered. Real scenes gain at most 0.085 (602 nuScenes prediction scenes, moves within 16 m on a 1 m grid),
# and a share above 1 - 0.12 cannot gain as much, so the search runs only on scenes below 0.88, none of them real.
MAX_REGISTRATION_GAIN = 0.12
REGISTRATION_REACH_M = 16.0
MAX_AGENTS = 1024
MOVING_SPEED_MPS = 1.0  # parked vehicles may stand off the drivable layer (parking lots, driveways)
OPTIONS_HINT = "TRAFFICRLHF_SOURCE_OPTIONS='{option}=...' for every command, or {option}=... in code"
_PROBE_POINTS = 256  # positions tried per candidate map offset when looking for a better fit
_PROBE_REACH_M, _PROBE_STEP_M = 64.0, 2.0


def _probe_positions(scene: ScenarioTensor) -> torch.Tensor:
    """Scene-frame positions ``(N, 2)`` float64 the check reads: moving vehicles, else every vehicle."""
    vehicle = (scene.agent_type == AgentType.VEHICLE)[..., None] & scene.valid
    moving = vehicle & (scene.speed.abs() > MOVING_SPEED_MPS)
    return scene.xy[moving if bool(moving.any()) else vehicle].double()


def on_map_share(scene: ScenarioTensor) -> tuple[float, int]:
    """``(share, positions)`` for one scene (B = 1): the share of the logged positions of its moving vehicles
    (every vehicle's when none moves faster than ``MOVING_SPEED_MPS``) on the drivable layer of its map, and how
    many positions that is. ``(nan, 0)`` without a map or vehicles."""
    if scene.map is None or "drivable" not in scene.map.layers:
        return math.nan, 0
    xy = _probe_positions(scene)
    if not len(xy):
        return math.nan, 0
    return float(scene.map.lookup(xy[None]).double().mean()), len(xy)


def _best_offset(scene: ScenarioTensor, xy: torch.Tensor, reach_m: float = _PROBE_REACH_M,
                 step_m: float = _PROBE_STEP_M) -> tuple[float, float, float, float]:
    """``(dx, dy, share, here)``: the move of the map's origin (m, on a ``step_m`` grid within ``reach_m``) that
    puts most of ``xy`` on the drivable layer, the share it reaches, and the share without a move (both on the
    same sample of at most 256 positions)."""
    assert scene.map is not None
    pick = xy[torch.linspace(0, len(xy) - 1, min(len(xy), _PROBE_POINTS)).long()]
    steps = torch.arange(-reach_m, reach_m + step_m / 2, step_m, dtype=torch.float64)
    offsets = torch.cartesian_prod(steps, steps)  # (K, 2)
    hits = scene.map.lookup((pick[None] - offsets[:, None]).reshape(1, -1, 2)).reshape(len(offsets), -1)
    share = hits.double().mean(1)
    # many moves along a road fit equally well: report the smallest of those that fit best
    fits = share >= share.max() - 1e-9
    best = int(torch.where(fits, offsets.norm(dim=1), torch.full_like(share, math.inf)).argmin())
    here = float(scene.map.lookup(pick[None]).double().mean())
    return float(offsets[best, 0]), float(offsets[best, 1]), float(share[best]), here


def check_on_map(scene: ScenarioTensor, min_share: float, where: str, fix: str) -> None:
    """Raise :class:`MapMismatchError` when less than ``min_share`` of the moving vehicles' logged positions of
    ``scene`` (B = 1) lie on the drivable layer of its own map (:func:`on_map_share`), or when moving the map by
    up to ``REGISTRATION_REACH_M`` would put ``MAX_REGISTRATION_GAIN`` more of them on it (a misregistered map).

    ``where`` names the scene (its file) and ``fix`` says which file holds the map's origin and scale. The message
    gives the share measured, the origin move that fits best (searched within 64 m below ``min_share``, within
    ``REGISTRATION_REACH_M`` for a misregistered map) and the option that accepts the scene anyway. ``min_share``
    0 turns both checks off.
    """
    if min_share <= 0:
        return
    share, count = on_map_share(scene)
    if not count or share >= max(min_share, 1 - MAX_REGISTRATION_GAIN):
        return
    accept = (f"To load the scene as it is, set min_on_map_share=0 "
              f"({OPTIONS_HINT.format(option='min_on_map_share')}).")
    if share >= min_share:
        dx, dy, best, here = _best_offset(scene, _probe_positions(scene), REGISTRATION_REACH_M, 1.0)
        if best - here >= MAX_REGISTRATION_GAIN:
            raise MapMismatchError(
                f"{where}: {share:.0%} of the {count:,} logged positions of its moving vehicles lie on the drivable "
                f"layer of its own map, but moving the map's origin by about ({dx:+.0f}, {dy:+.0f}) m would put "
                f"{best:.0%} on it (real nuScenes scenes gain at most 9 points from any move within "
                f"{REGISTRATION_REACH_M:.0f} m), so the map is misregistered; fix {fix}. {accept}"
            )
        return
    dx, dy, best, _ = _best_offset(scene, _probe_positions(scene))
    if best >= min_share and (dx, dy) != (0.0, 0.0):
        hint = f"moving the map's origin by about ({dx:+.0f}, {dy:+.0f}) m would put {best:.0%} on it; "
    else:
        hint = "no shift within 64 m fits (a wrong scale, a transposed or a foreign map); "
    raise MapMismatchError(
        f"{where}: only {share:.0%} of the {count:,} logged positions of its moving vehicles lie on the drivable "
        f"layer of its own map (at least {min_share:.0%} expected; real nuScenes scenes measure 90% or more), so "
        f"the map does not line up with the tracks; {hint}fix {fix}. {accept}"
    )


def check_agent_count(count: int, limit: int, where: str) -> None:
    """Raise :class:`InputLimitError` when a scene holds more than ``limit`` agents (before anything per agent is
    allocated)."""
    if count > limit:
        raise InputLimitError(
            f"{where}: {count:,} agents (tracks), more than max_agents={limit:,}; duplicated or generated tracks "
            f"are likely. If the scene is right, raise the limit with {OPTIONS_HINT.format(option='max_agents')}."
        )
