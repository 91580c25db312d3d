"""Network blocks the reference models share."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["Mish", "mish", "mlp"]

# exp(20)^2 is far inside float32's range, and beyond x = 20 mish(x) rounds to x in float32 and float64 alike
_MISH_CLAMP = 20.0


def _mish_forward(x: torch.Tensor) -> torch.Tensor:
    """``x * tanh(softplus(x))`` written with one exponential: with ``e = exp(x)``, ``tanh(log(1 + e)) = n / (n + 2)``
    where ``n = e (e + 2)``."""
    e = x.clamp(max=_MISH_CLAMP).exp_()
    n = e.add(2.0).mul_(e)
    return n.div_(n + 2.0).mul_(x)


class _MishFunction(torch.autograd.Function):
    """Mish with the same one-exponential form in its derivative
    ``tanh(sp) + x (1 - tanh(sp)^2) sigmoid(x)``, ``1 - tanh(sp)^2 = 4 (n + 1) / (n + 2)^2``."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        return _mish_forward(x)

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        (x,) = ctx.saved_tensors  # type: ignore[attr-defined]
        e = x.clamp(max=_MISH_CLAMP).exp()
        n = e * (e + 2.0)
        d = n + 2.0
        tanh_sp = n / d
        sech2 = 4.0 * (n + 1.0) / (d * d)
        sigmoid = e / (e + 1.0)
        return grad * (tanh_sp + x * sech2 * sigmoid)


def mish(x: torch.Tensor) -> torch.Tensor:
    """Mish, ``x * tanh(softplus(x))``, for float32 / float64 with one exponential instead of the exp, log1p and tanh
    of ``torch.nn.functional.mish`` (which dominate the time of CTG's temporal U-Net on a CPU; see benchmarks/), as
    accurate as torch's kernel against a float64 evaluation; other dtypes use torch's kernel. Its last bits differ
    from torch's, so a network switched to it samples slightly different numbers."""
    if x.dtype not in (torch.float32, torch.float64):
        return F.mish(x)
    if torch.is_grad_enabled() and x.requires_grad:
        return _MishFunction.apply(x)  # type: ignore[no-any-return]
    return _mish_forward(x)


class Mish(nn.Module):
    """:func:`mish` as a module (no parameters: a drop-in for ``torch.nn.Mish`` in saved state dicts)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Elementwise mish of ``x``."""
        return mish(x)


def mlp(sizes: list[int]) -> nn.Sequential:
    """Linear layers with LayerNorm + Mish between them (none after the last): ``sizes[0]`` in, ``sizes[-1]`` out."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers += [nn.LayerNorm(sizes[i + 1]), nn.Mish()]
    return nn.Sequential(*layers)
