"""What the compact reference models share: their Mish and MLP block (:mod:`reference_common.layers`) and their training
loop (:mod:`reference_common.training`). Plain PyTorch; no SDK import."""

from reference_common.layers import Mish, mish, mlp
from reference_common.training import cosine_rate, fit, take_rows

__all__ = ["Mish", "cosine_rate", "fit", "mish", "mlp", "take_rows"]
