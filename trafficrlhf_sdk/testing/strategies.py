"""Hypothesis strategies that build valid random :class:`~trafficrlhf_sdk.scenario.ScenarioTensor` batches.

For plugin authors who want property tests of code that consumes scenarios (traffic models, metrics, sources)::

    from hypothesis import given
    from trafficrlhf_sdk.testing.strategies import feasible_trajectories, scenario_tensors

    @given(scenario_tensors(max_agents=4))
    def test_my_metric_is_finite(scenario):
        assert torch.isfinite(my_metric(scenario)).all()

Two strategies:

- :func:`scenario_tensors`: arbitrary *valid* scenarios: random validity masks with holes and fully invalid
  padding agents, states zeroed where invalid, yaw in [-pi, pi) (float32), optional small uint8 map rasters
  with a scaled and shifted ``world_to_pixel`` and optional polylines. The states are not dynamically
  feasible; use them for shape, masking and IO properties.
- :func:`feasible_trajectories`: scenarios whose states come from
  :func:`~trafficrlhf_sdk.simulation.dynamics.unicycle_rollout` of random actions drawn inside
  :func:`~trafficrlhf_sdk.simulation.dynamics.action_bounds` (every agent valid at every step), so
  ``scenario.actions()`` recovers the actions.

Needs ``hypothesis`` and ``numpy`` (the ``test`` extra).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from trafficrlhf_sdk.simulation.dynamics import (
    DEFAULT_BOUNDS,
    UnicycleBounds,
    action_bounds,
    unicycle_rollout,
    unicycle_step,
)
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.map import DEFAULT_LAYERS, MapRaster, PolylineType
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["feasible_trajectories", "map_rasters", "scenario_tensors"]

# float32 pi: wrap_angle() of float32 tensors returns values in [-PI32, PI32).
PI32 = float(np.float32(math.pi))
DTS = (0.05, 0.1, 0.25, 0.5)
_AGENT_TYPES = tuple(int(t) for t in AgentType if t != AgentType.UNSET)
_POLYLINE_TYPES = (
    PolylineType.UNSET,
    PolylineType.LANE_CENTER,
    PolylineType.ROAD_EDGE,
    PolylineType.ROAD_LINE,
    PolylineType.CROSSWALK,
    PolylineType.OTHER,
)


def _f32(lo: float, hi: float, **kwargs: Any) -> st.SearchStrategy[float]:
    return st.floats(float(np.float32(lo)), float(np.float32(hi)), width=32, **kwargs)


def _yaw() -> st.SearchStrategy[float]:
    return st.floats(-PI32, PI32, width=32, exclude_max=True)


@st.composite
def map_rasters(
    draw: st.DrawFn,
    num_scenes: int,
    max_size: int = 8,
    layers: tuple[str, ...] = DEFAULT_LAYERS,
    with_polylines: bool | None = None,
) -> MapRaster:
    """A :class:`MapRaster` of ``num_scenes`` scenes: 0/1 uint8 rasters of at most ``max_size`` x ``max_size``
    pixels, each scene's of its own size, ``world_to_pixel = [[s, 0, ti], [0, s, tj], [0, 0, 1]]`` with a scale
    ``s`` in {0.5, 1, 2, 3} px/m, and (when ``with_polylines`` is True, or at random when None) polylines with
    masks and type codes."""
    h = draw(st.integers(1, max_size), label="H")
    w = draw(st.integers(1, max_size), label="W")
    raster = draw(arrays(np.uint8, (num_scenes, len(layers), h, w), elements=st.integers(0, 1)), label="raster")
    sizes = [[draw(st.integers(1, h), label="H_b"), draw(st.integers(1, w), label="W_b")] for _ in range(num_scenes)]
    w2p = np.zeros((num_scenes, 3, 3), np.float32)
    for b in range(num_scenes):
        scale = draw(st.sampled_from((0.5, 1.0, 2.0, 3.0)), label="scale")
        w2p[b] = [[scale, 0.0, draw(_f32(-4, 4))], [0.0, scale, draw(_f32(-4, 4))], [0.0, 0.0, 1.0]]
    polylines = polyline_valid = polyline_type = None
    if with_polylines or (with_polylines is None and draw(st.booleans(), label="with_polylines")):
        p = draw(st.integers(1, 3), label="P")
        length = draw(st.integers(1, 4), label="L")
        polylines = torch.from_numpy(
            draw(arrays(np.float32, (num_scenes, p, length, 2), elements=_f32(-50, 50)), label="polylines")
        )
        polyline_valid = torch.from_numpy(draw(arrays(np.bool_, (num_scenes, p, length)), label="polyline_valid"))
        polylines = polylines * polyline_valid[..., None]
        polyline_type = torch.from_numpy(
            draw(arrays(np.int64, (num_scenes, p), elements=st.sampled_from(_POLYLINE_TYPES)), label="types")
        )
    return MapRaster(
        raster=torch.from_numpy(raster),
        sizes=torch.tensor(sizes, dtype=torch.int64).reshape(num_scenes, 2),
        world_to_pixel=torch.from_numpy(w2p),
        layers=tuple(layers),
        polylines=polylines,
        polyline_valid=polyline_valid,
        polyline_type=polyline_type,
    )


def _ids(num_scenes: int, valid_agents: torch.Tensor) -> tuple[tuple[str, ...], tuple[tuple[str, ...], ...]]:
    scene_ids = tuple(f"scene-{b:04d}" for b in range(num_scenes))
    agent_ids = tuple(
        tuple(str(a) if bool(valid_agents[b, a]) else "" for a in range(valid_agents.shape[1]))
        for b in range(num_scenes)
    )
    return scene_ids, agent_ids


@st.composite
def scenario_tensors(
    draw: st.DrawFn,
    max_scenes: int = 3,
    max_agents: int = 5,
    max_steps: int = 12,
    with_map: bool | None = True,
    dt: float | None = 0.1,
    min_steps: int = 1,
) -> ScenarioTensor:
    """Random valid :class:`ScenarioTensor` batches.

    Args:
        max_scenes, max_agents, max_steps: upper bounds of B, A and T (each drawn from 1 up).
        with_map: True attaches a :func:`map_rasters` map, False none, None either at random.
        dt: step length in seconds; None draws one of 0.05, 0.1, 0.25, 0.5.
        min_steps: lower bound of T.

    ``valid`` is an arbitrary mask (holes and never-valid padding agents included); states are zero where
    invalid, x and y lie in [-200, 200] m, speed in [-10, 30] m/s and yaw in [-pi, pi). Padding agents have
    type ``UNSET``, zero extent, id ``""`` and are never controlled; ``origin`` is float64 or None.
    """
    b = draw(st.integers(1, max_scenes), label="B")
    a = draw(st.integers(1, max_agents), label="A")
    t = draw(st.integers(min_steps, max(min_steps, max_steps)), label="T")
    valid = torch.from_numpy(draw(arrays(np.bool_, (b, a, t)), label="valid"))
    xy = draw(arrays(np.float32, (b, a, t, 2), elements=_f32(-200, 200)), label="xy")
    speed = draw(arrays(np.float32, (b, a, t, 1), elements=_f32(-10, 30)), label="speed")
    yaw = draw(arrays(np.float32, (b, a, t, 1), elements=_yaw()), label="yaw")
    states = torch.from_numpy(np.concatenate([xy, speed, yaw], -1))
    states = torch.where(valid[..., None], states, torch.zeros(()))
    present = valid.any(-1)
    extent = torch.from_numpy(draw(arrays(np.float32, (b, a, 2), elements=_f32(0.5, 20)), label="extent"))
    extent = extent * present[..., None]
    agent_type = torch.from_numpy(
        draw(arrays(np.int64, (b, a), elements=st.sampled_from(_AGENT_TYPES)), label="agent_type")
    )
    agent_type = torch.where(present, agent_type, torch.zeros((), dtype=torch.int64))
    controlled = torch.from_numpy(draw(arrays(np.bool_, (b, a)), label="controlled")) & present
    origin = None
    if draw(st.booleans(), label="with_origin"):
        origin = torch.from_numpy(draw(arrays(np.float64, (b, 2), elements=st.floats(-1e5, 1e5)), label="origin"))
    use_map = draw(st.booleans(), label="with_map") if with_map is None else with_map
    scene_ids, agent_ids = _ids(b, present)
    return ScenarioTensor(
        states=states,
        valid=valid,
        extent=extent,
        agent_type=agent_type,
        controlled=controlled,
        dt=draw(st.sampled_from(DTS), label="dt") if dt is None else dt,
        current_index=draw(st.integers(0, t - 1), label="current_index"),
        map=draw(map_rasters(b), label="map") if use_map else None,
        origin=origin,
        scene_ids=scene_ids,
        agent_ids=agent_ids,
        source="hypothesis",
        extras={"strategy": "scenario_tensors"},
    )


@st.composite
def feasible_trajectories(
    draw: st.DrawFn,
    max_scenes: int = 2,
    max_agents: int = 4,
    max_steps: int = 12,
    dt: float = 0.1,
    bounds: UnicycleBounds | None = DEFAULT_BOUNDS,
    with_map: bool = False,
    return_actions: bool = False,
) -> ScenarioTensor | tuple[ScenarioTensor, torch.Tensor]:
    """Scenarios whose states are unicycle rollouts of random in-bounds actions.

    Draws B, A and T >= 2, an initial state per agent (x, y in [-100, 100] m, speed in [-2, 20] m/s clipped
    to the speed bounds, yaw in [-pi, pi)) and, step by step, an action strictly inside
    ``action_bounds(speed, bounds)`` for the running speed (a box of +-4 m/s^2 and +-0.5 rad/s when
    ``bounds`` is None). The states are ``cat(initial, unicycle_rollout(initial, actions, dt, bounds))`` in
    float32, every agent valid at every step, ``current_index`` 0 and every agent controlled.

    With ``return_actions`` the strategy yields ``(scenario, actions)`` with ``actions`` float32
    ``(B, A, T-1, 2)``.
    """
    b = draw(st.integers(1, max_scenes), label="B")
    a = draw(st.integers(1, max_agents), label="A")
    t = draw(st.integers(2, max(2, max_steps)), label="T")
    v_lo, v_hi = (-2.0, 20.0) if bounds is None else (max(bounds.v_min, -2.0), min(bounds.v_max, 20.0))
    xy0 = draw(arrays(np.float32, (b, a, 2), elements=_f32(-100, 100)), label="xy0")
    v0 = draw(arrays(np.float32, (b, a, 1), elements=_f32(v_lo, v_hi)), label="v0")
    yaw0 = draw(arrays(np.float32, (b, a, 1), elements=_yaw()), label="yaw0")
    initial = torch.from_numpy(np.concatenate([xy0, v0, yaw0], -1))
    # Fractions in [0, 1] of the admissible interval; a 0.1% margin keeps float rounding away from the bounds.
    frac = torch.from_numpy(
        draw(arrays(np.float32, (b, a, t - 1, 2), elements=_f32(0, 1)), label="action_fractions")
    )
    frac = 0.001 + 0.998 * frac
    actions = []
    state = initial
    for k in range(t - 1):
        if bounds is None:
            lb = torch.tensor([-4.0, -0.5]).expand(b, a, 2)
            ub = -lb
        else:
            lb, ub = action_bounds(state[..., 2], bounds)
        action = lb + frac[:, :, k] * (ub - lb)
        actions.append(action)
        state = unicycle_step(state, action, dt, bounds)
    action_tensor = torch.stack(actions, 2)
    rolled = unicycle_rollout(initial, action_tensor, dt, bounds)
    states = torch.cat([initial[:, :, None], rolled], 2)
    valid = torch.ones(b, a, t, dtype=torch.bool)
    scene_ids, agent_ids = _ids(b, valid.any(-1))
    scenario = ScenarioTensor(
        states=states,
        valid=valid,
        extent=torch.tensor([4.5, 1.9]).expand(b, a, 2).clone(),
        agent_type=torch.full((b, a), int(AgentType.VEHICLE), dtype=torch.int64),
        controlled=torch.ones(b, a, dtype=torch.bool),
        dt=dt,
        current_index=0,
        map=draw(map_rasters(b), label="map") if with_map else None,
        scene_ids=scene_ids,
        agent_ids=agent_ids,
        source="hypothesis",
        extras={"strategy": "feasible_trajectories"},
    )
    return (scenario, action_tensor) if return_actions else scenario
