"""Per-(agent, step) inputs of the CTG-style reward model, computed once and reused across training epochs.

A reward model scores a scenario step by step. For every selected agent ``a`` and scored step ``t`` it sees, in
the agent's own frame at ``t`` (origin at its position, x along its heading):

- its own recent motion: the states at ``t - k * stride`` for ``k = 1 .. history_steps`` (x, y, speed, cos and
  sin of the heading change, a valid flag), its speed at ``t`` and its box length and width, and the
  longitudinal acceleration, lateral acceleration and jerk over the last ``step_dt`` intervals and the two
  accelerations over the last two (/ 3 m/s^2, 3 m/s^3);
- whether it collided with another agent (exact box overlap) or had its centre off the drivable layer at any
  step of the scenario since the previous scored step, so events between two 2 Hz samples are not missed;
- its speed at the scenario's ``current_index`` ("now", when the candidates start), so stalling is visible;
- the ``num_neighbours`` nearest other agents valid at ``t`` within ``neighbour_radius_m``: whether its box
  overlaps the agent's (exact separating-axis test) and a valid flag. Continuous neighbour inputs (coordinates,
  gaps, closing speeds) differ between any two candidates, so they let the model memorise the random labels of
  equally good candidates: with them, held-out accuracy against a noise-free annotator dropped by 5-10 points;
- whether its centre and its four box corners lie on the drivable layer, and whether a map is present;
- with ``scene_context``, what an annotator sees around it since the candidates started: events between the 2 Hz
  samples, pace against its own history, its lead and its neighbours' flow, and lateral and longitudinal
  reversals (:mod:`~trafficrlhf_sdk.reward.scene_context`);
- a map crop ``(C, S, S)`` around it (``S = crop_size``), sampled on a grid ``crop_supersample`` times finer
  and stored as the count of "on" sub-cells per cell (uint8), so the crop costs one byte per cell.

Positions and distances are divided by 10 m, speeds by 10 m/s and box sizes by 5 m. Everything is packed in a
:class:`StepInputs`: flat tensors over the selected items with their scene and step indices, sorted by scene,
which :meth:`StepInputs.select` slices by scene without copying the whole set.
"""

from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Sequence

import torch

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_per_step
from trafficrlhf_sdk.metrics.geometry import box_corners, boxes_overlap
from trafficrlhf_sdk.reward.scene_context import NUM_SCENE_CONTEXT_FEATURES, scene_context_features
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["FeatureSpec", "StepInputs", "compute_step_inputs", "scored_steps", "selected_agents"]

POS_SCALE = 10.0  # m
SPEED_SCALE = 10.0  # m/s
SIZE_SCALE = 5.0  # m
ACCEL_SCALE = 3.0  # m/s^2 and m/s^3: the synthetic annotator's plausible bounds


@dataclass(frozen=True)
class FeatureSpec:
    """What :func:`compute_step_inputs` extracts (a copy of the architecture's settings)."""

    step_dt: float = 0.5
    history_steps: int = 4
    num_neighbours: int = 6
    neighbour_radius_m: float = 40.0
    crop_size: int = 16
    crop_resolution_m: float = 1.0
    crop_supersample: int = 2
    crop_behind_fraction: float = 0.25
    map_layers: tuple[str, ...] = ("drivable", "road_divider", "lane_divider")
    agents: str = "controlled"
    scene_context: bool = False

    @property
    def num_features(self) -> int:
        """Length of the flat feature vector (crops excluded)."""
        extra = NUM_SCENE_CONTEXT_FEATURES if self.scene_context else 0
        return 6 * self.history_steps + 3 + 5 + 2 + 2 * self.num_neighbours + 6 + 2 + extra


@dataclass(frozen=True)
class StepInputs:
    """Flat per-(agent, step) inputs of a batch of B scenes with T steps each.

    Fields:
        features: float32 ``(N, F)``; crops: uint8 ``(N, C, S, S)`` (counts of "on" sub-cells, see ``crop_max``);
        scene: int64 ``(N,)`` scene index in ``0 .. B-1`` (non-decreasing); step: int64 ``(N,)`` step in
        ``0 .. T-1``; num_scenes B; num_steps T; crop_max: the count that means "fully on".
    """

    features: torch.Tensor
    crops: torch.Tensor
    scene: torch.Tensor
    step: torch.Tensor
    num_scenes: int
    num_steps: int
    crop_max: int

    def __len__(self) -> int:
        return int(self.scene.shape[0])

    def select(self, scenes: torch.Tensor | Sequence[int]) -> StepInputs:
        """The items of ``scenes`` (repeats allowed), renumbered ``0 .. len(scenes)-1`` in the given order."""
        scenes = torch.as_tensor(scenes, dtype=torch.long)
        counts = torch.bincount(self.scene, minlength=self.num_scenes)
        offsets = torch.cumsum(counts, 0) - counts
        lengths = counts[scenes]
        total = int(lengths.sum())
        starts = torch.repeat_interleave(offsets[scenes], lengths)
        within = torch.arange(total) - torch.repeat_interleave(torch.cumsum(lengths, 0) - lengths, lengths)
        index = starts + within
        return StepInputs(self.features[index], self.crops[index],
                          torch.repeat_interleave(torch.arange(len(scenes)), lengths), self.step[index],
                          len(scenes), self.num_steps, self.crop_max)

    @staticmethod
    def concat(parts: Sequence[StepInputs]) -> StepInputs:
        """Stack along the scene axis (steps padded to the largest T)."""
        shift = torch.cumsum(torch.tensor([0] + [p.num_scenes for p in parts[:-1]]), 0)
        return StepInputs(torch.cat([p.features for p in parts]), torch.cat([p.crops for p in parts]),
                          torch.cat([p.scene + int(s) for p, s in zip(parts, shift, strict=True)]),
                          torch.cat([p.step for p in parts]), sum(p.num_scenes for p in parts),
                          max(p.num_steps for p in parts), parts[0].crop_max)

    @property
    def device(self) -> torch.device:
        """Where the inputs are."""
        return self.features.device

    def to(self, device: torch.device | str) -> StepInputs:
        """The same inputs on ``device``."""
        return StepInputs(self.features.to(device), self.crops.to(device), self.scene.to(device),
                          self.step.to(device), self.num_scenes, self.num_steps, self.crop_max)


def selected_agents(scenario: ScenarioTensor, mode: str) -> torch.Tensor:
    """Agents whose rewards are averaged, bool ``(B, A)``.

    ``"controlled"``: the controlled agents of each scene that has any (the agents a traffic model drove; the
    others replay the log and are the same in every candidate), all agents of a scene that has none.
    ``"all"``: every agent.
    """
    every = scenario.valid.any(-1)
    if mode == "all":
        return every
    if mode != "controlled":
        raise ValueError(f"`agents` must be 'controlled' or 'all'; got {mode!r}.")
    controlled = scenario.controlled & every
    return torch.where(controlled.any(-1, keepdim=True), controlled, every)


def stride_of(scenario: ScenarioTensor, step_dt: float) -> int:
    """Steps of ``scenario`` per reward step (at least 1)."""
    return max(1, round(step_dt / scenario.dt))


def scored_steps(scenario: ScenarioTensor, step_dt: float) -> torch.Tensor:
    """The steps a scenario's score averages (int64): the future, ``current_index + stride, + 2 stride, ...``.

    "Now" is left out (it is shared by every candidate of a context); a scenario that ends at ``current_index``
    is scored at that step alone.
    """
    stride = stride_of(scenario, step_dt)
    first = scenario.current_index + stride
    if first >= scenario.num_steps:
        return torch.tensor([scenario.current_index])
    return torch.arange(first, scenario.num_steps, stride)


def _rotate(dx: torch.Tensor, dy: torch.Tensor, yaw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    cos, sin = torch.cos(yaw), torch.sin(yaw)
    return cos * dx + sin * dy, -sin * dx + cos * dy


def _crops(scenario: ScenarioTensor, spec: FeatureSpec, scene: torch.Tensor, pose: torch.Tensor,
           chunk: int = 4096) -> torch.Tensor:
    """uint8 ``(N, C, S, S)``: per item, the count of sub-cells on each layer (``crop_supersample ** 2`` = full)."""
    n, c, s, ss = len(scene), len(spec.map_layers), spec.crop_size, spec.crop_supersample
    out = torch.zeros(n, c, s, s, dtype=torch.uint8)
    scenario_map = scenario.map
    if scenario_map is None or n == 0:
        return out
    channels = [(k, scenario_map.layers.index(name)) for k, name in enumerate(spec.map_layers)
                if name in scenario_map.layers]
    if not channels:
        return out
    fine = s * ss
    cell = spec.crop_resolution_m / ss
    behind = spec.crop_behind_fraction * s * spec.crop_resolution_m
    ahead = (torch.arange(fine, dtype=torch.float64) + 0.5) * cell - behind
    left = (torch.arange(fine, dtype=torch.float64) + 0.5) * cell - s * spec.crop_resolution_m / 2
    gx, gy = torch.meshgrid(ahead, left, indexing="ij")
    gx, gy = gx.reshape(1, -1), gy.reshape(1, -1)
    layer_index = [src for _, src in channels]
    for lo in range(0, n, chunk):
        b = scene[lo:lo + chunk]
        p = pose[lo:lo + chunk].double()
        cos, sin = torch.cos(p[:, 2:3]), torch.sin(p[:, 2:3])
        x = p[:, 0:1] + cos * gx - sin * gy
        y = p[:, 1:2] + sin * gx + cos * gy
        m = scenario_map.world_to_pixel[b].double()
        i = torch.floor(m[:, 0, 0:1] * x + m[:, 0, 1:2] * y + m[:, 0, 2:3]).long()
        j = torch.floor(m[:, 1, 0:1] * x + m[:, 1, 1:2] * y + m[:, 1, 2:3]).long()
        values = scenario_map.read(b[:, None], i, j, layer_index).transpose(0, 1) > 0  # (n, C', fine*fine)
        pooled = values.reshape(-1, len(channels), s, ss, s, ss).sum((3, 5), dtype=torch.int32).to(torch.uint8)
        out[lo:lo + chunk, [k for k, _ in channels]] = pooled
    return out


def compute_step_inputs(scenario: ScenarioTensor, spec: FeatureSpec, steps: torch.Tensor | None = None) -> StepInputs:
    """Inputs of every selected agent (see :func:`selected_agents`) at ``steps`` (default :func:`scored_steps`).

    Args:
        scenario: B scenes ``(B, A, T)``.
        spec: what to extract.
        steps: int64 step indices into T; an item exists where the agent is valid at that step.
    """
    steps = scored_steps(scenario, spec.step_dt) if steps is None else torch.as_tensor(steps, dtype=torch.long)
    states, valid = scenario.states, scenario.valid
    b_, a_, t_ = valid.shape
    chosen = selected_agents(scenario, spec.agents)
    item_mask = valid[:, :, steps] & chosen[:, :, None]  # (B, A, S)
    scene, agent, slot = item_mask.nonzero(as_tuple=True)  # sorted by scene
    step = steps[slot]
    pose = states[scene, agent, step]  # (N, 4)
    x, y, v, yaw = pose.unbind(-1)
    stride = stride_of(scenario, spec.step_dt)
    parts = []
    window = []  # (speed, yaw, ok) at t - k * stride, k = 0 .. 2, for the kinematic features
    for k in range(0, max(spec.history_steps, 2) + 1):
        past = step - k * stride
        ok = (past >= 0) & valid[scene, agent, past.clamp_min(0)]
        st = states[scene, agent, past.clamp_min(0)]
        px, py = _rotate(st[:, 0] - x, st[:, 1] - y, yaw)
        dyaw = wrap_angle(st[:, 3] - yaw)
        okf = ok.float()
        if k <= 2:
            window.append((st[:, 2], st[:, 3], ok))
        if k == 0 or k > spec.history_steps:
            continue
        parts += [px / POS_SCALE * okf, py / POS_SCALE * okf, st[:, 2] / SPEED_SCALE * okf, torch.cos(dyaw) * okf,
                  torch.sin(dyaw) * okf, okf]
    extent = scenario.extent[scene, agent]
    parts += [v / SPEED_SCALE, extent[:, 0] / SIZE_SCALE, extent[:, 1] / SIZE_SCALE]
    interval = stride * scenario.dt
    (v0, y0, ok0), (v1, y1, ok1), (v2, _, ok2) = window
    acc_ok, jerk_ok = (ok0 & ok1).float(), (ok0 & ok1 & ok2).float()
    lon = (v0 - v1) / interval
    lat = v0 * wrap_angle(y0 - y1) / interval
    jerk = (v0 - 2 * v1 + v2) / interval**2
    lon2 = (v0 - v2) / (2 * interval)
    lat2 = v0 * wrap_angle(y0 - window[2][1]) / (2 * interval)
    parts += [(lon * acc_ok / ACCEL_SCALE).clamp(-5, 5), (lat * acc_ok / ACCEL_SCALE).clamp(-5, 5),
              (jerk * jerk_ok / ACCEL_SCALE).clamp(-5, 5), (lon2 * jerk_ok / ACCEL_SCALE).clamp(-5, 5),
              (lat2 * jerk_ok / ACCEL_SCALE).clamp(-5, 5)]
    now_ok = valid[scene, agent, scenario.current_index].float()
    parts += [states[scene, agent, scenario.current_index, 2] / SPEED_SCALE * now_ok, now_ok]
    # neighbours: all other agents valid at the item's step, nearest first
    others = states[scene, :, step]  # (N, A, 4)
    others_ok = valid[scene, :, step] & (torch.arange(a_)[None] != agent[:, None])
    rx, ry = _rotate(others[..., 0] - x[:, None], others[..., 1] - y[:, None], yaw[:, None])
    dist = torch.sqrt(rx * rx + ry * ry)
    others_ok &= dist <= spec.neighbour_radius_m
    k = min(spec.num_neighbours, a_)
    # ties by agent index (a stable sort), so appended padding agents cannot reorder equally near neighbours
    nearest = torch.where(others_ok, dist, torch.full_like(dist, float("inf")))
    order = torch.sort(nearest, dim=1, stable=True).indices[:, :k]
    pick = lambda t: t.gather(1, order)  # noqa: E731
    n_ok = pick(others_ok).float()
    ryaw = wrap_angle(others[..., 3] - yaw[:, None])
    o_ext = scenario.extent[scene]  # (N, A, 2)
    n_ext = torch.stack([pick(o_ext[..., 0]), pick(o_ext[..., 1])], -1)  # (N, k, 2)
    n_x, n_y, n_yaw = pick(rx), pick(ry), pick(ryaw)
    own = box_corners(torch.zeros(len(scene), 1, 2, dtype=torch.float64), torch.zeros(len(scene), 1,
                      dtype=torch.float64), extent[:, None].double())
    overlap = boxes_overlap(own.expand(-1, k, -1, -1), box_corners(torch.stack([n_x, n_y], -1).double(),
                                                                   n_yaw.double(), n_ext.double()))
    neighbour = torch.stack([overlap.float() * n_ok, n_ok], -1)  # (N, k, 2)
    if k < spec.num_neighbours:
        neighbour = torch.nn.functional.pad(neighbour, (0, 0, 0, spec.num_neighbours - k))  # missing: all zero
    # drivable lookups at the centre and the four box corners
    lookups = torch.zeros(len(scene), 6)
    if scenario.map is not None and "drivable" in scenario.map.layers and len(scene):
        half_l, half_w = extent[:, 0:1].double() / 2, extent[:, 1:2].double() / 2
        lon = torch.cat([torch.zeros_like(half_l), half_l, half_l, -half_l, -half_l], 1)
        lat = torch.cat([torch.zeros_like(half_w), half_w, -half_w, half_w, -half_w], 1)
        c, s = torch.cos(yaw.double())[:, None], torch.sin(yaw.double())[:, None]
        pts = torch.stack([x.double()[:, None] + c * lon - s * lat, y.double()[:, None] + s * lon + c * lat], -1)
        on = scenario.map.lookup_points(scene.repeat_interleave(5), pts.reshape(-1, 2)).reshape(-1, 5)
        lookups = torch.cat([on.float(), torch.ones(len(scene), 1)], 1)
    # events at any step since the previous scored one (the 10 Hz steps a 2 Hz sample would skip)
    events = [collisions_per_step(scenario)]
    has_drivable = scenario.map is not None and "drivable" in scenario.map.layers
    events.append(offroad_per_step(scenario) if has_drivable else torch.zeros_like(valid))
    recent = []
    for event in events:
        counts = torch.nn.functional.pad(torch.cumsum(event.long(), -1), (1, 0))  # (B, A, T + 1)
        lo = (step - stride + 1).clamp_min(0)
        recent.append(((counts[scene, agent, step + 1] - counts[scene, agent, lo]) > 0).float())
    features = torch.cat([torch.stack(parts + recent, -1), neighbour.flatten(1), lookups], -1).float()
    if spec.scene_context:
        features = torch.cat([features, scene_context_features(scenario, scene, agent, step, stride)], -1)
    crops = _crops(scenario, spec, scene, torch.stack([x, y, yaw], -1))
    return StepInputs(features.contiguous(), crops, scene, step, b_, t_, spec.crop_supersample ** 2)
