"""The compact TrafficGen network: a raster initializer and a multi-modal motion forecaster (plain PyTorch).

This module does not import the SDK; :mod:`trafficgen_reference.data` turns a ``ScenarioTensor`` into the
tensors used here. Facts about the upstream model (metadriverse/trafficgen) are in
``shared/reference/upstream-models-and-metrics.md`` §3; what differs here is said where it happens.

Frames: every input is expressed in one agent's frame (origin at the agent, x along its heading, y to its left).

* :class:`Initializer` ("where are the vehicles?"): a small U-Net over a map crop centred on a context agent
  (upstream's ``context_num=1``: the first logged agent) predicts, on a grid of ``cell_m`` cells, an occupancy
  logit and a K-component mixture of diagonal Gaussians over (sub-cell offset x/y, length, width, heading,
  speed) of the vehicle in that cell. Upstream predicts the same quantities per lane vector with GMMs.
* :class:`Forecaster` ("actuator"): history, neighbours and a map crop of one agent -> M modes, each a
  diagonal Gaussian over H (acceleration, yaw rate) actions, plus mode logits. The density over action
  sequences is the mixture ``p(a) = sum_m pi_m N(a; mu_m, sigma_m)``; upstream has deterministic modes only.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from reference_common.layers import mlp
from torch import nn

__all__ = [
    "ForecastOutput",
    "Forecaster",
    "Initializer",
    "TrafficGenConfig",
    "TrafficGenModel",
    "boxes_overlap",
    "unicycle_rollout",
    "wrap",
]

HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)
# Initializer mixture dimensions, in this order; heading is an angle (residuals are wrapped).
INIT_DIMS = ("dx", "dy", "length", "width", "heading", "speed")


@dataclass
class TrafficGenConfig:
    """Architecture of both parts (JSON-serializable via :meth:`to_dict`)."""

    # --- initializer
    init_crop_px: int = 80  # map crop side (pixels of init_crop_res_m), centred on the context agent
    init_crop_res_m: float = 1.0
    init_cell_px: int = 2  # one occupancy cell = init_cell_px x init_cell_px crop pixels (2 m)
    init_width: int = 16
    init_components: int = 4
    # --- forecaster
    horizon: int = 20
    dt: float = 0.1
    modes: int = 6
    history_steps: int = 10
    num_neighbours: int = 8
    map_channels: int = 3
    map_size: int = 40  # forecaster crop side (pixels of 1 m), a quarter behind the agent
    hidden: int = 256
    log_std_range: tuple[float, float] = (-3.0, 0.7)  # per-step action log-std, in action_std units
    position_loss_weight: float = 0.5
    road_head: bool = False  # a head that re-weights the modes from the drivable area along each mode's plan
    steer_head: bool = False  # a head that shifts each mode's mean actions from the drivable area along its plan
    # normalization (filled from data by the training script)
    action_mean: list[float] = field(default_factory=lambda: [0.0, 0.0])
    action_std: list[float] = field(default_factory=lambda: [1.0, 0.1])

    @property
    def init_cells(self) -> int:
        """Occupancy cells per side."""
        return self.init_crop_px // self.init_cell_px

    @property
    def init_cell_m(self) -> float:
        """Occupancy cell size (m)."""
        return self.init_cell_px * self.init_crop_res_m

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (tuples as lists)."""
        d = asdict(self)
        d["log_std_range"] = list(self.log_std_range)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrafficGenConfig:
        """Inverse of :meth:`to_dict` (unknown keys are an error)."""
        d = dict(d)
        if "log_std_range" in d:
            d["log_std_range"] = tuple(d["log_std_range"])
        return cls(**d)


# --------------------------------------------------------------------------------------------- utilities
def wrap(angle: torch.Tensor) -> torch.Tensor:
    """Wrap angles to [-pi, pi)."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


def unicycle_rollout(state0: torch.Tensor, actions: torch.Tensor, dt: float) -> torch.Tensor:
    """Roll ``state0 (..., 4)`` = (x, y, v, yaw) through ``actions (..., H, 2)`` = (acc, yaw rate).

    The SDK's unicycle step (tbsim's) without action bounds, except that the speed does not go below 0 (no
    reversing): ``v' = max(v + dt a, 0)``, travel ``dt (v + v') / 2`` along the old yaw, ``yaw' = yaw + dt w``.
    Returns ``(..., H, 4)`` with yaw wrapped.
    """
    x, y, v, yaw = state0.unbind(-1)
    out = []
    for t in range(actions.shape[-2]):
        acc, rate = actions[..., t, 0], actions[..., t, 1]
        v_next = (v + dt * acc).clamp_min(0.0)
        travel = 0.5 * dt * (v + v_next)
        x = x + travel * torch.cos(yaw)
        y = y + travel * torch.sin(yaw)
        v, yaw = v_next, yaw + dt * rate
        out.append(torch.stack([x, y, v, wrap(yaw)], -1))
    return torch.stack(out, -2)


def box_corners(box: torch.Tensor) -> torch.Tensor:
    """Corners ``(..., 4, 2)`` of boxes ``(..., 5)`` = (x, y, yaw, length, width)."""
    x, y, yaw, length, width = box.unbind(-1)
    c, s = torch.cos(yaw), torch.sin(yaw)
    lx = torch.tensor([0.5, 0.5, -0.5, -0.5], dtype=box.dtype, device=box.device)
    ly = torch.tensor([0.5, -0.5, -0.5, 0.5], dtype=box.dtype, device=box.device)
    dx, dy = lx * length[..., None], ly * width[..., None]
    return torch.stack([x[..., None] + c[..., None] * dx - s[..., None] * dy,
                        y[..., None] + s[..., None] * dx + c[..., None] * dy], -1)


def boxes_overlap(box: torch.Tensor, others: torch.Tensor) -> torch.Tensor:
    """Whether oriented box ``box (5,)`` intersects each of ``others (N, 5)`` (separating-axis test); ``(N,)``."""
    if others.shape[0] == 0:
        return torch.zeros(0, dtype=torch.bool)
    a = box_corners(box)[None].expand(others.shape[0], 4, 2)
    b = box_corners(others)
    yaws = torch.stack([box[2].expand(others.shape[0]), others[:, 2]], -1)  # (N, 2)
    axes = torch.cat([torch.stack([torch.cos(yaws), torch.sin(yaws)], -1),
                      torch.stack([-torch.sin(yaws), torch.cos(yaws)], -1)], 1)  # (N, 4, 2)
    pa = torch.einsum("nkd,npd->nkp", axes, a)  # (N, axes, corners)
    pb = torch.einsum("nkd,npd->nkp", axes, b)
    separated = (pa.amax(-1) < pb.amin(-1)) | (pb.amax(-1) < pa.amin(-1))
    return ~separated.any(-1)


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.GroupNorm(8, cout), nn.Mish())


# --------------------------------------------------------------------------------------------- initializer
class Initializer(nn.Module):
    """Occupancy + per-cell mixture over the vehicle state, from a map crop around a context agent.

    Input ``crop (N, C, S, S)`` in {0, 1} (S = ``init_crop_px``, the context agent at the centre, heading along
    rows) and ``context (N, 3)`` = (speed / 10, length / 5, width / 2) of the context agent. Output per cell of
    the ``(S / init_cell_px)^2`` grid: ``1 + K * 14`` raw channels (occupancy logit, K mixture logits, K x 7
    mean parameters, K x 6 log-std parameters).
    """

    # log-std bounds per INIT_DIMS entry (offsets in cell units, metres, radians, m/s)
    LOG_STD_RANGE = ((-4.0, -0.5), (-4.0, -0.5), (-3.0, 1.5), (-4.0, 0.0), (-4.0, 1.0), (-2.5, 2.0))

    def __init__(self, cfg: TrafficGenConfig) -> None:
        super().__init__()
        if cfg.init_cell_px != 2:
            raise ValueError(f"init_cell_px must be 2 (one stride-2 stage); got {cfg.init_cell_px}.")
        w, k = cfg.init_width, cfg.init_components
        self.cfg = cfg
        self.stem = nn.Sequential(_conv(cfg.map_channels + 3, w, 2), _conv(w, w))  # S/2: the cell grid
        self.down = nn.Sequential(_conv(w, 2 * w, 2), _conv(2 * w, 2 * w))  # S/4
        self.bottom = nn.Sequential(_conv(2 * w, 2 * w, 2), _conv(2 * w, 2 * w))  # S/8: wide context
        self.up1 = _conv(4 * w, 2 * w)
        self.up2 = _conv(3 * w, w)
        self.head = nn.Conv2d(w, 1 + 14 * k, 1)
        lo, hi = zip(*self.LOG_STD_RANGE)
        self.register_buffer("log_std_lo", torch.tensor(lo), persistent=False)
        self.register_buffer("log_std_hi", torch.tensor(hi), persistent=False)
        with torch.no_grad():  # start with a low occupancy prior (a few vehicles among ~1600 cells)
            self.head.bias[0] = -6.0

    def forward(self, crop: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """Raw head ``(N, G, G, 1 + 14K)`` over the cell grid (G = ``init_cells``)."""
        s = crop.shape[-1]
        x = torch.cat([crop.float(), context[:, :, None, None].expand(-1, -1, s, s)], 1)
        c1 = self.stem(x)
        c2 = self.down(c1)
        c3 = self.bottom(c2)
        u = self.up1(torch.cat([c2, F.interpolate(c3, size=c2.shape[-2:], mode="nearest")], 1))
        u = self.up2(torch.cat([c1, F.interpolate(u, size=c1.shape[-2:], mode="nearest")], 1))
        return self.head(u).permute(0, 2, 3, 1)

    def split(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Occupancy logit ``(...)``, mixture log-weights ``(..., K)``, means and log-stds ``(..., K, 6)``."""
        k = self.cfg.init_components
        occ, mix = raw[..., 0], F.log_softmax(raw[..., 1 : 1 + k], -1)
        m = raw[..., 1 + k : 1 + 8 * k].unflatten(-1, (k, 7))
        mean = torch.stack([
            0.5 * torch.tanh(m[..., 0]), 0.5 * torch.tanh(m[..., 1]),  # offset in the cell (cell units)
            4.5 + 2.0 * m[..., 2], 1.9 + 0.4 * m[..., 3],  # length, width (m)
            torch.atan2(m[..., 5], m[..., 4] + 1e-6),  # heading relative to the context agent (rad)
            5.0 + 5.0 * m[..., 6],  # speed (m/s)
        ], -1)
        s = raw[..., 1 + 8 * k :].unflatten(-1, (k, 6))
        log_std = self.log_std_lo + (self.log_std_hi - self.log_std_lo) * torch.sigmoid(s)
        return occ, mix, mean, log_std

    @staticmethod
    def mixture_log_prob(mix: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor, value: torch.Tensor
                         ) -> torch.Tensor:
        """Log-density of ``value (..., 6)`` under the mixture ``(..., K)`` / ``(..., K, 6)``; ``(...)``."""
        diff = value[..., None, :] - mean
        diff = torch.cat([diff[..., :4], wrap(diff[..., 4:5]), diff[..., 5:]], -1)
        z = diff * torch.exp(-log_std)
        comp = (-0.5 * z * z - log_std - HALF_LOG_2PI).sum(-1)
        return torch.logsumexp(mix + comp, -1)

    def cell_targets(self, agents: torch.Tensor,
                     valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Cell index ``(N, P)`` (row * G + col), inside-grid mask, and mixture targets ``(N, P, 6)`` for
        agents ``(N, P, 6)`` = (x, y, heading, speed, length, width) in the context frame."""
        g, cell = self.cfg.init_cells, self.cfg.init_cell_m
        u = agents[..., 0] / cell + g / 2
        v = agents[..., 1] / cell + g / 2
        iu, iv = torch.floor(u), torch.floor(v)
        inside = valid & (iu >= 0) & (iu < g) & (iv >= 0) & (iv < g)
        index = (iu.clamp(0, g - 1) * g + iv.clamp(0, g - 1)).long()
        target = torch.stack([u - iu - 0.5, v - iv - 0.5, agents[..., 4], agents[..., 5], agents[..., 2],
                              agents[..., 3]], -1)
        return index, inside, target

    def loss(self, crop: torch.Tensor, context: torch.Tensor, agents: torch.Tensor, valid: torch.Tensor
             ) -> tuple[torch.Tensor, dict[str, float]]:
        """Occupancy BCE over every cell (summed per scene, divided by the number of vehicles) + mixture NLL
        of each vehicle's state in its cell (mean). ``agents (N, P, 6)``, ``valid (N, P)``."""
        raw = self(crop, context)
        n, g = raw.shape[0], raw.shape[1]
        occ, mix, mean, log_std = self.split(raw.reshape(n, g * g, -1))
        index, inside, target = self.cell_targets(agents, valid)
        occupied = torch.zeros(n, g * g, device=raw.device)
        occupied.scatter_add_(1, index, inside.float())
        occupied = occupied.clamp_max(1.0)
        count = inside.sum().clamp_min(1)
        bce = F.binary_cross_entropy_with_logits(occ, occupied, reduction="sum") / count
        pick = lambda t: t.gather(1, index.reshape(n, -1, *([1] * (t.dim() - 2))).expand(-1, -1, *t.shape[2:]))  # noqa: E731
        nll = -self.mixture_log_prob(pick(mix), pick(mean), pick(log_std), target)
        nll = (nll * inside).sum() / count
        return bce + 0.2 * nll, {"bce": float(bce.detach()), "nll": float(nll.detach())}

    @torch.no_grad()
    def initialize(self, crop: torch.Tensor, context: torch.Tensor, context_box: torch.Tensor, num_agents: int,
                   generator: torch.Generator | None = None, candidates: int = 5, tries: int = 3) -> torch.Tensor:
        """Place up to ``num_agents`` vehicles around one context agent, one at a time (upstream's procedure).

        For each vehicle: draw a drivable, still-free cell with probability proportional to its occupancy; draw
        ``candidates`` states from the cell's mixture and keep the most likely; reject it if its box overlaps a
        placed box (or the context agent's ``context_box (5,)``) or its centre is off the drivable layer, and
        retry with a new cell (at most ``tries`` times); give up on that vehicle after that.

        Args:
            crop: ``(C, S, S)`` map crop of the context agent (channel 0 drivable).
            context: ``(3,)`` context-agent features as in :meth:`forward`.
            context_box: ``(5,)`` (x, y, yaw, length, width) of the context agent in its own frame.
            generator: source of all randomness (a fixed seed gives the same placement).

        Returns:
            ``(P, 6)`` placed vehicles (x, y, heading, speed, length, width) in the context frame, P <= num_agents.
        """
        cfg = self.cfg
        g, cell, px = cfg.init_cells, cfg.init_cell_m, cfg.init_cell_px
        s = crop.shape[-1]
        drivable = crop[0] > 0
        cell_drivable = drivable.reshape(g, px, g, px).all(-1).all(1).reshape(-1)  # every pixel of the cell
        occ, mix, mean, log_std = self.split(self(crop[None], context[None])[0].reshape(g * g, -1))
        weight = torch.sigmoid(occ) * cell_drivable
        boxes = [context_box.float()]
        placed: list[torch.Tensor] = []
        for _ in range(num_agents):
            for _ in range(tries):
                if weight.sum() <= 0:
                    return torch.stack(placed) if placed else torch.zeros(0, 6)
                c = int(torch.multinomial(weight, 1, generator=generator))
                comps = torch.multinomial(mix[c].exp(), candidates, replacement=True, generator=generator)
                noise = torch.randn(candidates, 6, generator=generator)
                draws = mean[c, comps] + log_std[c, comps].exp() * noise
                best = draws[self.mixture_log_prob(mix[c], mean[c], log_std[c], draws).argmax()]
                row, col = c // g, c % g
                x = (row - g / 2 + 0.5 + best[0].clamp(-0.5, 0.5)) * cell
                y = (col - g / 2 + 0.5 + best[1].clamp(-0.5, 0.5)) * cell
                length, width = best[2].clamp(2.5, 18.0), best[3].clamp(1.4, 3.2)
                state = torch.stack([x, y, wrap(best[4]), best[5].clamp_min(0.0), length, width])
                weight[c] = 0.0  # one vehicle per cell, and a rejected cell is not tried again
                i = math.floor(float(x) / cfg.init_crop_res_m + s / 2)
                j = math.floor(float(y) / cfg.init_crop_res_m + s / 2)
                on_road = 0 <= i < s and 0 <= j < s and bool(drivable[i, j])
                box = torch.stack([x, y, state[2], length, width])
                if on_road and not boxes_overlap(box, torch.stack(boxes)).any():
                    boxes.append(box)
                    placed.append(state)
                    break
        return torch.stack(placed) if placed else torch.zeros(0, 6)


# --------------------------------------------------------------------------------------------- forecaster
class ForecastOutput(NamedTuple):
    """Mode means ``(N, M, H, 2)`` and log-stds ``(N, M, H, 2)`` of (acc m/s^2, yaw rate rad/s), and mode
    log-probabilities ``(N, M)`` (log-softmax of the logits)."""

    mean: torch.Tensor
    log_std: torch.Tensor
    log_pi: torch.Tensor


class Forecaster(nn.Module):
    """Agent-centric encoder + M learned mode queries -> per-mode diagonal Gaussian over H actions + logits.

    Inputs (agent frame): map ``(N, C, S, S)``; history ``(N, Th, 5)`` (x, y, speed, cos, sin of relative yaw)
    with ``history_valid (N, Th)``; extent ``(N, 2)``; neighbours ``(N, K, 7)`` (x, y, cos, sin, speed, length,
    width) with ``neighbour_valid (N, K)``.

    Two optional heads (not upstream's; for fine-tuning) read :meth:`road_features` along each mode's mean plan:
    ``steer`` (``cfg.steer_head``) adds a shift to the mode's mean actions, ``road`` (``cfg.road_head``) to its
    logit. Both end in a zero layer, so a new head changes nothing until it is trained.
    """

    def __init__(self, cfg: TrafficGenConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c, h = cfg.map_channels, cfg.hidden
        self.cnn = nn.Sequential(_conv(c, 16, 2), _conv(16, 32, 2), _conv(32, 32, 2), nn.Flatten())
        with torch.no_grad():
            flat = self.cnn(torch.zeros(1, c, cfg.map_size, cfg.map_size)).shape[-1]
        self.map_head = nn.Sequential(nn.Linear(flat, 128), nn.Mish())
        self.history = mlp([cfg.history_steps * 6 + 2, 128, 64])
        self.neighbour = mlp([8, 64, 64])
        self.fuse = mlp([128 + 64 + 64, h, h])
        self.mode_query = nn.Parameter(torch.randn(cfg.modes, h) * 0.5)
        self.decoder = mlp([h, h, h, cfg.horizon * 4 + 1])
        self.register_buffer("history_scale", torch.tensor([10.0, 2.0, 10.0, 1.0, 1.0]), persistent=False)
        self.register_buffer("neighbour_scale", torch.tensor([20.0, 20.0, 1.0, 1.0, 10.0, 5.0, 2.0]),
                             persistent=False)
        if cfg.road_head:
            self.road = mlp([4 * (cfg.horizon // 5), 32, 1])
            nn.init.zeros_(self.road[-1].weight)
            nn.init.zeros_(self.road[-1].bias)
        if cfg.steer_head:
            self.steer = mlp([4 * (cfg.horizon // 5) + 1, 64, 2 * cfg.horizon])
            nn.init.zeros_(self.steer[-1].weight)
            nn.init.zeros_(self.steer[-1].bias)
        self.register_buffer("action_mean", torch.tensor(cfg.action_mean, dtype=torch.float32))
        self.register_buffer("action_std", torch.tensor(cfg.action_std, dtype=torch.float32))

    def encoder_modules(self) -> list[nn.Module]:
        """Modules of the scene encoder (a parameter group)."""
        return [self.cnn, self.map_head, self.history, self.neighbour, self.fuse]

    def decoder_parameters(self) -> list[nn.Parameter]:
        """Parameters of the mode decoder (mode queries + head)."""
        return [self.mode_query, *self.decoder.parameters()]

    def forward(self, f: dict[str, torch.Tensor]) -> ForecastOutput:
        """Decode every mode for the ``N`` rows of features ``f`` (keys as in the class docstring)."""
        cfg = self.cfg
        m = self.map_head(self.cnn(f["map"].float()))
        hv = f["history_valid"].float()
        hist = torch.cat([f["history"] / self.history_scale * hv[..., None], hv[..., None]], -1).flatten(1)
        hist = self.history(torch.cat([hist, f["extent"] / 5.0], -1))
        nv = f["neighbour_valid"]
        nb = self.neighbour(torch.cat([f["neighbours"] / self.neighbour_scale, nv[..., None].float()], -1))
        nb = torch.where(nv[..., None], nb, torch.full_like(nb, -1e4)).amax(1)
        nb = torch.where(nv.any(1, keepdim=True), nb, torch.zeros_like(nb))
        ctx = self.fuse(torch.cat([m, hist, nb], -1))  # (N, h)
        raw = self.decoder(ctx[:, None] + self.mode_query)  # (N, M, 4H + 1)
        h = cfg.horizon
        mean = self.action_mean + self.action_std * raw[..., : 2 * h].unflatten(-1, (h, 2))
        lo, hi = cfg.log_std_range
        log_std = self.action_std.log() + lo + (hi - lo) * torch.sigmoid(raw[..., 2 * h : 4 * h].unflatten(-1, (h, 2)))
        logits = raw[..., -1]
        if cfg.steer_head:
            n, m_ = mean.shape[:2]
            speed = (f["history"][:, -1, 2] / 10.0)[:, None, None].expand(n, m_, 1)
            shift = self.steer(torch.cat([self.road_features(f, mean.detach()), speed], -1))
            mean = mean + self.action_std * shift.unflatten(-1, (h, 2))
        if cfg.road_head:
            logits = logits + self.road(self.road_features(f, mean.detach()))[..., 0]
        return ForecastOutput(mean, log_std, F.log_softmax(logits, -1))

    def road_features(self, f: dict[str, torch.Tensor], mean: torch.Tensor) -> torch.Tensor:
        """``(N, M, 4K)``: the drivable layer of the map crop at every 5th step of each mode's mean plan (K
        points), on the plan and 1.5 m to either side, and whether each point lies inside the crop."""
        cfg = self.cfg
        n, m = mean.shape[:2]
        v0 = f["history"][:, -1, 2]
        start = torch.stack([torch.zeros_like(v0), torch.zeros_like(v0), v0, torch.zeros_like(v0)], -1)
        plan = unicycle_rollout(start[:, None].expand(n, m, 4), mean, cfg.dt)[:, :, 4::5]  # (N, M, K, 4)
        side = torch.stack([-torch.sin(plan[..., 3]), torch.cos(plan[..., 3])], -1) * 1.5
        probes = torch.stack([plan[..., :2], plan[..., :2] + side, plan[..., :2] - side], -2)  # (N, M, K, 3, 2)
        size = cfg.map_size
        u = torch.floor(probes[..., 0] + 0.25 * size).long()
        v = torch.floor(probes[..., 1] + size / 2).long()
        inside = (u >= 0) & (u < size) & (v >= 0) & (v < size)
        flat = (u.clamp(0, size - 1) * size + v.clamp(0, size - 1)).reshape(n, -1)
        drivable = f["map"][:, 0].float().reshape(n, -1).gather(1, flat).reshape(inside.shape) * inside
        return torch.cat([drivable.flatten(2), inside[..., 0].float()], -1)

    @staticmethod
    def log_density(out: ForecastOutput, mode: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """``log pi_m + log N(actions; mu_m, sigma_m)`` for ``mode (N, S)`` and ``actions (N, S, H, 2)``: the
        joint log-density of the (mode, action sequence) pair; ``(N, S)``."""
        idx = mode[..., None, None].expand(-1, -1, *out.mean.shape[-2:])
        mu, log_std = out.mean.gather(1, idx), out.log_std.gather(1, idx)
        z = (actions - mu) * torch.exp(-log_std)
        gauss = (-0.5 * z * z - log_std - HALF_LOG_2PI).sum((-1, -2))
        return out.log_pi.gather(1, mode) + gauss

    @staticmethod
    def mixture_log_density(out: ForecastOutput, actions: torch.Tensor) -> torch.Tensor:
        """Marginal ``log sum_m pi_m N(actions; mu_m, sigma_m)`` of ``actions (N, S, H, 2)``; ``(N, S)``."""
        z = (actions[:, :, None] - out.mean[:, None]) * torch.exp(-out.log_std[:, None])
        gauss = (-0.5 * z * z - out.log_std[:, None] - HALF_LOG_2PI).sum((-1, -2))  # (N, S, M)
        return torch.logsumexp(out.log_pi[:, None] + gauss, -1)

    @staticmethod
    def draw(out: ForecastOutput, uniform: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mode ``(N, S)`` by inverting the mode CDF at ``uniform (N, S)`` and actions ``(N, S, H, 2)`` =
        ``mu_m + sigma_m * noise``."""
        cdf = out.log_pi.exp().cumsum(-1)
        mode = torch.searchsorted(cdf.contiguous(), uniform.contiguous()).clamp_max(cdf.shape[-1] - 1)
        idx = mode[..., None, None].expand(-1, -1, *out.mean.shape[-2:])
        return mode, out.mean.gather(1, idx) + out.log_std.gather(1, idx).exp() * noise

    def loss(self, f: dict[str, torch.Tensor], actions: torch.Tensor, future_xy: torch.Tensor
             ) -> tuple[torch.Tensor, dict[str, float]]:
        """Winner-takes-all loss on logged ``actions (N, H, 2)`` with agent-frame positions ``future_xy (N, H, 2)``.

        The winner is the mode whose mean actions, rolled out from the current speed, have the lowest average
        displacement error (upstream picks by endpoint error). Loss = CE(logits, winner) + Gaussian NLL per step
        of the logged actions under the winner + ``position_loss_weight`` * Huber error of its rolled-out
        positions (m).
        """
        out = self(f)
        n, m = out.mean.shape[:2]
        v0 = f["history"][:, -1, 2]
        start = torch.stack([torch.zeros_like(v0), torch.zeros_like(v0), v0, torch.zeros_like(v0)], -1)
        xy = unicycle_rollout(start[:, None].expand(n, m, 4), out.mean, self.cfg.dt)[..., :2]  # (N, M, H, 2)
        ade = torch.linalg.vector_norm(xy - future_xy[:, None], dim=-1).mean(-1)
        best = ade.detach().argmin(-1)
        ce = F.nll_loss(out.log_pi, best)
        h = actions.shape[1]
        log_density = self.log_density(out, best[:, None], actions[:, None])[:, 0]
        nll = -(log_density - out.log_pi.gather(1, best[:, None])[:, 0])
        nll = nll.mean() / h
        pos = F.huber_loss(xy[torch.arange(n), best], future_xy, delta=1.0)
        loss = ce + nll + self.cfg.position_loss_weight * pos
        return loss, {"ce": float(ce.detach()), "nll_per_step": float(nll.detach()), "pos": float(pos.detach()),
                      "min_ade": float(ade.detach().amin(-1).mean()),
                      "top1_ade": float(ade.detach().gather(1, out.log_pi.argmax(-1, keepdim=True)).mean())}


class TrafficGenModel(nn.Module):
    """Both parts in one module (one checkpoint): ``initializer`` (kept frozen) and ``forecaster``."""

    def __init__(self, cfg: TrafficGenConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.initializer = Initializer(cfg)
        self.forecaster = Forecaster(cfg)
