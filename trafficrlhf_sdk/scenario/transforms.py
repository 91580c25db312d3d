"""Geometric transforms of whole scenes that keep every agent, the map and the metrics consistent."""

from __future__ import annotations

import dataclasses

import torch

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["MIRROR_SUFFIX", "mirror_scenario", "perturb_history"]

MIRROR_SUFFIX = "~mirror"
"""Appended to the scene ids of a mirrored scenario, so a mirrored scene never passes for its original."""


def mirror_scenario(scenario: ScenarioTensor) -> ScenarioTensor:
    """The scenes reflected across their scene frame's x axis: ``y -> -y``, ``yaw -> -yaw``.

    Shapes are unchanged (``states (B, A, T, 4)``: x, y m; speed m/s; yaw rad). The map raster is kept as is and
    ``world_to_pixel`` composed with the reflection, so a mirrored point reads the pixel its original read; the
    vector map (if any) is reflected too. Distances, speeds, box overlaps and drivable-area membership are those of
    the original scene; turns change sign and right-hand traffic becomes left-hand traffic (nuScenes holds both:
    Boston and Singapore). Used to show a fine-tuner roads its base model never imitated
    (``AlignConfig.mirror_scenes``). Mirroring twice gives the original back (ids included).
    """
    states = scenario.states.clone()
    states[..., 1] = -states[..., 1]
    yaw = -states[..., 3]
    states[..., 3] = torch.where(yaw >= torch.pi, yaw - 2 * torch.pi, yaw)  # keep [-pi, pi): -(-pi) = pi wraps
    states = states * scenario.valid[..., None]
    changes: dict = {"states": states}
    if scenario.map is not None:
        m = scenario.map
        flip = torch.diag(torch.tensor([1.0, -1.0, 1.0], dtype=m.world_to_pixel.dtype, device=m.world_to_pixel.device))
        map_changes: dict = {"world_to_pixel": (m.world_to_pixel @ flip).contiguous()}
        if m.polylines is not None:
            polylines = m.polylines.clone()
            polylines[..., 1] = -polylines[..., 1]
            map_changes["polylines"] = polylines * m.polyline_valid[..., None]
        changes["map"] = dataclasses.replace(m, **map_changes)
    if scenario.origin is not None:
        origin = scenario.origin.clone()
        origin[:, 1] = -origin[:, 1]
        changes["origin"] = origin
    changes["scene_ids"] = tuple(s[: -len(MIRROR_SUFFIX)] if s.endswith(MIRROR_SUFFIX) else s + MIRROR_SUFFIX
                                 for s in scenario.scene_ids)
    return dataclasses.replace(scenario, **changes)


def perturb_history(scenario: ScenarioTensor, lateral: torch.Tensor, turn: torch.Tensor) -> ScenarioTensor:
    """Each agent's states up to ``current_index`` moved rigidly: rotated by ``turn`` about its position now and
    shifted ``lateral`` across its heading now (positive: to its left).

    ``lateral`` (m) and ``turn`` (rad) are ``(B, A)``; zeros leave an agent as logged. Speeds, validity and the
    steps after ``current_index`` are unchanged, so a perturbed agent's history ends off its logged path while its
    logged future still starts on it (a context for learning to recover; ``AlignConfig.perturb_fraction``).
    An agent not valid now is left as is.
    """
    shape = tuple(scenario.controlled.shape)
    for name, value in (("lateral", lateral), ("turn", turn)):
        if tuple(value.shape) != shape:
            raise ValueError(f"`{name}` has shape {tuple(value.shape)}; give one value per agent slot, {shape} "
                             "(batch, agents).")
    now = scenario.current_index
    movable = scenario.valid[:, :, now]
    dtype = scenario.states.dtype
    lateral, turn = lateral.to(dtype), turn.to(dtype)
    past = scenario.states[:, :, : now + 1]
    pivot = past[:, :, now, :2]  # (B, A, 2)
    yaw_now = past[:, :, now, 3]
    cos, sin = torch.cos(turn)[..., None], torch.sin(turn)[..., None]  # (B, A, 1)
    rel = past[..., :2] - pivot[:, :, None]
    rotated = torch.stack([cos * rel[..., 0] - sin * rel[..., 1], sin * rel[..., 0] + cos * rel[..., 1]], -1)
    normal = torch.stack([-torch.sin(yaw_now), torch.cos(yaw_now)], -1)  # left of the heading now
    # added as a displacement, not as pivot + rotated: far from the origin the round trip would lose float32 bits
    xy = past[..., :2] + (rotated - rel) + (lateral[..., None] * normal)[:, :, None]
    yaw = wrap_angle(past[..., 3] + turn[..., None])
    moved_past = torch.cat([xy, past[..., 2:3], yaw[..., None]], -1)
    # agents not valid now keep their states bit for bit (a zero move would still round them)
    moved_past = torch.where(movable[:, :, None, None], moved_past, past) * scenario.valid[:, :, : now + 1, None]
    states = torch.cat([moved_past, scenario.states[:, :, now + 1 :]], 2)
    return dataclasses.replace(scenario, states=states)
