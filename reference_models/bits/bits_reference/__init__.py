"""Compact BITS reference model (plain PyTorch in :mod:`bits_reference.model`) and its training script."""

from bits_reference.model import BITSConfig, BITSModel

__all__ = ["BITSConfig", "BITSModel"]
