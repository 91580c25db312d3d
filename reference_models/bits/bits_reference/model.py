"""A compact BITS (Xu et al. 2023, "BITS: Bi-level Imitation for Traffic Simulation") in plain PyTorch.

This module knows nothing of the TrafficRLHF SDK: it takes per-agent tensors and returns per-agent tensors.
Facts about the upstream model are from ``shared/reference/upstream-models-and-metrics.md`` §2.1-2.4; the
code is written from that description, sized for CPU training.

* :class:`SpatialGoalNet` (the part TrafficRLHF fine-tunes): a small U-Net over an agent-centric map crop
  (``map_channels`` semantic layers + two coordinate channels + a "where constant turn rate and velocity would
  be at the horizon" prior channel), with the agent's history, box and neighbours injected by FiLM at the
  bottleneck and as per-channel biases in the decoder. Output at crop resolution: 4 channels
  ``[location logit, row offset, column offset, yaw]``. The goal distribution is a categorical over the
  ``S x S`` cells (masked to drivable cells at sampling time); offsets pass through a sigmoid (sub-cell
  position in [0, 1]); yaw is the goal heading relative to the agent's current heading.
* :class:`GoalConditionedPolicy` (frozen in TrafficRLHF): its own small encoder of the same inputs plus the
  goal ``(x, y, cos yaw, sin yaw)`` -> an MLP -> ``horizon x (acceleration, yaw rate)``, rolled out through the
  unicycle from ``(0, 0, v0, 0)``. Deterministic given the goal. Trained on ground-truth goals.
* :func:`selection_score`: BITS's choice among sampled goals (tbsim ``ego_sample_planning`` weights
  ``0.01 * progress - 15 * collision - 1 * drivable``).

Agent frame: origin at the agent's current position, x along its current heading, y to the left. Crop cell
``(u, v)`` (u along rows = ahead, v along columns = left) covers agent-frame x in
``[(u - behind) * res, (u + 1 - behind) * res)`` and y in ``[(v - S/2) * res, (v + 1 - S/2) * res)`` where
``behind = behind_fraction * S``. One unicycle step of ``dt``::

    x' = x + dt cos(yaw) (v + a dt / 2),  y' = y + dt sin(yaw) (v + a dt / 2),  v' = v + a dt,  yaw' = yaw + w dt
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from reference_common.layers import mlp
from torch import nn

__all__ = [
    "BITSConfig",
    "BITSModel",
    "GoalConditionedPolicy",
    "GoalOutput",
    "SpatialGoalNet",
    "selection_score",
    "unicycle_from_origin",
]


@dataclass
class BITSConfig:
    """Architecture, crop geometry and normalization (JSON-serializable via :meth:`to_dict`)."""

    horizon: int = 20  # policy steps (tbsim future_num_frames = 20 -> 2 s at 0.1 s); the goal is the state at H
    dt: float = 0.1
    map_channels: int = 3
    map_size: int = 32  # crop side S (cells)
    resolution_m: float = 1.5  # cell size (m): 48 m x 48 m
    behind_fraction: float = 0.125  # share of the crop behind the agent (6 m of 48 m)
    history_steps: int = 10  # 1 s of history at 0.1 s
    num_neighbours: int = 8
    cond_dim: int = 64
    unet_dims: tuple[int, int, int, int] = (12, 24, 48, 64)
    prior_sigma_m: float = 2.0  # base width of the constant-turn-rate prior channel
    policy_hidden: int = 256
    # loss weights of the goal network (upstream: pixel CE 1, residual MSE 1, yaw MSE 1)
    pixel_weight: float = 1.0
    offset_weight: float = 1.0
    yaw_weight: float = 1.0
    # normalization of the policy's actions / states (filled from data by the training script)
    action_std: list[float] = field(default_factory=lambda: [1.0, 0.1])
    state_std: list[float] = field(default_factory=lambda: [6.0, 0.6, 4.0, 0.1])

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (tuples as lists)."""
        d = asdict(self)
        d["unet_dims"] = list(self.unet_dims)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BITSConfig:
        """Inverse of :meth:`to_dict` (unknown keys are an error)."""
        d = dict(d)
        if "unet_dims" in d:
            d["unet_dims"] = tuple(d["unet_dims"])
        return cls(**d)

    @property
    def behind_cells(self) -> float:
        """Cells behind the agent along u."""
        return self.behind_fraction * self.map_size


# --------------------------------------------------------------------------------------------- utilities
def unicycle_from_origin(actions: torch.Tensor, v0: torch.Tensor, dt: float) -> torch.Tensor:
    """Unicycle rollout (no bounds) from ``(0, 0, v0, 0)``: actions ``(..., H, 2)``, ``v0 (...)`` ->
    agent-frame states ``(..., H, 4)`` (yaw not wrapped; it stays small over 2 s)."""
    acc, yaw_rate = actions.unbind(-1)
    v0 = v0[..., None]
    v = v0 + dt * torch.cumsum(acc, -1)
    yaw = dt * torch.cumsum(yaw_rate, -1)
    v_before = torch.cat([v0, v[..., :-1]], -1)
    yaw_before = torch.cat([torch.zeros_like(v0), yaw[..., :-1]], -1)
    travel = dt * (v_before + 0.5 * dt * acc)
    return torch.stack([torch.cumsum(travel * torch.cos(yaw_before), -1),
                        torch.cumsum(travel * torch.sin(yaw_before), -1), v, yaw], -1)


def yaw_rate_estimate(history: torch.Tensor, history_valid: torch.Tensor, dt: float, lag: int = 5) -> torch.Tensor:
    """Recent yaw rate ``(N,)`` (rad/s) from the relative yaw ``lag`` steps ago in ``history (N, Th, 5)``
    (x, y, speed, cos, sin of the yaw relative to now); 0 where that step is invalid."""
    idx = max(history.shape[1] - 1 - lag, 0)
    past = torch.atan2(history[:, idx, 4], history[:, idx, 3])  # yaw(then) - yaw(now)
    steps = history.shape[1] - 1 - idx
    return torch.where(history_valid[:, idx], -past / max(steps * dt, dt), torch.zeros_like(past))


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.GroupNorm(4, cout), nn.Mish())


class AgentEncoder(nn.Module):
    """History MLP + neighbour MLP/max-pool (+ box size) -> ``(N, out_dim)``.

    Inputs (agent frame): history ``(N, Th, 5)`` (x, y, speed, cos, sin of relative yaw) with ``history_valid
    (N, Th)``; extent ``(N, 2)`` (length, width); neighbours ``(N, K, 7)`` (x, y, cos, sin, speed, length,
    width) with ``neighbour_valid (N, K)``.
    """

    def __init__(self, history_steps: int, out_dim: int) -> None:
        super().__init__()
        self.history = mlp([history_steps * 6 + 2, 128, out_dim])
        self.neighbour = mlp([8, 64, out_dim])
        self.fuse = mlp([2 * out_dim, 128, out_dim])
        self.register_buffer("history_scale", torch.tensor([10.0, 2.0, 10.0, 1.0, 1.0]), persistent=False)
        self.register_buffer("neighbour_scale", torch.tensor([20.0, 20.0, 1.0, 1.0, 10.0, 5.0, 2.0]),
                             persistent=False)

    def forward(self, history: torch.Tensor, history_valid: torch.Tensor, extent: torch.Tensor,
                neighbours: torch.Tensor, neighbour_valid: torch.Tensor) -> torch.Tensor:
        """``(N, out_dim)``."""
        hv = history_valid.float()
        h = torch.cat([history / self.history_scale * hv[..., None], hv[..., None]], -1).flatten(1)
        h = self.history(torch.cat([h, extent / 5.0], -1))
        nv = neighbour_valid.float()
        n = self.neighbour(torch.cat([neighbours / self.neighbour_scale, nv[..., None]], -1))
        n = torch.where(neighbour_valid[..., None], n, torch.full_like(n, -1e4)).amax(1)
        n = torch.where(neighbour_valid.any(1, keepdim=True), n, torch.zeros_like(n))
        return self.fuse(torch.cat([h, n], -1))


# --------------------------------------------------------------------------------------------- goal network
class GoalOutput(NamedTuple):
    """Per-cell outputs of :class:`SpatialGoalNet` for ``N`` agents over ``S x S`` cells (flattened ``S*S``,
    row-major in (u, v))."""

    logits: torch.Tensor  # (N, S*S) location logits (unmasked)
    offset: torch.Tensor  # (N, S*S, 2) sub-cell position in [0, 1] along (u, v)
    yaw: torch.Tensor  # (N, S*S) goal yaw relative to the current heading (rad)


class SpatialGoalNet(nn.Module):
    """U-Net encoder-decoder over the crop, conditioned on the agent's state (FiLM + decoder biases)."""

    def __init__(self, cfg: BITSConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d0, d1, d2, d3 = cfg.unet_dims
        cin = cfg.map_channels + 3  # + coordinate channels (2) + motion prior (1)
        self.agent = AgentEncoder(cfg.history_steps, cfg.cond_dim)
        self.state = mlp([3, 32, cfg.cond_dim])  # speed, yaw-rate estimate, speed * horizon time
        self.enc0 = _conv(cin, d0)
        self.enc1 = nn.Sequential(_conv(d0, d1, 2), _conv(d1, d1))
        self.enc2 = nn.Sequential(_conv(d1, d2, 2), _conv(d2, d2))
        self.enc3 = nn.Sequential(_conv(d2, d3, 2), _conv(d3, d3))
        self.film = nn.Linear(cfg.cond_dim, 2 * d3)
        self.dec2 = _conv(d3 + d2, d2)
        self.dec1 = _conv(d2 + d1, d1)
        self.dec0 = _conv(d1 + d0, d0)
        self.bias2 = nn.Linear(cfg.cond_dim, d2)
        self.bias1 = nn.Linear(cfg.cond_dim, d1)
        self.bias0 = nn.Linear(cfg.cond_dim, d0)
        self.head = nn.Conv2d(d0, 4, 1)
        s, res = cfg.map_size, cfg.resolution_m
        cells = torch.arange(s, dtype=torch.float32) + 0.5
        x = (cells - cfg.behind_cells) * res
        y = (cells - s / 2) * res
        grid = torch.stack(torch.meshgrid(x, y, indexing="ij"), 0)  # (2, S, S) agent-frame cell centres (m)
        self.register_buffer("cell_xy", grid, persistent=False)

    def motion_prior(self, v0: torch.Tensor, w0: torch.Tensor) -> torch.Tensor:
        """``(N, 1, S, S)`` Gaussian bump at the point a constant speed and yaw rate reach at the horizon."""
        t = self.cfg.horizon * self.cfg.dt
        w = w0.clamp(-1.0, 1.0)
        small = w.abs() < 1e-3
        w_safe = torch.where(small, torch.ones_like(w), w)
        x = torch.where(small, v0 * t, v0 / w_safe * torch.sin(w_safe * t))
        y = torch.where(small, 0.5 * v0 * w * t * t, v0 / w_safe * (1 - torch.cos(w_safe * t)))
        sigma = self.cfg.prior_sigma_m + 0.1 * v0.abs() * t
        d2 = (self.cell_xy[0] - x[:, None, None]) ** 2 + (self.cell_xy[1] - y[:, None, None]) ** 2
        return torch.exp(-0.5 * d2 / sigma[:, None, None] ** 2)[:, None]

    def forward(self, features: dict[str, torch.Tensor]) -> GoalOutput:
        """Goal outputs for a feature dict (keys: map, history, history_valid, extent, neighbours,
        neighbour_valid, v0)."""
        cfg = self.cfg
        history, history_valid, v0 = features["history"], features["history_valid"], features["v0"]
        n = v0.shape[0]
        w0 = yaw_rate_estimate(history, history_valid, cfg.dt)
        cond = self.agent(history, history_valid, features["extent"], features["neighbours"],
                          features["neighbour_valid"])
        cond = cond + self.state(torch.stack([v0 / 10.0, w0 * 5.0, v0 * cfg.horizon * cfg.dt / 20.0], -1))
        coords = (self.cell_xy / (cfg.map_size * cfg.resolution_m / 2))[None].expand(n, -1, -1, -1)
        x = torch.cat([features["map"].float(), coords, self.motion_prior(v0, w0)], 1)
        e0 = self.enc0(x)
        e1 = self.enc1(e0)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        scale, shift = self.film(cond).chunk(2, -1)
        e3 = e3 * (1 + scale[..., None, None]) + shift[..., None, None]
        up = lambda t, ref: F.interpolate(t, size=ref.shape[-2:], mode="nearest")  # noqa: E731
        d2 = self.dec2(torch.cat([up(e3, e2), e2], 1)) + self.bias2(cond)[..., None, None]
        d1 = self.dec1(torch.cat([up(d2, e1), e1], 1)) + self.bias1(cond)[..., None, None]
        d0 = self.dec0(torch.cat([up(d1, e0), e0], 1)) + self.bias0(cond)[..., None, None]
        out = self.head(d0).flatten(2)  # (N, 4, S*S)
        return GoalOutput(out[:, 0], torch.sigmoid(out[:, 1:3]).transpose(1, 2), out[:, 3])

    # ------------------------------------------------------------ cells <-> agent-frame goals
    def cell_of(self, goal_xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Cell index ``(N,)``, sub-cell offset ``(N, 2)`` and inside-the-crop flag ``(N,)`` of agent-frame
        points ``(N, 2)`` (m)."""
        cfg = self.cfg
        uv = torch.stack([goal_xy[:, 0] / cfg.resolution_m + cfg.behind_cells,
                          goal_xy[:, 1] / cfg.resolution_m + cfg.map_size / 2], -1)
        cell = torch.floor(uv)
        inside = ((cell >= 0) & (cell < cfg.map_size)).all(-1)
        cell = cell.clamp(0, cfg.map_size - 1)
        index = (cell[:, 0] * cfg.map_size + cell[:, 1]).long()
        return index, (uv - cell).clamp(0, 1), inside

    def goal_at(self, out: GoalOutput, index: torch.Tensor) -> torch.Tensor:
        """Agent-frame goals ``(N, S', 3)`` (x, y, yaw) of cells ``index (N, S')`` with the predicted offsets."""
        cfg = self.cfg
        offset = out.offset.gather(1, index[..., None].expand(-1, -1, 2))  # (N, S', 2)
        u = torch.div(index, cfg.map_size, rounding_mode="floor").float()
        v = (index % cfg.map_size).float()
        x = (u + offset[..., 0] - cfg.behind_cells) * cfg.resolution_m
        y = (v + offset[..., 1] - cfg.map_size / 2) * cfg.resolution_m
        return torch.stack([x, y, out.yaw.gather(1, index)], -1)

    def loss(self, out: GoalOutput, goal: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Upstream supervision on ground-truth agent-frame goals ``(N, 3)``: pixel cross-entropy over all cells,
        sub-cell offset MSE and yaw MSE at the true cell. Goals outside the crop are left out."""
        index, offset, inside = self.cell_of(goal[:, :2])
        if not inside.any():
            zero = out.logits.sum() * 0.0
            return zero, {"pixel": zero.detach(), "offset": zero.detach(), "yaw": zero.detach()}
        logits, index, offset = out.logits[inside], index[inside], offset[inside]
        pixel = F.cross_entropy(logits, index)
        pred_offset = out.offset[inside].gather(1, index[:, None, None].expand(-1, 1, 2))[:, 0]
        offset_loss = F.mse_loss(pred_offset, offset)
        yaw_err = out.yaw[inside].gather(1, index[:, None])[:, 0] - goal[inside, 2]
        yaw_loss = torch.atan2(torch.sin(yaw_err), torch.cos(yaw_err)).pow(2).mean()
        cfg = self.cfg
        total = cfg.pixel_weight * pixel + cfg.offset_weight * offset_loss + cfg.yaw_weight * yaw_loss
        return total, {"pixel": pixel.detach(), "offset": offset_loss.detach(), "yaw": yaw_loss.detach()}


# --------------------------------------------------------------------------------------------- policy
class GoalConditionedPolicy(nn.Module):
    """Own encoder (map CNN, history/neighbour MLPs) + goal MLP -> ``horizon`` normalized actions (one shot)."""

    def __init__(self, cfg: BITSConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.agent = AgentEncoder(cfg.history_steps, 64)
        self.cnn = nn.Sequential(
            nn.Conv2d(cfg.map_channels, 8, 3, stride=2, padding=1), nn.Mish(),
            nn.Conv2d(8, 16, 3, stride=2, padding=1), nn.Mish(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.Mish(),
            nn.AdaptiveAvgPool2d(3), nn.Flatten(), nn.Linear(32 * 9, 64), nn.Mish(),
        )
        self.goal = mlp([5, 32, 32])
        h = cfg.policy_hidden
        self.decoder = mlp([64 + 64 + 32 + 1, h, h, cfg.horizon * 2])
        self.register_buffer("action_std", torch.tensor(cfg.action_std, dtype=torch.float32))
        self.register_buffer("state_std", torch.tensor(cfg.state_std, dtype=torch.float32))

    def forward(self, features: dict[str, torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Physical actions ``(N, G, H, 2)`` for agent-frame goals ``goal (N, G, 3)`` (G goals per agent)."""
        n, g = goal.shape[:2]
        ctx = torch.cat([
            self.agent(features["history"], features["history_valid"], features["extent"], features["neighbours"],
                       features["neighbour_valid"]),
            self.cnn(features["map"].float()),
            (features["v0"] / 10.0)[:, None],
        ], -1)
        goal_in = torch.stack([goal[..., 0] / 20.0, goal[..., 1] / 5.0, torch.cos(goal[..., 2]),
                               torch.sin(goal[..., 2]), goal[..., 0].abs().sqrt() / 5.0], -1)
        x = torch.cat([ctx[:, None].expand(n, g, ctx.shape[-1]), self.goal(goal_in)], -1)
        return self.decoder(x).reshape(n, g, self.cfg.horizon, 2) * self.action_std

    def rollout(self, features: dict[str, torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Agent-frame states ``(N, G, H, 4)`` reached by the policy's actions for goals ``(N, G, 3)``."""
        actions = self(features, goal)
        v0 = features["v0"][:, None].expand(actions.shape[:2])
        return unicycle_from_origin(actions, v0, self.cfg.dt)

    def loss(self, features: dict[str, torch.Tensor], actions: torch.Tensor, states: torch.Tensor
             ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Trajectory loss on ground-truth goals (the logged state at the horizon): normalized agent-frame state
        MSE + 0.1 x normalized action MSE + 0.001 x mean squared yaw rate (upstream's regularizer)."""
        goal = torch.stack([states[:, -1, 0], states[:, -1, 1], states[:, -1, 3]], -1)[:, None]
        pred_actions = self(features, goal)[:, 0]
        pred = unicycle_from_origin(pred_actions, features["v0"], self.cfg.dt)
        diff = pred - states
        diff = torch.cat([diff[..., :3], torch.atan2(torch.sin(diff[..., 3:]), torch.cos(diff[..., 3:]))], -1)
        state_loss = ((diff / self.state_std) ** 2).mean()
        action_loss = (((pred_actions - actions) / self.action_std) ** 2).mean()
        reg = pred_actions[..., 1].pow(2).mean()
        total = state_loss + 0.1 * action_loss + 0.001 * reg
        ade = torch.linalg.vector_norm(diff[..., :2], dim=-1).mean()
        return total, {"state": state_loss.detach(), "action": action_loss.detach(), "ade": ade.detach()}


# --------------------------------------------------------------------------------------------- the model
class BITSModel(nn.Module):
    """Spatial goal network + goal-conditioned policy."""

    def __init__(self, cfg: BITSConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg or BITSConfig()
        self.goal_net = SpatialGoalNet(self.cfg)
        self.policy = GoalConditionedPolicy(self.cfg)

    def set_normalization(self, action_std: torch.Tensor, state_std: torch.Tensor) -> None:
        """Set the policy's normalization statistics (buffers and config)."""
        self.policy.action_std.copy_(action_std)
        self.policy.state_std.copy_(state_std)
        self.cfg.action_std = [float(v) for v in action_std]
        self.cfg.state_std = [float(v) for v in state_std]

    @staticmethod
    def masked_log_probs(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Log-probabilities ``(N, S*S)`` of the cells under ``logits`` restricted to ``mask`` (bool, same
        shape); rows without any allowed cell are left unmasked. Masked cells get -inf."""
        mask = mask | ~mask.any(-1, keepdim=True)
        return torch.log_softmax(logits.masked_fill(~mask, float("-inf")), -1)

    def sample_goals(self, out: GoalOutput, mask: torch.Tensor, num_samples: int,
                     generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Sample ``num_samples`` cells per agent from the masked categorical: cells ``(N, S')`` and their
        log-probabilities ``(N, S')``."""
        log_p = self.masked_log_probs(out.logits, mask)
        at = generator.device if generator is not None else log_p.device  # a CPU generator draws on the CPU
        index = torch.multinomial(log_p.exp().to(at), num_samples, replacement=True, generator=generator)
        index = index.to(log_p.device)
        return index, log_p.gather(1, index)

    def mode_goals(self, out: GoalOutput, mask: torch.Tensor) -> torch.Tensor:
        """The most likely allowed cell ``(N, 1)`` ("BITS max")."""
        return self.masked_log_probs(out.logits, mask).argmax(-1, keepdim=True)


# --------------------------------------------------------------------------------------------- selection
def selection_score(progress: torch.Tensor, collision: torch.Tensor, drivable: torch.Tensor,
                    weights: tuple[float, float, float] = (0.01, 15.0, 1.0)) -> torch.Tensor:
    """BITS's planning score (higher is better): ``w_p * progress - w_c * collision - w_d * drivable``.

    Upstream (tbsim ``EvaluationConfig.policy.cost_weights``): progress 0.01, collision 15, drivable area 1
    (log-likelihood 0; the lane-direction term needs a vector map and is left out here).
    """
    return weights[0] * progress - weights[1] * collision - weights[2] * drivable


def disk_collision(candidates: torch.Tensor, others: torch.Tensor, extent: torch.Tensor, other_extent: torch.Tensor,
                   other_valid: torch.Tensor, num_disks: int = 2) -> torch.Tensor:
    """Collision term ``(N, S)`` in [0, 1] of candidate trajectories ``(N, S, H, 4)`` against other agents'
    predicted trajectories ``(N, K, H, 4)`` (same frame): each box is covered by ``num_disks`` disks of radius
    width/2 along its length; a pair at centre distance d costs ``relu(1 - d / (r_i + r_j))``; the worst other
    agent counts at each step, averaged over the steps. ``extent (N, 2)``, ``other_extent (N, K, 2)``,
    ``other_valid (N, K, H)``."""
    offsets = torch.linspace(-1.0, 1.0, num_disks, device=candidates.device)

    def centres(states: torch.Tensor, ext: torch.Tensor) -> torch.Tensor:
        along = (ext[..., 0] / 2 - ext[..., 1] / 2).clamp_min(0)[..., None, None] * offsets  # (..., 1, D)
        cos, sin = torch.cos(states[..., 3])[..., None], torch.sin(states[..., 3])[..., None]
        return torch.stack([states[..., 0:1] + along * cos, states[..., 1:2] + along * sin], -1)  # (..., H, D, 2)

    mine = centres(candidates, extent[:, None])  # (N, S, H, D, 2)
    theirs = centres(others, other_extent)  # (N, K, H, D, 2)
    diff = mine[:, :, None, :, :, None] - theirs[:, None, :, :, None, :]  # (N, S, K, H, D, D, 2)
    dist = torch.linalg.vector_norm(diff, dim=-1).amin((-1, -2))  # (N, S, K, H)
    reach = (extent[:, None, None, None, 1] + other_extent[:, None, :, None, 1]) / 2
    penalty = torch.relu(1 - dist / reach.clamp_min(0.1)) * other_valid[:, None]
    if penalty.shape[2] == 0:
        return penalty.new_zeros(penalty.shape[:2])
    return penalty.amax(2).mean(-1)
