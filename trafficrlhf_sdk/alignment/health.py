"""The health figures of a PPO epoch and their typical ranges (docs/how-to/align.md, "Reading the training table").

- ``approx_kl``: how far one epoch's updates moved the policy from the one that drew the samples, averaged over
  the sampled steps. The committed recipes stay between 0.001 (CTG, steering head only) and about 0.15 (BITS).
  Far above, the samples no longer describe the policy being updated: lower ``learning_rate`` or set
  ``target_kl``.
- ``clip_fraction``: the share of sampled steps whose probability ratio left ``1 +- clip_range``, so that their
  gradient was cut. The committed recipes stay between 0.01 and about 0.45. Above one half, most of the batch no
  longer trains: lower ``learning_rate`` or the passes per epoch.

Values near 0 are healthy when the reward asks for little change; :func:`health_warnings` flags only the high
side.
"""

from __future__ import annotations

__all__ = ["HEALTH_RANGES", "health_warnings"]

HEALTH_RANGES: dict[str, tuple[float, float, str]] = {
    "approx_kl": (0.0, 0.2, "lower learning_rate or set target_kl (e.g. 0.05)"),
    "clip_fraction": (0.0, 0.5, "lower learning_rate or the PPO passes per epoch"),
}
"""Per figure: its typical low and high end over the committed recipes' epochs, and what to do above it."""


def health_warnings(stats: dict[str, float]) -> list[str]:
    """One line per health figure of an epoch's ``stats`` above its typical range (:data:`HEALTH_RANGES`)."""
    lines = []
    for key, (low, high, fix) in HEALTH_RANGES.items():
        value = stats.get(key)
        if value is not None and value > high:
            lines.append(f"epoch {int(stats.get('epoch', 0))}: {key} {value:.3g} is above its typical range "
                         f"{low:g}-{high:g} (docs/how-to/align.md, 'Reading the training table'); {fix}.")
    return lines
