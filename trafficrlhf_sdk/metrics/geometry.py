"""Oriented-box geometry, batched: corners and separating-axis overlap tests, and the agents in each agent's path
ahead (gaps, closing speeds), and the direction of the nearest lane centerline."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from trafficrlhf_sdk.scenario.map import PolylineType

if TYPE_CHECKING:
    from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["box_corners", "boxes_overlap", "colliding_pairs", "following_gaps", "lane_direction", "pair_step_flags",
           "pairwise_collisions", "path_gaps"]


def box_corners(xy: torch.Tensor, yaw: torch.Tensor, extent: torch.Tensor) -> torch.Tensor:
    """Corners ``(..., 4, 2)`` (m) of boxes centred at ``xy (..., 2)`` with heading ``yaw (...)`` (rad) and
    ``extent (..., 2)`` = (length, width) (m), counter-clockwise from front-left."""
    half_l, half_w = extent[..., 0] / 2, extent[..., 1] / 2
    cos, sin = torch.cos(yaw), torch.sin(yaw)
    signs = torch.tensor([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]], dtype=xy.dtype, device=xy.device)
    local_x = signs[:, 0] * half_l[..., None]  # (..., 4)
    local_y = signs[:, 1] * half_w[..., None]
    x = xy[..., 0:1] + local_x * cos[..., None] - local_y * sin[..., None]
    y = xy[..., 1:2] + local_x * sin[..., None] + local_y * cos[..., None]
    return torch.stack([x, y], -1)


def boxes_overlap(corners_a: torch.Tensor, corners_b: torch.Tensor) -> torch.Tensor:
    """Whether convex quadrilaterals ``(..., 4, 2)`` overlap (touching counts, like shapely ``intersects``).

    Separating-axis test on the two edge normals of each box; returns bool ``(...)``.
    """
    edges = torch.cat([corners_a[..., 1:3, :] - corners_a[..., 0:2, :],
                       corners_b[..., 1:3, :] - corners_b[..., 0:2, :]], -2)
    axes = torch.stack([-edges[..., 1], edges[..., 0]], -1)  # (..., 4, 2) normals
    proj_a = torch.einsum("...kc,...pc->...kp", axes, corners_a)  # (..., 4 axes, 4 corners)
    proj_b = torch.einsum("...kc,...pc->...kp", axes, corners_b)
    separated = (proj_a.amax(-1) < proj_b.amin(-1)) | (proj_b.amax(-1) < proj_a.amin(-1))
    return ~separated.any(-1)


def colliding_pairs(
    xy: torch.Tensor, yaw: torch.Tensor, extent: torch.Tensor, valid: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every pair of valid agents of one scene whose boxes overlap, and when.

    Args:
        xy: ``(B, A, T, 2)`` centres (m); yaw: ``(B, A, T)`` (rad); extent: ``(B, A, 2)`` length, width (m);
        valid: ``(B, A, T)`` bool.

    Returns:
        ``(scene, i, j, step)``, each int64 ``(P,)``: agents ``i < j`` of ``scene`` overlap at ``step``.

    A circumscribed-circle test prunes pairs first, so only nearby pairs reach the exact box test, which runs
    in float64. The pairs are taken ``PAIR_CHUNK_CELLS // (B * T)`` at a time, so memory follows a chunk (and the
    overlaps found), not the ``A^2 T`` pairs of a large scene; the result is the same in the same order.
    """
    b, a, t = valid.shape
    empty = torch.zeros(0, dtype=torch.long, device=xy.device)
    if a < 2:
        return empty, empty, empty, empty
    first, second = torch.triu_indices(a, a, 1, device=xy.device)  # each unordered pair once, (P,)
    chunk = max(1, PAIR_CHUNK_CELLS // max(1, b * t))
    if len(first) <= chunk:
        return _colliding_pairs(xy, yaw, extent, valid, first, second)
    parts = [_colliding_pairs(xy, yaw, extent, valid, first[lo:lo + chunk], second[lo:lo + chunk])
             for lo in range(0, len(first), chunk)]
    scene, i, j, step = (torch.cat([part[k] for part in parts]) for k in range(4))
    # the order of one pass over every pair: by scene, then pair (i, j), then step
    order = torch.argsort(((scene * a + i) * a + j) * t + step)
    return scene[order], i[order], j[order], step[order]


PAIR_CHUNK_CELLS = 1 << 22  # scene x pair x step cells tested at once by colliding_pairs (4 M: tens of MB)


def _colliding_pairs(xy: torch.Tensor, yaw: torch.Tensor, extent: torch.Tensor, valid: torch.Tensor,
                     first: torch.Tensor, second: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`colliding_pairs` over the agent pairs ``(first, second)`` only."""
    # most agent slots are padding or absent: list the pairs valid together first, then prune those by distance
    scene, pair, step = (valid[:, first] & valid[:, second]).nonzero(as_tuple=True)
    i, j = first[pair], second[pair]
    radius = 0.5 * torch.linalg.vector_norm(extent, dim=-1)  # (B, A)
    # the circles touch exactly when two boxes touch corner to corner: a relative slack keeps rounding in the
    # norms from pruning such a pair before the exact test (pruning more loosely only costs a few box tests)
    reach = (radius[scene, i] + radius[scene, j]) * (1 + 1e-5)
    gap = xy[scene, i, step] - xy[scene, j, step]
    near = ((gap * gap).sum(-1) <= reach * reach).nonzero().squeeze(-1)
    scene, i, j, step = scene[near], i[near], j[near], step[near]
    if near.numel() == 0:
        return scene, i, j, step
    # the exact test runs in float64 whatever the input dtype: float32 corners at scene-frame coordinates of a
    # few hundred metres are off by tens of micrometres, enough to flip a near-touching pair
    corners_i = box_corners(xy[scene, i, step].double(), yaw[scene, i, step].double(), extent[scene, i].double())
    corners_j = box_corners(xy[scene, j, step].double(), yaw[scene, j, step].double(), extent[scene, j].double())
    overlap = boxes_overlap(corners_i, corners_j).nonzero().squeeze(-1)
    return scene[overlap], i[overlap], j[overlap], step[overlap]


def pairwise_collisions(
    xy: torch.Tensor, yaw: torch.Tensor, extent: torch.Tensor, valid: torch.Tensor
) -> torch.Tensor:
    """Which agents overlap another valid agent of the same scene at each step.

    Args: as :func:`colliding_pairs`.

    Returns:
        bool ``(B, A, T)``: agent overlaps at least one other valid agent at that step.
    """
    return pair_step_flags(valid, *colliding_pairs(xy, yaw, extent, valid))


def pair_step_flags(valid: torch.Tensor, scene: torch.Tensor, i: torch.Tensor, j: torch.Tensor,
                    step: torch.Tensor) -> torch.Tensor:
    """bool ``(B, A, T)`` shaped as ``valid``: True for both agents of each listed pair ``(scene, i, j, step)``
    (as :func:`colliding_pairs` returns them) at that step."""
    hit = torch.zeros(valid.shape, dtype=torch.bool, device=valid.device)
    hit[scene, i, step] = True
    hit[scene, j, step] = True
    return hit


def path_gaps(xy: torch.Tensor, yaw: torch.Tensor, speed: torch.Tensor, extent: torch.Tensor, valid: torch.Tensor,
              lane_margin_m: float = 0.5) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every other agent as seen along each agent's path: ``(gap, closing, in_path)``, each ``(B, A_self, A_other,
    T)``, from positions ``xy (B, A, T, 2)`` m, headings ``yaw (B, A, T)`` rad, speeds ``(B, A, T)`` m/s, ``extent
    (B, A, 2)`` (length, width) m and ``valid (B, A, T)``.

    The other agent is in the path when its centre lies ahead along the agent's heading and at most half of both
    widths plus ``lane_margin_m`` to the side (both valid, never the agent itself). ``gap`` is bumper to bumper (m:
    the centre distance along the heading less half of both lengths, 0 when they already touch); ``closing`` is
    the agent's speed less the other's velocity along that heading (m/s, positive when closing in)."""
    forward = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)  # (B, A, T, 2)
    offset = xy[:, None] - xy[:, :, None]  # (B, A_self, A_other, T, 2)
    along = (offset * forward[:, :, None]).sum(-1)
    across = (offset[..., 1] * forward[:, :, None, :, 0] - offset[..., 0] * forward[:, :, None, :, 1]).abs()
    width, length = extent[..., 1], extent[..., 0]  # (B, A)
    reach_side = (width[:, :, None] + width[:, None, :]) / 2 + lane_margin_m  # (B, A, A)
    reach_along = (length[:, :, None] + length[:, None, :]) / 2
    others = ~torch.eye(xy.shape[1], dtype=torch.bool, device=xy.device)[None, :, :, None]
    in_path = (along > 0) & (across <= reach_side[..., None]) & valid[:, :, None] & valid[:, None] & others
    other_along = speed[:, None] * torch.cos(yaw[:, None] - yaw[:, :, None])  # the other's speed along my heading
    closing = speed[:, :, None] - other_along
    gap = (along - reach_along[..., None]).clamp_min(0)
    return gap, closing, in_path


def following_gaps(xy: torch.Tensor, yaw: torch.Tensor, speed: torch.Tensor, extent: torch.Tensor,
                   valid: torch.Tensor, lane_margin_m: float = 0.5) -> torch.Tensor:
    """``(B, A, T)`` m: the bumper gap to the nearest agent in each agent's path ahead (:func:`path_gaps`, same
    arguments), ``inf`` where there is none or the agent is not valid."""
    gap, _, in_path = path_gaps(xy, yaw, speed, extent, valid, lane_margin_m)
    gap = torch.where(in_path, gap, torch.full_like(gap, math.inf))
    return gap.amin(2) if gap.shape[2] else torch.full_like(speed, math.inf)


def lane_direction(window: ScenarioTensor, reach_m: float = 2.0, chunk: int = 1 << 21
                    ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Direction ``(K, A, T)`` of the nearest lane-centerline segment within ``reach_m`` of each agent, and where
    there is one (None when the map has no centerlines). Points are compared with segments ``chunk`` pairs at a
    time, so memory stays bounded whatever the size of the map."""
    m = window.map
    k, a, t = window.valid.shape
    lane_yaw = torch.zeros(k, a * t, dtype=torch.float64)
    if m is None or m.polylines is None or m.polyline_type is None or m.polyline_valid is None:
        return lane_yaw.reshape(k, a, t), None
    lanes = m.polyline_type == PolylineType.LANE_CENTER  # (K, P)
    if not bool(lanes.any()):
        return lane_yaw.reshape(k, a, t), None
    found = torch.zeros(k, a * t, dtype=torch.bool)
    pts = m.polylines.double()
    seg_ok = m.polyline_valid[:, :, :-1] & m.polyline_valid[:, :, 1:] & lanes[:, :, None]
    xy = window.xy.double().reshape(k, a * t, 2)
    wanted = window.valid.reshape(k, a * t)
    for scene in range(k):
        seg_a, seg_b = pts[scene, :, :-1][seg_ok[scene]], pts[scene, :, 1:][seg_ok[scene]]  # (S, 2)
        points = wanted[scene].nonzero().flatten()
        if len(seg_a) == 0 or len(points) == 0:
            continue
        d = seg_b - seg_a
        length2 = (d * d).sum(-1).clamp_min(1e-9)
        step = max(1, chunk // len(seg_a))
        for lo in range(0, len(points), step):
            idx = points[lo:lo + step]
            rel = xy[scene, idx, None] - seg_a[None]  # (n, S, 2)
            u = ((rel * d[None]).sum(-1) / length2).clamp(0, 1)
            dist = torch.linalg.vector_norm(rel - u[..., None] * d[None], dim=-1)
            best, index = dist.min(-1)
            lane_yaw[scene, idx] = torch.atan2(d[index, 1], d[index, 0])
            found[scene, idx] = best <= reach_m
    return lane_yaw.reshape(k, a, t), found.reshape(k, a, t)
