"""Credit for models whose planner executes the best of K samples (BITS-style selection).

Such a planner draws K futures ``x_1..x_K`` iid from the model and executes the one with the highest score
``s(x)`` (a fixed function of the sample and the context). What the closed loop feels is then
``J = E[R(x_best)]``, not ``E[R(x)]``: PPO on single samples improves samples the planner rarely executes.
For a distribution over score classes, with ``H(t) = P(s <= t)`` and ``G(t) = P(s < t)``,
``J = sum_c R_c (H_c^K - G_c^K)`` and

    grad J = E_y[ grad log p(y) * A(y) ],
    A(y) = K * ( R(y) H(s_y)^(K-1) + sum_{classes c: s_c > s_y} R_c (H_c^(K-1) - G_c^(K-1)) )

for scores without ties (a tied class executes its members in proportion to their probability, which changes
the first term to ``K R_c H^(K-1) + (R(y) - R_c) (H^K - G^K) / P(class)``).

The first term is the sample's own reward, weighted by how likely it wins; the second is the value of drawing
``y`` as a competitor: it lowers the chance that better-scored samples win, which helps when they have low
rewards. :func:`best_of_k_returns` is the plug-in estimate of ``A`` from the S samples of one group (H and G are
the group's empirical CDFs). Shifting every reward by ``b`` shifts every ``A`` by the same ``K b`` (the terms'
weights sum to ``K``), so the reward's offset carries no credit; the function centres the rewards of each group
first. With ``K = 1``, ``A = R``.
"""

from __future__ import annotations

import torch

from trafficrlhf_sdk.errors import TrafficRLHFError

__all__ = ["best_of_k_returns"]


def best_of_k_returns(rewards: torch.Tensor, scores: torch.Tensor, k: int, dim: int = 1) -> torch.Tensor:
    """Per-sample returns whose policy gradient is that of the best-of-``k`` executed sample's reward.

    Args:
        rewards: rewards of the S samples of each group, e.g. ``(B, S)`` or ``(B, S, A)`` (group = all other
            dims). Only differences within a group matter.
        scores: the planner's selection scores, same shape (higher = executed first); ties are one class.
        k: how many samples the planner draws and selects from (>= 1).
        dim: the sample dimension S.

    Returns:
        ``A`` with the shape of ``rewards`` (see the module docstring); the rewards are centred per group first.
    """
    if rewards.shape != scores.shape:
        raise TrafficRLHFError(f"rewards {tuple(rewards.shape)} and scores {tuple(scores.shape)} must have the "
                               "same shape (one selection score per sample).")
    if k < 1:
        raise TrafficRLHFError(f"k is {k}; the planner selects among k >= 1 samples.")
    if not torch.isfinite(scores).all():
        raise TrafficRLHFError("selection scores contain NaN or infinity; the adapter's `selection_scores` must "
                               "return finite values for every sample.")
    r = rewards.movedim(dim, -1)
    s = scores.movedim(dim, -1).to(r.dtype)
    r = r - r.mean(-1, keepdim=True)
    if k == 1:
        return r.movedim(-1, dim)
    # pairwise[..., i, j] compares sample j with sample i
    below = (s[..., None, :] < s[..., :, None]).to(r.dtype)
    same = (s[..., None, :] == s[..., :, None]).to(r.dtype)
    g = below.mean(-1)  # G(s_i): share of the group's samples scored strictly below i
    share = same.mean(-1)  # P(class of i)
    h = g + share  # H(s_i)
    class_reward = (same * r[..., None, :]).sum(-1) / same.sum(-1)  # R_c of i's class
    # each class's term R_c (H^(K-1) - G^(K-1)), spread evenly over its members
    per_member = class_reward * (h.pow(k - 1) - g.pow(k - 1)) / same.sum(-1)
    above = below.transpose(-1, -2)  # above[..., i, j]: sample j scored strictly above i
    # within a tied class the executed member is drawn by probability: a member's own reward then counts with
    # (H^K - G^K) / P(class), the class's mean reward with the rest of K H^(K-1)
    win = (h.pow(k) - g.pow(k)) / share
    own = k * class_reward * h.pow(k - 1) + (r - class_reward) * win
    returns = own + k * (above * per_member[..., None, :]).sum(-1)
    return returns.movedim(-1, dim)
