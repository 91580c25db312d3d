"""Oriented-box geometry, batched: corners and separating-axis overlap tests."""

from __future__ import annotations

import torch

__all__ = ["box_corners", "boxes_overlap", "colliding_pairs", "pairwise_collisions"]


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
    in float64.
    """
    a = valid.shape[1]
    empty = torch.zeros(0, dtype=torch.long, device=xy.device)
    if a < 2:
        return empty, empty, empty, empty
    first, second = torch.triu_indices(a, a, 1, device=xy.device)  # each unordered pair once, (P,)
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
    hit = torch.zeros(valid.shape, dtype=torch.bool, device=xy.device)
    scene, i, j, step = colliding_pairs(xy, yaw, extent, valid)
    hit[scene, i, step] = True
    hit[scene, j, step] = True
    return hit
