"""Agent-centric inputs that most traffic models share: map crops, history and neighbours in each agent's frame.

Every function takes a :class:`ScenarioTensor` ``context`` whose ``current_index`` is "now" and returns
tensors with leading dims ``(B, A)``. The agent frame has its origin at the agent's current position and its x
axis along the agent's current heading.
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["agent_poses", "from_agent_frame", "history_features", "map_crops", "neighbour_features", "to_agent_frame"]


def agent_poses(context: ScenarioTensor) -> torch.Tensor:
    """Current pose ``(B, A, 3)``: x, y (m, scene frame), yaw (rad)."""
    now = context.states[:, :, context.current_index]
    return torch.stack([now[..., 0], now[..., 1], now[..., 3]], -1)


def to_agent_frame(xy: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Scene-frame points ``(B, A, ..., 2)`` into the frame of ``pose (B, A, 3)``."""
    extra = xy.dim() - 3
    shape = pose.shape[:2] + (1,) * extra
    cos, sin = torch.cos(pose[..., 2]).reshape(shape), torch.sin(pose[..., 2]).reshape(shape)
    dx = xy[..., 0] - pose[..., 0].reshape(shape)
    dy = xy[..., 1] - pose[..., 1].reshape(shape)
    return torch.stack([cos * dx + sin * dy, -sin * dx + cos * dy], -1)


def from_agent_frame(xy: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Agent-frame points ``(B, A, ..., 2)`` back into the scene frame."""
    extra = xy.dim() - 3
    shape = pose.shape[:2] + (1,) * extra
    cos, sin = torch.cos(pose[..., 2]).reshape(shape), torch.sin(pose[..., 2]).reshape(shape)
    x = pose[..., 0].reshape(shape) + cos * xy[..., 0] - sin * xy[..., 1]
    y = pose[..., 1].reshape(shape) + sin * xy[..., 0] + cos * xy[..., 1]
    return torch.stack([x, y], -1)


def history_features(context: ScenarioTensor, num_steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The last ``num_steps`` steps up to now, in the agent frame.

    Returns:
        features ``(B, A, num_steps, 5)``: x, y (m), speed (m/s), cos and sin of the yaw relative to now;
        valid ``(B, A, num_steps)``. Steps before the scene start are invalid (zeros).
    """
    end = context.current_index + 1
    start = end - num_steps
    states = context.states[:, :, max(start, 0) : end]
    valid = context.valid[:, :, max(start, 0) : end]
    if start < 0:
        states = torch.nn.functional.pad(states, (0, 0, -start, 0))
        valid = torch.nn.functional.pad(valid, (-start, 0))
    pose = agent_poses(context)
    local = to_agent_frame(states[..., :2], pose)
    rel_yaw = states[..., 3] - pose[..., 2:3]
    features = torch.cat([local, states[..., 2:3], torch.cos(rel_yaw)[..., None], torch.sin(rel_yaw)[..., None]], -1)
    return features * valid[..., None], valid


def neighbour_features(context: ScenarioTensor, num_neighbours: int, radius_m: float = 50.0,
                       return_index: bool = False) -> tuple[torch.Tensor, ...]:
    """The nearest ``num_neighbours`` other agents valid now, in each agent's frame.

    Returns:
        features ``(B, A, K, 7)``: x, y (m), cos and sin of relative yaw, speed (m/s), length, width (m);
        valid ``(B, A, K)`` (False for missing neighbours and those beyond ``radius_m``); with ``return_index``
        also the neighbours' agent slots ``(B, A, K)`` long (arbitrary where not valid).
    """
    now = context.states[:, :, context.current_index]
    valid_now = context.valid[:, :, context.current_index]
    pose = agent_poses(context)
    b, a = valid_now.shape
    rel = to_agent_frame(now[:, None, :, :2].expand(b, a, a, 2), pose)  # (B, A, A, 2): agent j in frame of i
    dist = torch.linalg.vector_norm(rel, dim=-1)
    usable = valid_now[:, None, :] & valid_now[:, :, None] & ~torch.eye(a, dtype=torch.bool, device=now.device)
    usable &= dist <= radius_m
    k = min(num_neighbours, a)
    score = torch.where(usable, dist, torch.full_like(dist, float("inf")))
    order = score.topk(k, dim=-1, largest=False).indices  # (B, A, K)
    picked_valid = usable.gather(2, order)
    rel_yaw = wrap_angle(now[..., 3][:, None, :] - pose[..., 2:3])  # (B, A, A)
    gather = lambda t: t.gather(2, order)  # noqa: E731
    features = torch.stack(
        [
            gather(rel[..., 0]),
            gather(rel[..., 1]),
            gather(torch.cos(rel_yaw)),
            gather(torch.sin(rel_yaw)),
            gather(now[..., 2][:, None, :].expand(b, a, a)),
            gather(context.extent[..., 0][:, None, :].expand(b, a, a)),
            gather(context.extent[..., 1][:, None, :].expand(b, a, a)),
        ],
        -1,
    )
    if k < num_neighbours:
        features = torch.nn.functional.pad(features, (0, 0, 0, num_neighbours - k))
        picked_valid = torch.nn.functional.pad(picked_valid, (0, num_neighbours - k))
        order = torch.nn.functional.pad(order, (0, num_neighbours - k))
    if return_index:
        return features * picked_valid[..., None], picked_valid, order
    return features * picked_valid[..., None], picked_valid


def map_crops(
    context: ScenarioTensor, size_px: int = 48, resolution_m: float = 1.0, behind_fraction: float = 0.25,
    agents: torch.Tensor | None = None,
) -> torch.Tensor:
    """Map layers around each agent, rotated into its frame (nearest-pixel sampling).

    Cell ``(u, v)`` of the crop shows agent-frame point ``x = (u - behind_fraction*size_px + 0.5)*res`` (ahead
    along rows), ``y = (v - size_px/2 + 0.5)*res`` (to the left along columns).

    ``agents``: optional bool ``(B, A)``: crop only these agent slots (the others are 0), which costs in
    proportion to them rather than to every slot; their crops equal those of the full call.

    Returns:
        float32 ``(B, A, C, size_px, size_px)`` in {0, 1}; cells outside the raster are 0.
    """
    if context.map is None:
        raise ValueError("map_crops needs `context.map`; load scenes from a source that provides rasters.")
    scene_map = context.map
    c = len(scene_map.layers)
    b, a = context.num_scenes, context.num_agents
    cells = torch.arange(size_px, device=scene_map.pixels.device, dtype=torch.float32)
    local_x = (cells - behind_fraction * size_px + 0.5) * resolution_m
    local_y = (cells - size_px / 2 + 0.5) * resolution_m
    grid = torch.stack(torch.meshgrid(local_x, local_y, indexing="ij"), -1)  # (S, S, 2)
    if agents is None:
        points = from_agent_frame(grid.reshape(1, 1, -1, 2).expand(b, a, -1, 2), agent_poses(context))
        ij = torch.floor(scene_map.to_pixel(points)).long()  # (B, A, S*S, 2)
        scene = torch.arange(b, device=ij.device)[:, None, None]
        values = scene_map.read(scene, ij[..., 0], ij[..., 1])  # (C, B, A, S*S), 0 outside the raster
        return values.permute(1, 2, 0, 3).float().reshape(b, a, c, size_px, size_px)
    scene, slot = agents.nonzero(as_tuple=True)
    n = len(scene)
    pose = agent_poses(context)[scene, slot][:, None]  # (N, 1, 3): one "scene" per row, one agent
    points = from_agent_frame(grid.reshape(1, 1, -1, 2).expand(n, 1, -1, 2), pose)[:, 0]  # (N, S*S, 2)
    m = scene_map.world_to_pixel.to(points.dtype)[scene]  # the scene's transform, as MapRaster.to_pixel
    ij = torch.floor(torch.einsum("bkc,bnc->bnk", m[:, :2, :2], points) + m[:, None, :2, 2]).long()
    values = scene_map.read(scene[:, None], ij[..., 0], ij[..., 1])  # (C, N, S*S)
    crops = values.permute(1, 0, 2).float().reshape(n, c, size_px, size_px)
    out = crops.new_zeros(b, a, c, size_px, size_px)
    out[scene, slot] = crops
    return out
