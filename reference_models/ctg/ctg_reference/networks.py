"""The compact CTG's networks: context encoder, temporal U-Net denoiser and scene-level mixer.

Plain PyTorch modules built from a :class:`~ctg_reference.config.CTGConfig`; :class:`~ctg_reference.model.CTGModel`
wires them into the diffusion model. Shapes are stated per module; all inputs are in the agent frame.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from reference_common.layers import Mish, mish, mlp
from torch import nn

if TYPE_CHECKING:
    from ctg_reference.config import CTGConfig

__all__ = ["CoDenoiseMixer", "ContextEncoder", "ResBlock1d", "SinusoidalEmbedding", "TemporalUNet", "mlp"]


# --------------------------------------------------------------------------------------------- encoder
class ContextEncoder(nn.Module):
    """Map crop CNN + history MLP + neighbour MLP/max-pool -> conditioning vector ``(N, cond_dim)``.

    Inputs (all in the agent frame):
        map ``(N, C, S, S)`` in {0, 1}; history ``(N, Th, 5)`` (x, y, speed, cos, sin of relative yaw) with
        ``history_valid (N, Th)``; extent ``(N, 2)`` (length, width); neighbours ``(N, K, 7)`` (x, y, cos, sin,
        speed, length, width) with ``neighbour_valid (N, K)``; optionally the neighbours' planned positions
        ``neighbour_plan (N, [S,] K, F, 2)`` (m) with ``neighbour_plan_valid (N, [S,] K, F)``, F =
        ``len(cfg.neighbour_plan_steps)``; with the sample axis S the output is ``(N, S, cond_dim)``.
    """

    def __init__(self, cfg: CTGConfig) -> None:
        super().__init__()
        c, w = cfg.map_channels, cfg.cnn_width
        self.cnn = nn.Sequential(
            nn.Conv2d(c, w, 3, stride=2, padding=1), nn.GroupNorm(4, w), Mish(),
            nn.Conv2d(w, 2 * w, 3, stride=2, padding=1), nn.GroupNorm(4, 2 * w), Mish(),
            nn.Conv2d(2 * w, 4 * w, 3, stride=2, padding=1), nn.GroupNorm(8, 4 * w), Mish(),
            nn.Conv2d(4 * w, 8 * w, 3, stride=2, padding=1), nn.GroupNorm(8, 8 * w), Mish(),
            nn.Flatten(),
        )
        with torch.no_grad():
            flat = self.cnn(torch.zeros(1, c, cfg.map_size, cfg.map_size)).shape[-1]
        self.map_head = nn.Sequential(nn.Linear(flat, cfg.map_dim), Mish())
        self.history = mlp([cfg.history_steps * 6 + 2, 128, 64])
        self.num_plan_steps = len(cfg.neighbour_plan_steps)
        self.neighbour = mlp([8 + 3 * self.num_plan_steps, 64, 64])
        self.fuse = mlp([cfg.map_dim + 64 + 64, 256, cfg.cond_dim])
        # fixed input scales (m, m/s): keep inputs O(1)
        self.register_buffer("history_scale", torch.tensor([10.0, 2.0, 10.0, 1.0, 1.0]), persistent=False)
        self.register_buffer("neighbour_scale", torch.tensor([20.0, 20.0, 1.0, 1.0, 10.0, 5.0, 2.0]),
                             persistent=False)

    def forward(self, map_crop: torch.Tensor, history: torch.Tensor, history_valid: torch.Tensor,
                extent: torch.Tensor, neighbours: torch.Tensor, neighbour_valid: torch.Tensor,
                neighbour_plan: torch.Tensor | None = None, neighbour_plan_valid: torch.Tensor | None = None
                ) -> torch.Tensor:
        """Conditioning ``(N, cond_dim)``, or ``(N, S, cond_dim)`` for a plan with a sample axis."""
        m, h = self.own(map_crop, history, history_valid, extent)
        return self.combine(m, h, neighbours, neighbour_valid, neighbour_plan, neighbour_plan_valid)

    def own(self, map_crop: torch.Tensor, history: torch.Tensor, history_valid: torch.Tensor, extent: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor]:
        """The parts that do not depend on the neighbours: map ``(N, map_dim)`` and history ``(N, 64)`` features
        (computed once when the neighbours' plans change between denoising steps)."""
        m = self.map_head(self.cnn(map_crop.float()))
        hv = history_valid.float()
        h = torch.cat([history / self.history_scale * hv[..., None], hv[..., None]], -1).flatten(1)
        return m, self.history(torch.cat([h, extent / 5.0], -1))

    def neighbour_input(self, neighbours: torch.Tensor, neighbour_valid: torch.Tensor) -> torch.Tensor:
        """Scaled neighbour features with their validity flag, ``(N, K, 8)``."""
        return torch.cat([neighbours / self.neighbour_scale, neighbour_valid.float()[..., None]], -1)

    def combine(self, m: torch.Tensor, h: torch.Tensor, neighbours: torch.Tensor, neighbour_valid: torch.Tensor,
                neighbour_plan: torch.Tensor | None = None, neighbour_plan_valid: torch.Tensor | None = None
                ) -> torch.Tensor:
        """Conditioning from :meth:`own`'s features and the neighbours (see :meth:`forward`)."""
        n_in = self.neighbour_input(neighbours, neighbour_valid)  # (N, K, 8)
        valid = neighbour_valid
        per_sample = neighbour_plan is not None and neighbour_plan.dim() == 5
        if self.num_plan_steps:
            n, k, f = neighbours.shape[0], neighbours.shape[1], self.num_plan_steps
            if neighbour_plan is None or neighbour_plan_valid is None:  # nobody's plan known
                neighbour_plan = neighbours.new_zeros(n, k, f, 2)
                neighbour_plan_valid = torch.zeros(n, k, f, dtype=torch.bool, device=neighbours.device)
            pv = neighbour_plan_valid.float()
            plan = torch.cat([neighbour_plan / 20.0 * pv[..., None], pv[..., None]], -1).flatten(-2)  # (.., K, 3F)
            if per_sample:
                n_in = n_in[:, None].expand(n, plan.shape[1], k, n_in.shape[-1])
                valid = valid[:, None].expand(n, plan.shape[1], k)
            n_in = torch.cat([n_in, plan], -1)
        nb = self.neighbour(n_in)  # (N, [S,] K, 64)
        nb = torch.where(valid[..., None], nb, torch.full_like(nb, -1e4)).amax(-2)
        nb = torch.where(valid.any(-1, keepdim=True), nb, torch.zeros_like(nb))
        if per_sample:
            m, h = (t[:, None].expand(t.shape[0], nb.shape[1], t.shape[-1]) for t in (m, h))
        return self.fuse(torch.cat([m, h, nb], -1))


# --------------------------------------------------------------------------------------------- denoiser
class SinusoidalEmbedding(nn.Module):
    """Sinusoidal embedding of the (integer) diffusion step."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        """``(N,)`` -> ``(N, dim)``."""
        half = self.dim // 2
        freq = torch.exp(-math.log(10000) * torch.arange(half, device=t.device, dtype=torch.float32) / (half - 1))
        arg = t.float()[:, None] * freq[None]
        return torch.cat([arg.sin(), arg.cos()], -1)


class ResBlock1d(nn.Module):
    """Two Conv1d + GroupNorm + Mish with the embedding added as a per-channel bias, plus a residual path."""

    def __init__(self, cin: int, cout: int, emb_dim: int, kernel: int, groups: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv1d(cin, cout, kernel, padding=kernel // 2)
        self.norm1 = nn.GroupNorm(groups, cout)
        self.conv2 = nn.Conv1d(cout, cout, kernel, padding=kernel // 2)
        self.norm2 = nn.GroupNorm(groups, cout)
        self.emb = nn.Sequential(Mish(), nn.Linear(emb_dim, cout))
        self.skip = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        """``(N, cin, L)`` -> ``(N, cout, L)``."""
        h = mish(self.norm1(self.conv1(x))) + self.emb(emb)[..., None]
        h = mish(self.norm2(self.conv2(h)))
        return h + self.skip(x)


class TemporalUNet(nn.Module):
    """1-D temporal U-Net with one down/up level over ``(N, 2, H)`` normalized actions."""

    def __init__(self, cfg: CTGConfig) -> None:
        super().__init__()
        d1, d2 = cfg.unet_dims
        k, g = cfg.kernel_size, cfg.groups
        self.time = nn.Sequential(SinusoidalEmbedding(cfg.time_dim), nn.Linear(cfg.time_dim, 64), Mish(),
                                  nn.Linear(64, cfg.time_dim))
        emb = cfg.time_dim + cfg.cond_dim
        self.down1 = ResBlock1d(2, d1, emb, k, g)
        self.down2 = ResBlock1d(d1, d1, emb, k, g)
        self.downsample = nn.Conv1d(d1, d1, 3, stride=2, padding=1)
        self.mid1 = ResBlock1d(d1, d2, emb, k, g)
        self.mid2 = ResBlock1d(d2, d2, emb, k, g)
        self.upsample = nn.ConvTranspose1d(d2, d2, 4, stride=2, padding=1)
        self.up1 = ResBlock1d(d2 + d1, d1, emb, k, g)
        self.up2 = ResBlock1d(d1, d1, emb, k, g)
        self.out = nn.Sequential(nn.Conv1d(d1, d1, k, padding=k // 2), nn.GroupNorm(g, d1), Mish(),
                                 nn.Conv1d(d1, 2, 1))

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """x ``(N, H, 2)``, t ``(N,)`` int, cond ``(N, cond_dim)`` -> x0 prediction ``(N, H, 2)``."""
        emb = torch.cat([self.time(t), cond], -1)
        h = x.transpose(1, 2)
        length = h.shape[-1]
        h = self.down2(self.down1(h, emb), emb)
        skip = h
        h = self.downsample(h)
        h = self.mid2(self.mid1(h, emb), emb)
        h = self.upsample(h)[..., :length]
        h = self.up2(self.up1(torch.cat([h, skip], 1), emb), emb)
        return self.out(h).transpose(1, 2)


# --------------------------------------------------------------------------------------------- scene-level denoising
class CoDenoiseMixer(nn.Module):
    """What an agent reads, at one denoising step, from the noisy samples of the neighbours denoised with it.

    Per neighbour: its noisy normalized actions ``(H, 2)`` (frame-free), its pose and size in the agent's frame
    (the encoder's neighbour input) and the noise level; an MLP, a max-pool over the co-denoised neighbours and a
    zero-initialized projection whose output is added to the conditioning vector (so an untrained mixer changes
    nothing).
    """

    def __init__(self, cfg: CTGConfig) -> None:
        super().__init__()
        self.steps = cfg.diffusion_steps
        self.net = mlp([cfg.horizon * 2 + 8 + 1, 128, 64])
        self.out = nn.Linear(64, cfg.cond_dim)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor, k: torch.Tensor | int, neighbour_in: torch.Tensor, neighbour_row: torch.Tensor
                ) -> torch.Tensor:
        """x ``(N, S, H, 2)`` every row's current noisy sample at step ``k`` (int or ``(N,)``), neighbour_in
        ``(N, K, 8)``, neighbour_row ``(N, K)`` long (the row denoised as that neighbour, -1: none) ->
        ``(N, S, cond_dim)``."""
        n, s = x.shape[:2]
        kk = neighbour_row.shape[1]
        known = neighbour_row >= 0
        picked = x[neighbour_row.clamp_min(0)].transpose(1, 2) * known[:, None, :, None, None]  # (N, S, K, H, 2)
        level = (torch.as_tensor(k, device=x.device, dtype=x.dtype) / self.steps).reshape(-1, 1, 1, 1)
        features = torch.cat([picked.flatten(-2), neighbour_in[:, None].expand(n, s, kk, 8),
                              level.expand(n, s, kk, 1)], -1)
        mixed = self.net(features)  # (N, S, K, 64)
        mixed = torch.where(known[:, None, :, None], mixed, torch.full_like(mixed, -1e4)).amax(-2)
        mixed = torch.where(known.any(-1)[:, None, None], mixed, torch.zeros_like(mixed))
        return self.out(mixed)

