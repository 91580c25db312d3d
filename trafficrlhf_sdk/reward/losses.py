"""Bradley–Terry preference loss with the options of TRL's reward trainer, and its metrics."""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["bradley_terry_loss", "preference_metrics"]


def bradley_terry_loss(chosen: torch.Tensor, rejected: torch.Tensor, labels: torch.Tensor | None = None,
                       margin: float | torch.Tensor = 0.0, center_rewards_coefficient: float | None = None,
                       logit_scale: float = 1.0) -> torch.Tensor:
    """Mean over pairs of ``-[p log σ(d) + (1 - p) log σ(-d)]`` with ``d = s * (r_w - r_l) - margin``.

    Args:
        chosen: rewards ``(P,)`` of the preferred scenarios (r(S_w)).
        rejected: rewards ``(P,)`` of the others (r(S_l)).
        labels: probability ``p`` that ``chosen`` is preferred, ``(P,)``; None means 1 (hard labels). 0.5 marks
            a tie: the loss then pulls the two rewards together from both sides alike.
        margin: subtracted from the scaled difference (a float or ``(P,)``); asks preferred scenarios to win
            by at least this much. For ``p < 1`` it is applied symmetrically: ``d = s (r_w - r_l) - (2p - 1) m``.
        center_rewards_coefficient: adds ``c * mean((r_w + r_l)^2)`` (Eisenstein et al. 2023), which keeps the
            rewards centred on 0 without changing the preferences; None or 0 turns it off.
        logit_scale: ``s``, the inverse temperature of the Bradley–Terry model; rewards in [-1, 1] give
            differences of at most 2, so ``s`` sets how confident the model can become.
    """
    if chosen.shape != rejected.shape:
        raise ValueError(f"`chosen` and `rejected` must have the same shape; got {tuple(chosen.shape)} and "
                         f"{tuple(rejected.shape)}.")
    p = torch.ones_like(chosen) if labels is None else labels.to(chosen.dtype)
    diff = logit_scale * (chosen - rejected) - (2 * p - 1) * margin
    loss = -(p * F.logsigmoid(diff) + (1 - p) * F.logsigmoid(-diff)).mean()
    if center_rewards_coefficient:
        loss = loss + center_rewards_coefficient * ((chosen + rejected) ** 2).mean()
    return loss


def preference_metrics(chosen: torch.Tensor, rejected: torch.Tensor,
                       labels: torch.Tensor | None = None) -> dict[str, float]:
    """Accuracy, mean margin and reward range over pairs (no gradient).

    ``accuracy``: share of pairs ranked as labeled (``r_w > r_l`` where ``p > 0.5``, ``r_w < r_l`` where
    ``p < 0.5``; an exact tie counts one half; pairs labeled 0.5 are left out). ``margin``: mean of ``r_w - r_l``.
    """
    with torch.no_grad():
        p = torch.ones_like(chosen) if labels is None else labels.to(chosen.dtype)
        sign = torch.sign(p - 0.5)
        decided = sign != 0
        diff = (chosen - rejected) * sign
        correct = (diff > 0).double() + 0.5 * (diff == 0).double()
        both = torch.cat([chosen, rejected]).double()
        n = int(decided.sum())
        return {
            "accuracy": float(correct[decided].mean()) if n else float("nan"),
            "margin": float((chosen - rejected).double().mean()) if len(chosen) else float("nan"),
            "mean_reward": float(both.mean()) if len(both) else float("nan"),
            "min_reward": float(both.min()) if len(both) else float("nan"),
            "max_reward": float(both.max()) if len(both) else float("nan"),
            "num_pairs": float(len(chosen)),
        }
