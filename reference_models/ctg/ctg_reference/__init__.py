"""Compact CTG reference model (plain PyTorch in :mod:`ctg_reference.model`) and its training script."""

from ctg_reference.config import CTGConfig
from ctg_reference.model import CTGModel

__all__ = ["CTGConfig", "CTGModel"]
