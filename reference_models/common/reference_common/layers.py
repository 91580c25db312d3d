"""Network blocks the reference models share."""

from __future__ import annotations

from torch import nn

__all__ = ["mlp"]


def mlp(sizes: list[int]) -> nn.Sequential:
    """Linear layers with LayerNorm + Mish between them (none after the last): ``sizes[0]`` in, ``sizes[-1]`` out."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers += [nn.LayerNorm(sizes[i + 1]), nn.Mish()]
    return nn.Sequential(*layers)
