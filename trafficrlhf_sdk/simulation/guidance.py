"""CTG's five guidance objectives as batched, differentiable losses, with the heuristics that derive their targets
from the logged scene (facts: shared/reference/upstream-models-and-metrics.md §1.4).

A guidance is first ``fit`` on the logged scenario (targets per scene/agent), then scores candidate futures:
``loss(futures, now) -> (B, S, A)`` for futures ``(B, S, A, H, 4)`` in the scene frame starting at step
``now + 1``. Any adapter can use the losses for gradient perturbation (:func:`perturb_with_guidance`) or for
sample filtering (:func:`select_samples`). ``objective(rollout)`` is the matching evaluation metric.
"""

from __future__ import annotations

import abc
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import ClassVar

import torch

from trafficrlhf_sdk.errors import UnknownComponentError
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = [
    "GUIDANCE_CLASSES",
    "GoalWaypointGuidance",
    "Guidance",
    "GuidanceSet",
    "NoCollisionGuidance",
    "NoOffroadGuidance",
    "SpeedLimitGuidance",
    "TargetSpeedGuidance",
    "guidance_swapped",
    "make_guidance",
    "perturb_with_guidance",
    "select_samples",
]


def _time_weights(h: int, decay: float, device: torch.device) -> torch.Tensor:
    w = decay ** torch.arange(h, dtype=torch.float32, device=device)
    return w / w.sum()


class Guidance(abc.ABC):
    """One objective. ``weight`` scales it inside a :class:`GuidanceSet`."""

    name: ClassVar[str] = ""
    scene_level: ClassVar[bool] = False  # True: samples must be chosen jointly for the whole scene

    def __init__(self, weight: float = 1.0) -> None:
        self.weight = weight
        self.log: ScenarioTensor | None = None

    def fit(self, scenario: ScenarioTensor) -> Guidance:
        """Derive targets from the logged ``scenario`` (its ``current_index`` is the rollout start)."""
        self.log = scenario
        return self

    @abc.abstractmethod
    def loss(self, futures: torch.Tensor, now: int, context: ScenarioTensor) -> torch.Tensor:
        """Per-agent loss ``(B, S, A)`` of candidate futures ``(B, S, A, H, 4)`` that start at step ``now + 1``."""

    def objective(self, simulated: ScenarioTensor, controlled: torch.Tensor, start: int, end: int) -> float:
        """The guidance metric on a rollout (lower is better): mean over controlled agents of the loss of the
        executed trajectory, steps ``start+1 .. end``."""
        executed = simulated.states[:, :, start + 1 : end + 1][:, None]  # (B, 1, A, T, 4)
        with torch.no_grad():
            per_agent = self.loss(executed, start, simulated)[:, 0]
        return float(per_agent[controlled].mean()) if controlled.any() else float("nan")


class SpeedLimitGuidance(Guidance):
    """Penalize speed above a limit: ``mean_t relu(|v_t| - v_lim)``.

    Heuristic limit per scene: the 0.75 quantile of logged future speeds above 1 m/s over 20 s (1 m/s if none).
    """

    name = "speed_limit"

    def __init__(self, weight: float = 1.0, limit: float | None = None, quantile: float = 0.75) -> None:
        super().__init__(weight)
        self.fixed_limit, self.quantile = limit, quantile

    def fit(self, scenario: ScenarioTensor) -> Guidance:
        """Per-scene limit ``(B,)`` in m/s."""
        super().fit(scenario)
        if self.fixed_limit is not None:
            self.limit = torch.full((scenario.num_scenes,), float(self.fixed_limit), device=scenario.device)
            return self
        now = scenario.current_index
        window = slice(now + 1, now + 1 + round(20.0 / scenario.dt))
        speeds, valid = scenario.speed[:, :, window].abs(), scenario.valid[:, :, window]
        limits = []
        for b in range(scenario.num_scenes):
            fast = speeds[b][valid[b] & (speeds[b] > 1.0)]
            limits.append(float(torch.quantile(fast, self.quantile)) if fast.numel() else 1.0)
        self.limit = torch.tensor(limits, device=scenario.device)
        return self

    def loss(self, futures: torch.Tensor, now: int, context: ScenarioTensor) -> torch.Tensor:
        """``(B, S, A)`` mean excess speed (m/s)."""
        excess = torch.relu(futures[..., 2].abs() - self.limit.to(futures)[:, None, None, None])
        return excess.mean(-1)


class TargetSpeedGuidance(Guidance):
    """Track the logged speed of each agent: ``mean_t |v_t - v*_{now+t}|`` (steps without a target count 0)."""

    name = "target_speed"

    def fit(self, scenario: ScenarioTensor) -> Guidance:
        """Targets are the logged speeds ``(B, A, T)``."""
        super().fit(scenario)
        self.target = scenario.speed.abs()
        self.target_valid = scenario.valid
        return self

    def loss(self, futures: torch.Tensor, now: int, context: ScenarioTensor) -> torch.Tensor:
        """``(B, S, A)`` mean absolute speed error (m/s)."""
        h = futures.shape[-2]
        target = self.target[:, :, now + 1 : now + 1 + h].to(futures)
        mask = self.target_valid[:, :, now + 1 : now + 1 + h]
        if target.shape[-1] < h:  # beyond the log: no target
            pad = h - target.shape[-1]
            target, mask = torch.nn.functional.pad(target, (0, pad)), torch.nn.functional.pad(mask, (0, pad))
        error = (futures[..., 2].abs() - target[:, None]).abs() * mask[:, None]
        return error.mean(-1)


class NoCollisionGuidance(Guidance):
    """Disk-based collision penalty (CTG ``AgentCollisionLoss``): each box is covered by ``num_disks`` disks of
    radius width/2; a pair closer than ``r_i + r_j + buffer`` costs ``1 - d / (r_i + r_j + buffer)``; steps are
    weighted by ``decay**t`` (normalized); the loss is the mean over other agents. Other agents follow their own
    candidate (same sample index) when controlled, else the log. Selection is scene-level."""

    name = "no_collision"
    scene_level = True

    def __init__(self, weight: float = 1.0, num_disks: int = 2, buffer_m: float = 0.2, decay: float = 0.9) -> None:
        super().__init__(weight)
        self.num_disks, self.buffer_m, self.decay = num_disks, buffer_m, decay

    def loss(self, futures: torch.Tensor, now: int, context: ScenarioTensor) -> torch.Tensor:
        """``(B, S, A)`` weighted mean pairwise penalty (0 = no near-collision)."""
        b, s, a, h, _ = futures.shape
        log = self.log if self.log is not None else context
        logged = log.states[:, :, now + 1 : now + 1 + h]
        logged_valid = log.valid[:, :, now + 1 : now + 1 + h]
        if logged.shape[2] < h:
            pad = h - logged.shape[2]
            logged = torch.nn.functional.pad(logged, (0, 0, 0, pad))
            logged_valid = torch.nn.functional.pad(logged_valid, (0, pad))
        controlled = context.controlled[:, None, :, None, None]
        states = torch.where(controlled, futures, logged[:, None].to(futures))  # (B, S, A, H, 4)
        valid = torch.where(context.controlled[:, :, None], torch.ones_like(logged_valid), logged_valid)  # (B, A, H)
        loss = torch.zeros(b, s, a, dtype=futures.dtype, device=futures.device)
        # Only pairs that can come within reach matter: prune with each agent's largest excursion from its first
        # planned position (exact: a pruned pair has zero penalty for every sample and step).
        present = valid.any(-1)
        first_xy = states[:, :, :, 0, :2]  # (B, S, A, 2)
        excursion = torch.linalg.vector_norm(states[..., :2] - first_xy[:, :, :, None], dim=-1).amax((1, 3))
        size = 0.5 * torch.linalg.vector_norm(context.extent, dim=-1)  # (B, A) half-diagonal covers every disk
        reach_ij = (excursion + size)[:, :, None] + (excursion + size)[:, None, :] + self.buffer_m
        gap = torch.linalg.vector_norm(first_xy[:, :, :, None] - first_xy[:, :, None, :], dim=-1).amin(1)  # (B,A,A)
        close = (gap <= reach_ij) & present[:, :, None] & present[:, None, :]
        close &= torch.ones(a, a, dtype=torch.bool, device=futures.device).triu(1)
        scene, i, j = close.nonzero(as_tuple=True)
        if scene.numel() == 0:
            return loss
        length, width = context.extent[..., 0], context.extent[..., 1]
        offsets = torch.linspace(-1.0, 1.0, self.num_disks, device=futures.device)

        def disk_centres(agent: torch.Tensor) -> torch.Tensor:  # (P, S, H, D, 2)
            st = states[scene, :, agent]  # (P, S, H, 4)
            along = (length[scene, agent] / 2 - width[scene, agent] / 2).clamp_min(0)[:, None, None, None] * offsets
            cos, sin = torch.cos(st[..., 3])[..., None], torch.sin(st[..., 3])[..., None]
            return torch.stack([st[..., 0:1] + along * cos, st[..., 1:2] + along * sin], -1)

        diff = disk_centres(i)[:, :, :, :, None] - disk_centres(j)[:, :, :, None, :]  # (P, S, H, D, D, 2)
        dist = torch.linalg.vector_norm(diff, dim=-1).amin((-1, -2))  # (P, S, H)
        reach = (width[scene, i] / 2 + width[scene, j] / 2 + self.buffer_m)[:, None, None]
        both = (valid[scene, i] & valid[scene, j])[:, None, :]  # (P, 1, H)
        penalty = torch.relu(1 - dist / reach) * both
        per_pair = (penalty * _time_weights(h, self.decay, futures.device)).sum(-1)  # (P, S)
        flat = loss.permute(0, 2, 1).reshape(b * a, s)  # (B*A, S)
        flat = flat.index_add(0, scene * a + i, per_pair).index_add(0, scene * a + j, per_pair)
        others = (present.sum(-1, keepdim=True) - 1).clamp_min(1)  # other agents of the scene
        return flat.reshape(b, a, s).permute(0, 2, 1) / others[:, None, :].to(futures)


class NoOffroadGuidance(Guidance):
    """Penalize box points off the drivable layer.

    Each of ``grid x grid`` points in the box costs its distance
    (m) to the nearest drivable pixel, read bilinearly from a distance map computed at ``fit``; steps weighted by
    ``decay**t``. (CTG uses 1 - distance/diagonal on points of partly off-road boxes; a metric distance gives a
    gradient everywhere off the road.)"""

    name = "no_offroad"

    def __init__(self, weight: float = 1.0, grid: int = 3, decay: float = 0.9) -> None:
        super().__init__(weight)
        self.grid, self.decay = grid, decay

    def fit(self, scenario: ScenarioTensor) -> Guidance:
        """Distance (m) from every off-road pixel to the drivable area, per scene."""
        super().fit(scenario)
        from scipy.ndimage import distance_transform_edt

        if scenario.map is None:
            raise ValueError("no_offroad guidance needs a map; the scenario has `map=None`.")
        drivable = scenario.map.layer("drivable").cpu().numpy()
        scale = float(scenario.map.world_to_pixel[0, 0, 0].abs())
        maps = [torch.from_numpy(distance_transform_edt(~d)).float() / scale if d.any() else torch.zeros(d.shape)
                for d in drivable]
        self.distance = torch.stack(maps).to(scenario.device)  # (B, H, W) metres
        return self

    def loss(self, futures: torch.Tensor, now: int, context: ScenarioTensor) -> torch.Tensor:
        """``(B, S, A)`` weighted mean off-road distance of the box points (m)."""
        b, s, a, h, _ = futures.shape
        u = torch.linspace(-0.5, 0.5, self.grid, device=futures.device)
        grid = torch.stack(torch.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)  # (G, 2) fractions of (L, W)
        local = grid * context.extent[:, None, :, None, None, :]  # (B, 1, A, 1, G, 2)
        cos, sin = torch.cos(futures[..., 3])[..., None], torch.sin(futures[..., 3])[..., None]
        px = futures[..., 0:1] + local[..., 0] * cos - local[..., 1] * sin
        py = futures[..., 1:2] + local[..., 0] * sin + local[..., 1] * cos
        ij = context.map.to_pixel(torch.stack([px, py], -1).reshape(b, -1, 2))  # type: ignore[union-attr]
        height, width = self.distance.shape[-2:]
        # grid_sample wants (x=col, y=row) in [-1, 1]; pixel centres sit at index + 0.5
        norm = torch.stack([(ij[..., 1]) / width * 2 - 1, (ij[..., 0]) / height * 2 - 1], -1)
        values = torch.nn.functional.grid_sample(
            self.distance[:, None], norm[:, None], mode="bilinear", padding_mode="border", align_corners=False
        ).reshape(b, s, a, h, -1)
        weights = _time_weights(h, self.decay, futures.device)
        return (values.mean(-1) * weights).sum(-1)


class GoalWaypointGuidance(Guidance):
    """Reach the logged position at ``target_time_s`` after the start (or the last logged position).

    Loss: when the goal is within reach of the horizon at the preferred speed, the closest planned distance to
    it; otherwise the shortfall of progress towards it: ``relu(min(reach, d_now) - (d_now - d_end))``.
    Objective: mean over agents of the minimum distance to the goal over the rollout (CTG's metric).
    """

    name = "goal_waypoint"

    def __init__(self, weight: float = 1.0, target_time_s: float = 7.5) -> None:
        super().__init__(weight)
        self.target_time_s = target_time_s

    def fit(self, scenario: ScenarioTensor) -> Guidance:
        """Goal ``(B, A, 2)`` and preferred speed ``(B, A)`` from the log."""
        super().fit(scenario)
        start = scenario.current_index
        target = min(start + round(self.target_time_s / scenario.dt), scenario.num_steps - 1)
        steps = torch.arange(scenario.num_steps, device=scenario.device)
        usable = scenario.valid & (steps > start) & (steps <= target)
        last = torch.where(usable, steps, torch.full_like(steps, -1)).amax(-1)  # (B, A)
        self.goal_valid = last >= 0
        idx = last.clamp_min(0)[..., None, None].expand(-1, -1, 1, 2)
        self.goal = scenario.xy.gather(2, idx)[:, :, 0]
        speeds = scenario.speed.abs() * usable
        self.pref_speed = (speeds.sum(-1) / usable.sum(-1).clamp_min(1)).clamp_min(1.0)
        return self

    def loss(self, futures: torch.Tensor, now: int, context: ScenarioTensor) -> torch.Tensor:
        """``(B, S, A)`` distance-to-goal or progress shortfall (m)."""
        goal = self.goal[:, None, :, None, :].to(futures)
        dist = torch.linalg.vector_norm(futures[..., :2] - goal, dim=-1)  # (B, S, A, H)
        d_now = torch.linalg.vector_norm(context.xy[:, :, now] - self.goal.to(futures), dim=-1)[:, None]
        reach = futures.shape[-2] * context.dt * self.pref_speed[:, None].to(futures)
        softmin = (torch.softmax(-dist, -1) * dist).sum(-1)
        progress = torch.relu(torch.minimum(reach, d_now) - (d_now - dist[..., -1]))
        loss = torch.where(d_now <= reach, softmin, progress)
        return loss * self.goal_valid[:, None]

    def objective(self, simulated: ScenarioTensor, controlled: torch.Tensor, start: int, end: int) -> float:
        """Mean over controlled agents with a goal of the closest distance to it during the rollout (m)."""
        xy = simulated.xy[:, :, start + 1 : end + 1]
        dist = torch.linalg.vector_norm(xy - self.goal[:, :, None], dim=-1).amin(-1)
        mask = controlled & self.goal_valid
        return float(dist[mask].mean()) if mask.any() else float("nan")


GUIDANCE_CLASSES: dict[str, type[Guidance]] = {
    cls.name: cls
    for cls in (SpeedLimitGuidance, TargetSpeedGuidance, NoCollisionGuidance, NoOffroadGuidance, GoalWaypointGuidance)
}


def make_guidance(name: str, **options: float) -> Guidance:
    """A guidance by name (``speed_limit``, ``target_speed``, ``no_collision``, ``no_offroad``, ``goal_waypoint``)."""
    if name not in GUIDANCE_CLASSES:
        raise UnknownComponentError(f"Unknown guidance: {name!r}. Available: {sorted(GUIDANCE_CLASSES)}.")
    return GUIDANCE_CLASSES[name](**options)


class GuidanceSet:
    """A weighted sum of guidances: ``GuidanceSet.parse("no_collision:50,no_offroad")``."""

    def __init__(self, guidances: Sequence[Guidance]) -> None:
        self.guidances = list(guidances)

    @classmethod
    def parse(cls, spec: str | Sequence[str] | None) -> GuidanceSet | None:
        """Parse ``"name[:weight],..."``; None or "" gives None."""
        if not spec:
            return None
        parts = spec.split(",") if isinstance(spec, str) else list(spec)
        guidances = []
        for part in parts:
            name, _, weight = part.strip().partition(":")
            try:
                guidances.append(make_guidance(name, weight=float(weight) if weight else 1.0))
            except ValueError as exc:
                raise ValueError(f"guidance weight in {part!r} must be a number, e.g. 'no_collision:50'.") from exc
        return cls(guidances)

    @property
    def names(self) -> list[str]:
        """Names of the member guidances."""
        return [g.name for g in self.guidances]

    @property
    def scene_level(self) -> bool:
        """Whether any member needs scene-level sample selection."""
        return any(g.scene_level for g in self.guidances)

    def fit(self, scenario: ScenarioTensor) -> GuidanceSet:
        """Fit every member on the logged scenario."""
        for g in self.guidances:
            g.fit(scenario)
        return self

    def loss(self, futures: torch.Tensor, now: int, context: ScenarioTensor) -> torch.Tensor:
        """Weighted sum ``(B, S, A)``."""
        return sum(g.weight * g.loss(futures, now, context) for g in self.guidances)  # type: ignore[return-value]


def select_samples(loss: torch.Tensor, controlled: torch.Tensor, scene_level: bool) -> torch.Tensor:
    """Index ``(B, A)`` of the lowest-loss sample from ``loss (B, S, A)``: per agent, or one index per scene
    (summed over controlled agents) when ``scene_level``."""
    if scene_level:
        total = (loss * controlled[:, None]).sum(-1)  # (B, S)
        return total.argmin(1)[:, None].expand_as(controlled)
    return loss.argmin(1)


def perturb_with_guidance(
    mean: torch.Tensor, sigma: torch.Tensor | float, objective: torch.Tensor, step_size: float = 0.3
) -> torch.Tensor:
    """One guidance step on a denoising mean, as CTG does with one Adam step of lr 0.3 clipped to +-sigma.

    Adam's first step moves each coordinate by ``lr * sign(grad)``; that is what is applied here, clipped to the
    step's standard deviation. ``objective`` is a scalar built from ``mean`` (which must require grad).
    """
    (grad,) = torch.autograd.grad(objective, mean, allow_unused=True)
    if grad is None:
        return mean.detach()
    delta = -step_size * torch.sign(grad)
    if isinstance(sigma, torch.Tensor):
        delta = torch.maximum(torch.minimum(delta, sigma), -sigma)
    else:
        delta = delta.clamp(-sigma, sigma)
    return (mean + delta).detach()


def guidance_objectives(simulated: ScenarioTensor, logged: ScenarioTensor, controlled: torch.Tensor, start: int,
                        end: int) -> dict[str, float]:
    """The guidance metrics of a rollout: speed-limit violation (m/s), target-speed error (m/s), goal distance (m)."""
    log = logged.replace_unchecked(current_index=start)
    values = {}
    for guidance in (SpeedLimitGuidance(), TargetSpeedGuidance(), GoalWaypointGuidance()):
        guidance.fit(log)
        values[f"guidance_{guidance.name}"] = guidance.objective(simulated, controlled, start, end)
    return values


@contextmanager
def guidance_swapped(policy: object, guidance: GuidanceSet | None) -> Iterator[None]:
    """Inside the block ``policy.guidance`` is ``guidance`` (left alone when ``guidance`` is None); the previous
    value is restored afterwards, also on error. For driving an adapter with a run's guidance instead of its own."""
    if guidance is None:
        yield
        return
    saved = getattr(policy, "guidance", None)
    policy.guidance = guidance  # type: ignore[attr-defined]
    try:
        yield
    finally:
        policy.guidance = saved  # type: ignore[attr-defined]
