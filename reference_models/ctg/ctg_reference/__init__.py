"""Compact CTG reference model (plain PyTorch in :mod:`ctg_reference.model`) and its training script."""

from ctg_reference.model import CTGConfig, CTGModel

__all__ = ["CTGConfig", "CTGModel"]
