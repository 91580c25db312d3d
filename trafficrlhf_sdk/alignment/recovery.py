"""Recovery targets: what the imitation loss learns on the states the policy drives itself into.

A failure-focused context (:mod:`~trafficrlhf_sdk.alignment.contexts`) holds the controlled agents where the
current model drove them: a turn taken too wide, a lane drifted from. The log's window at the same time shows how a
driver continues from the *logged* state, not from these, so imitating it there teaches nothing about the states
that lead to the model's failures (the covariate shift DAgger addresses). With ``AlignConfig.imitation_recovery``
the imitation loss on those contexts learns, from the simulated history, a future that a driver following the log
would take from where the agent stands:

* **Along the logged path**, the log's progress per step; the rate blends linearly over the horizon from the
  agent's own current speed to the log's, so the speed stays continuous.
* **Across it**, the signed lateral offset from the path closes along a cubic Hermite curve in the distance
  travelled that starts with the agent's own slope (its heading against the path's) and reaches the path,
  parallel to it, at the end of the horizon: position, heading and speed continue the simulated state. The
  heading follows the log's heading along the path plus that slope.

This is the recovery target of a perturbed trajectory in ChauffeurNet (Bansal, Krizhevsky and Ogale 2018,
"ChauffeurNet: Learning to Drive by Imitating the Best and Synthesizing the Worst"), taken on the model's own
closed-loop states instead of on random perturbations. The logged path is the log's positions from "now" to the
window's end, extended straight back from its first point and ahead from its last along the log's heading there.
Agents whose log is not valid over the whole future keep the log's window (the imitation loss skips windows with
missing steps).
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.dynamics import wrap_angle

__all__ = ["recovery_targets"]

EXTENSION_M = 100.0
"""Length of the straight pieces added before the logged path's first point and after its last."""
MIN_RECOVERY_M = 1.0
"""An agent that travels less than this (m) over the horizon keeps its lateral offset."""
MAX_SLOPE_RAD = 0.8
"""The agent's heading against the path's is clipped to this (rad) when it sets the initial lateral slope."""
STILL_M = 1e-3
"""Steps shorter than this (m) take their direction from the log's heading instead of their displacement."""


def _directions(points: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Unit direction of each segment ``points[:, j] -> points[:, j + 1]`` ``(N, P-1, 2)``; a segment shorter than
    ``STILL_M`` takes the heading ``yaw (N, P-1)``."""
    step = points[:, 1:] - points[:, :-1]
    length = torch.linalg.vector_norm(step, dim=-1, keepdim=True)
    heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)
    return torch.where(length > STILL_M, step / length.clamp_min(STILL_M), heading)


def _project(point: torch.Tensor, points: torch.Tensor, arc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Arc position and squared distance of the nearest point of each polyline ``points (N, P, 2)`` to ``point
    (N, 2)``; ``arc (N, P)`` is the arc length at each vertex. Returns ``(sigma (N,), segment (N,))``."""
    a, b = points[:, :-1], points[:, 1:]
    ab = b - a
    length2 = (ab * ab).sum(-1)
    t = (((point[:, None] - a) * ab).sum(-1) / length2.clamp_min(STILL_M**2)).clamp(0.0, 1.0)
    nearest = a + t[..., None] * ab
    dist2 = ((nearest - point[:, None]) ** 2).sum(-1)
    seg = dist2.argmin(-1)
    rows = torch.arange(point.shape[0], device=point.device)
    sigma = arc[rows, seg] + t[rows, seg] * (arc[rows, seg + 1] - arc[rows, seg])
    return sigma, seg


def _at(sigma: torch.Tensor, points: torch.Tensor, arc: torch.Tensor, dirs: torch.Tensor, yaw: torch.Tensor
        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Position ``(N, K, 2)``, unit normal ``(N, K, 2)`` and heading ``(N, K)`` of each polyline at arc positions
    ``sigma (N, K)``; the heading interpolates the unwrapped vertex headings ``yaw (N, P)`` linearly in arc."""
    last = arc.shape[1] - 2
    seg = (torch.searchsorted(arc.contiguous(), sigma.contiguous(), right=True) - 1).clamp(0, last)
    tangent = dirs.gather(1, seg[..., None].expand(-1, -1, 2))
    start = points.gather(1, seg[..., None].expand(-1, -1, 2))
    into = sigma - arc.gather(1, seg)
    length = arc.gather(1, seg + 1) - arc.gather(1, seg)
    frac = (into / length.clamp_min(STILL_M)).clamp(0.0, 1.0)
    heading = yaw.gather(1, seg) + frac * (yaw.gather(1, seg + 1) - yaw.gather(1, seg))
    normal = torch.stack([-tangent[..., 1], tangent[..., 0]], -1)
    return start + into[..., None] * tangent, normal, heading


def recovery_targets(context: ScenarioTensor, logged: ScenarioTensor) -> ScenarioTensor:
    """``logged`` with the history of every controlled agent of ``context`` and a future that returns it to its
    logged path (see the module docstring).

    Args:
        context: windows ``(B, A, T)`` whose controlled agents hold simulated states up to ``current_index``.
        logged: the same windows of the log (same shape and ``current_index``).

    Returns:
        A scenario with ``logged``'s agents, map and validity, in which each agent that is controlled and valid now
        in ``context`` and valid in the log from now to the window's end has ``context``'s states up to now and
        the recovery target after it; every other agent keeps the log's window.
    """
    now, dt = context.current_index, context.dt
    horizon = logged.num_steps - 1 - now
    driven = context.controlled & context.valid[:, :, now] & logged.valid[:, :, now:].all(-1)
    if horizon < 1 or not driven.any():
        return logged
    states = logged.states.clone()
    rows = driven.nonzero(as_tuple=True)
    log = logged.states[rows][:, now:]  # (N, H+1, 4): x, y, speed, yaw
    sim_now = context.states[rows][:, now]  # (N, 4)

    # the logged path, extended straight at both ends; its arc length and (unwrapped) heading at each vertex
    yaw0, yaw_end = log[:, 0, 3], log[:, -1, 3]
    back = log[:, 0, :2] - EXTENSION_M * torch.stack([torch.cos(yaw0), torch.sin(yaw0)], -1)
    ahead = log[:, -1, :2] + EXTENSION_M * torch.stack([torch.cos(yaw_end), torch.sin(yaw_end)], -1)
    points = torch.cat([back[:, None], log[:, :, :2], ahead[:, None]], 1)  # (N, H+3, 2)
    dirs = _directions(points, torch.cat([yaw0[:, None], log[:, :, 3]], 1))
    seg_len = torch.linalg.vector_norm(points[:, 1:] - points[:, :-1], dim=-1)
    arc = torch.cat([torch.zeros_like(seg_len[:, :1]), seg_len.cumsum(-1)], 1)  # (N, H+3)
    turn = wrap_angle(log[:, 1:, 3] - log[:, :-1, 3]).cumsum(-1)
    vertex_yaw = yaw0[:, None] + torch.cat([torch.zeros_like(yaw0[:, None]), turn], 1)
    vertex_yaw = torch.cat([vertex_yaw[:, :1], vertex_yaw, vertex_yaw[:, -1:]], 1)  # (N, H+3)

    # where the agent stands: arc position, signed lateral offset, and the slope of its heading across the path
    sigma0, _ = _project(sim_now[:, :2], points, arc)
    base0, normal0, path_yaw0 = (v[:, 0] for v in _at(sigma0[:, None], points, arc, dirs, vertex_yaw))
    offset0 = ((sim_now[:, :2] - base0) * normal0).sum(-1)
    slope0 = torch.tan(wrap_angle(sim_now[:, 3] - path_yaw0).clamp(-MAX_SLOPE_RAD, MAX_SLOPE_RAD))

    # progress: the speed blends from the agent's own to the log's over the horizon
    k = torch.arange(1, horizon + 1, device=log.device, dtype=log.dtype)
    w = k / horizon
    speed = (1 - w) * sim_now[:, 2:3].abs() + w * log[:, 1:, 2].abs()  # (N, H)
    travelled = (speed * dt).cumsum(-1)
    sigma = sigma0[:, None] + travelled

    # lateral: a cubic Hermite in the distance travelled, from (offset0, slope0) to (0, 0); an agent that barely
    # moves over the horizon keeps its offset (a car does not slide sideways)
    span = travelled[:, -1:]
    moving = span > MIN_RECOVERY_M
    u = travelled / span.clamp_min(MIN_RECOVERY_M)
    h00, h10 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u
    d00, d10 = 6 * u**2 - 6 * u, 3 * u**2 - 4 * u + 1  # their derivatives in u
    offset = torch.where(moving, h00 * offset0[:, None] + h10 * span * slope0[:, None], offset0[:, None])
    slope = torch.where(moving, (d00 * offset0[:, None]) / span.clamp_min(MIN_RECOVERY_M) + d10 * slope0[:, None],
                        torch.zeros_like(u))

    on_path, normal, heading = _at(sigma, points, arc, dirs, vertex_yaw)
    xy = on_path + offset[..., None] * normal
    yaw = wrap_angle(heading + torch.atan(slope))
    future = torch.cat([xy, speed[..., None], yaw[..., None]], -1)

    sim_hist = context.states[rows][:, : now + 1]
    states[rows] = torch.cat([sim_hist, future], 1)
    valid = logged.valid.clone()
    valid[rows] = torch.cat([context.valid[rows][:, : now + 1], logged.valid[rows][:, now + 1:]], 1)
    return logged.replace_unchecked(states=states * valid[..., None], valid=valid)
